"""Resumable stages of the long jobs (`yawil demo`, `yawil reproduce`, `yawil experiment`).

A finished stage leaves a small JSON marker (what it made, how long it took); a job run again skips every
stage whose marker exists, and the stages themselves resume mid-way (collection, training, benchmark). The
marker is written last and atomically, so a stage stopped half-way is never taken for done.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from yawil.fileio import write_json_atomic


def read_marker(path: Path) -> dict[str, Any] | None:
    """The marker's content, or None when the stage has not finished."""
    if not path.is_file():
        return None
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as err:
        raise ValueError(f"{path}: stage marker is not valid JSON ({err}); delete it to run the stage again") from None
    if not isinstance(info, dict):
        raise ValueError(f"{path}: stage marker must be a JSON object; delete it to run the stage again")
    return info


def write_marker(path: Path, info: dict[str, Any]) -> None:
    write_json_atomic(path, info)


def run_stage(path: Path, fn: Callable[[], dict[str, Any] | None], log: Callable[[str], None],
              name: str) -> dict[str, Any]:
    """Run `fn` unless `path` marks it done; the marker records its result and its wall time in seconds."""
    info = read_marker(path)
    if info is not None:
        log(f"{name}: done before, skipped")
        return info
    log(f"{name} ...")
    t0 = time.perf_counter()
    info = {**(fn() or {})}
    info.setdefault("seconds", time.perf_counter() - t0)
    write_marker(path, info)
    return info
