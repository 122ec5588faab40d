"""The `yawil` command. Each sub-command lives in the module that owns the work.

A command module exposes `add_parser(subparsers) -> argparse.ArgumentParser` and `run(args) -> int`.
Command modules import only argparse at module level, so that `yawil --help` stays fast; the heavy
imports (torch, panda3d) happen inside `run`.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from yawil.signals import Terminated

# name -> module that owns it, in the order of the loop.
COMMANDS: dict[str, str] = {
    "sim": "yawil.sim.cli",
    "collect": "yawil.data.collect_cli",
    "data": "yawil.data.cli",
    "models": "yawil.models.cli",
    "zoo": "yawil.zoo.cli",
    "train": "yawil.learn.cli",
    "dagger": "yawil.pipelines.dagger",
    "export": "yawil.learn.export",
    "bench": "yawil.bench.cli",
    "select": "yawil.bench.select",
    "trace": "yawil.bench.trace",
    "report": "yawil.bench.report_cli",
    "results": "yawil.bench.results_cli",
    "experiment": "yawil.bench.experiments_cli",
    "explain": "yawil.explain.cli",
    "demo": "yawil.pipelines.demo",
    "reproduce": "yawil.pipelines.reproduce",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="yawil",
        description="Yaw-guided imitation learning: sim -> expert -> data -> train -> agent -> bench -> report.",
    )
    parser.add_argument("--version", action="version", version=f"yawil {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in COMMANDS.values():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as err:
            if err.name != module_name:
                raise
            continue  # not built yet: the command is simply absent from --help
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
    return parser


def _version() -> str:
    from yawil import __version__

    return __version__


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated(signum)


def main(argv: Sequence[str] | None = None) -> int:
    import signal
    import threading

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    previous = {}
    if threading.current_thread() is threading.main_thread():  # handlers can only be set there
        previous = {sig: signal.signal(sig, _raise_terminated) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        return int(args._run(args) or 0)
    except Terminated as stop:
        print(f"terminated ({signal.Signals(stop.signum).name})", file=sys.stderr)
        return 128 + stop.signum
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as err:
        # Bad input (a value, a file, a full disk) is one line naming it; YAWIL_DEBUG=1 shows the traceback.
        if os.environ.get("YAWIL_DEBUG"):
            raise
        print(f"yawil {args.command}: {err}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def entry() -> int:
    """The `yawil` program: `main`, with a command's own one-line SystemExit given the exit status of every other
    refusal. Exit statuses: 0 done; 1 the work ran and a check it made failed (data check, export --check,
    zoo check); 2 refused before or during the work, in one line (bad input, a held folder, a full disk);
    130 Ctrl-C; 143 SIGTERM (129 SIGHUP)."""
    try:
        return main()
    except SystemExit as stop:
        if not isinstance(stop.code, str):
            raise
        print(stop.code, file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(entry())
