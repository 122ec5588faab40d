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

LOCK_FILE = ".yawil.lock"


@contextmanager
def folder_lock(folder: str | os.PathLike[str], what: str) -> Iterator[Path]:
    """Hold `folder`'s lock for the body (creating the folder); ValueError if another holder has it (another
    process, or a second lock of the same folder in this one)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: is a file; expected a folder for the {what}")
    folder.mkdir(parents=True, exist_ok=True)
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
