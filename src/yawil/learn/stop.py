"""Stopping a run cleanly: Ctrl-C, SIGTERM or SIGHUP ends it after the current optimiser step (then the loop
saves last.pt); a second signal stops at once."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class StopRequested(Exception):
    """Raised between two optimiser steps after a Ctrl-C or SIGTERM."""


STOP: dict[str, Any] = {"requested": False, "signal": None}


@contextmanager
def stop_between_steps(announce: bool = True) -> Iterator[None]:
    """Ctrl-C and SIGTERM ask the loop to stop after the current step instead of interrupting it: a step cut
    in the middle has already moved BatchNorm's running statistics (or some of the weights), and a checkpoint
    of that would not resume to an uninterrupted run's weights. A second signal stops at once, unsaved."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if STOP["requested"]:
            raise KeyboardInterrupt(f"signal {signum}")
        STOP["requested"], STOP["signal"] = True, signum
        if announce:
            print("stopping after this step (press Ctrl-C again to stop at once, unsaved)", file=sys.stderr, flush=True)

    STOP["requested"], STOP["signal"] = False, None
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        STOP["requested"] = False


def check_stop() -> None:
    if STOP["requested"]:
        raise StopRequested


def stopped(message: str) -> KeyboardInterrupt:
    """What a run stopped by a signal raises once its state is saved: `Terminated` for SIGTERM or SIGHUP (exit
    143 / 129, as every other command), KeyboardInterrupt for Ctrl-C (130)."""
    from yawil.signals import Terminated

    sig = STOP.get("signal")
    return Terminated(sig) if sig in (signal.SIGTERM, signal.SIGHUP) else KeyboardInterrupt(message)
