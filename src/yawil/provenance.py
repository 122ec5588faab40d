"""What made an artefact: the yawil version, the git commit it ran from, the command line and the date (UTC).

Reports, and anything else written for others to read, say where they came from, so a figure can be traced
to the code and the command that produced it.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path

__all__ = ["command_line", "git_commit", "provenance", "provenance_markdown"]


def git_commit(package_dir: str | Path | None = None) -> str:
    """The commit of the git checkout this package runs from ('-dirty' after it if tracked files differ), else
    'unknown' (an installed package, no git, or the package's files not tracked by the repository around it).

    `package_dir` (default: yawil's own folder) must hold a tracked __init__.py."""
    pkg = Path(package_dir) if package_dir is not None else Path(__file__).resolve().parent  # src/yawil
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}  # this checkout, not a caller's

    def git(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["git", "-C", str(pkg), *args], capture_output=True, text=True, timeout=20, env=env)

    try:
        if git("ls-files", "--error-unmatch", "__init__.py").returncode != 0:
            return "unknown"  # e.g. a copy in a virtual environment inside some repository
        head = git("rev-parse", "HEAD")
        if head.returncode != 0 or not head.stdout.strip():
            return "unknown"
        status = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head.stdout.strip() + ("-dirty" if status.returncode == 0 and status.stdout.strip() else "")


def command_line() -> str:
    """The command that runs: `yawil ...` when started as the yawil script, else the process's whole argv."""
    if sys.argv and Path(sys.argv[0]).name == "yawil":
        return shlex.join(["yawil", *sys.argv[1:]])
    argv = list(getattr(sys, "orig_argv", None) or sys.argv)
    return shlex.join(argv) if argv else "unknown"


def provenance(command: str | None = None) -> dict[str, str]:
    """What made a report: yawil version, git commit, command line and date (UTC, ISO 8601)."""
    from yawil import __version__

    return {
        "yawil_version": __version__,
        "git_commit": git_commit(),
        "command": command if command is not None else command_line(),
        "date_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def provenance_markdown(prov: Mapping[str, str]) -> str:
    return (f"Made by yawil {prov['yawil_version']} (commit {prov['git_commit']}) on "
            f"{prov['date_utc'].replace('T', ' ').rstrip('Z')} UTC with `{prov['command']}`.")
