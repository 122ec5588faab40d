"""SIGTERM and SIGHUP as exceptions, shared by the command line and the stages that stop cleanly on them.

Standard library only, importable from any stage without running back up to `yawil.cli`.
"""

from __future__ import annotations


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread so that it unwinds as Ctrl-C does: worker processes are
    ended, files are left whole and folder locks are held until the last worker is gone. A batch scheduler
    stops a job with SIGTERM; without this the main process died at once and its workers ran on. `yawil`
    exits 128 + the signal's number (143, 129)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
