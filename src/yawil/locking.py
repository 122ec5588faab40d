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
# The file each kind of folder writes first: a folder that holds files but not this one is a user's folder or
# another stage's, and writing there would mix (or replace) its files.
KIND_FILES: dict[str, str] = {"dataset": "manifest.json", "training run": "config.yaml",
                              "results folder": "run.json", "DAgger run": "dagger.json"}


@contextmanager
def folder_lock(folder: str | os.PathLike[str], what: str) -> Iterator[Path]:
    """Hold `folder`'s lock for the body (creating the folder); ValueError if another holder has it (another
    process, or a second lock of the same folder in this one)."""
    created = not Path(folder).exists()
    _check_kind(Path(folder), what)
    folder = make_folder(folder, what)
    before = {p.name for p in folder.iterdir()}
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
        _remove_if_unused(folder, path, before, created)


def _check_kind(folder: Path, what: str) -> None:
    """Refuse an existing folder with files that is not a `what` (its `KIND_FILES` file is missing)."""
    sig = KIND_FILES.get(what)
    if sig is None or not folder.is_dir() or (folder / sig).exists():
        return
    entries = [p.name for p in folder.iterdir() if p.name != LOCK_FILE]
    if entries:
        raise ValueError(f"{folder}: holds {len(entries)} entries but no {sig}, so it is not a yawil {what} (a "
                         f"user's folder or another stage's); give a new or empty folder")


def _remove_if_unused(folder: Path, lock_path: Path, before: set[str], created: bool) -> None:
    """What a refused command (nothing written) leaves goes again: the lock file it created and, when it made
    the folder, the folder. Left behind, a lone lock file marks a user's path as a yawil run."""
    try:
        now = {p.name for p in folder.iterdir()}
        if LOCK_FILE not in before and now == before | {LOCK_FILE}:
            lock_path.unlink()
            if created:
                folder.rmdir()
    except OSError:
        pass  # another process took the folder meanwhile: it stays
