"""One writer per output folder (a dataset, a training run, a results folder, a DAgger run).

Why: two `yawil bench` runs into one folder duplicated every episode record, and two `yawil train` runs into
one `--out` left a config of one and weights of the other; both exited 0. The second writer is now refused
at once. The lock is an OS file lock (`filelock`, flock on POSIX): the kernel drops it when its process
dies, so a `kill -9` never leaves a stale lock behind and the usual resume works.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from filelock import FileLock, Timeout

from yawil.fileio import make_folder

LOCK_FILE = ".yawil.lock"


@contextmanager
def folder_lock(folder: str | os.PathLike[str], what: str) -> Iterator[Path]:
    """Hold `folder`'s lock for the body (creating the folder); ValueError if another holder has it (another
    process, or a second lock of the same folder in this one)."""
    created = not Path(folder).exists()
    folder = make_folder(folder, what)
    path = folder / LOCK_FILE
    lock = FileLock(str(path), timeout=0, mode=0o644)
    try:
        lock.acquire()
    except Timeout:
        raise ValueError(
            f"{folder}: another yawil process is writing this {what} (it holds {path}); "
            "wait for it to finish or use another output folder"
        ) from None
    try:
        yield folder
    finally:
        lock.release()
        if created:
            _remove_if_unused(folder, path)


def _remove_if_unused(folder: Path, lock_path: Path) -> None:
    """A folder this lock created and nothing was written into (the command was refused after taking it) goes
    again: left behind, its lone lock file would mark a user's path as a yawil run."""
    try:
        if [p.name for p in folder.iterdir()] == [LOCK_FILE]:
            lock_path.unlink()
            folder.rmdir()
    except OSError:
        pass  # another process took the folder meanwhile: it stays
