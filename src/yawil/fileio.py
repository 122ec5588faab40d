"""Writing files whole, with the permissions any other new file would get.

`tempfile.mkstemp` creates its file with mode 0600 whatever the umask, so a file written to a temporary name
and renamed over its target stayed readable by its owner only (checkpoints, reports, plots). Every such
writer gives the temporary file `default_file_mode()` before the rename: 0644 under the usual umask 022.
Only the standard library is imported here: the CLI modules may use it without slowing `yawil --help`.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    """The process umask. Read from /proc where it is listed (Linux), as setting it to read it back changes
    it for every thread for a moment; elsewhere set and restore it under a lock."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def default_file_mode() -> int:
    """The mode `open(path, 'w')` gives a new file: 0o666 less the umask (0o644 under umask 022)."""
    return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """A binary file handle whose content replaces `path` when the block ends without an error: written to a
    temporary file beside it, fsynced, renamed over it. Readers see the old file or the new one, never half
    of one; on an error the temporary file is removed and `path` is untouched. With `atomic_path` (for writers
    that want a file name) the one implementation of atomic writes in yawil (checkpoints, manifests, records,
    reports, plots, videos, ONNX graphs)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), default_file_mode())  # mkstemp makes 0600
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:  # named by the file the user asked for, not the temporary one
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise _named(err, path) from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path beside `path` for writers that take a file name, not a handle (matplotlib, PIL,
    imageio, the ONNX exporter): it ends in `path`'s extension, so a writer that picks its format by the name
    picks the same one. When the block ends without an error the file gets `default_file_mode()` and is renamed
    over `path`; on an error it is removed and `path` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, default_file_mode())  # mkstemp makes 0600
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise _named(err, path) from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _named(err: OSError, path: Path) -> OSError:
    """The error of a failed atomic write, naming `path` (the temporary file's name means nothing to a user)."""
    return OSError(err.errno, f"writing {path} failed: {err.strerror or err}")


def write_atomic(path: str | os.PathLike[str], data: str | bytes) -> Path:
    """Write `data` (str as UTF-8) to `path` atomically (`atomic_file`) with `default_file_mode()`."""
    with atomic_file(path) as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)
    return Path(path)


def write_json_atomic(path: str | os.PathLike[str], obj: Any) -> None:
    """Write `obj` as indented JSON with sorted keys and a final newline, atomically (`write_atomic`): run
    descriptions, stage markers, route files, tables' data."""
    write_atomic(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


# A folder holding one of these belongs to a yawil stage: its files are that stage's, and no file option of
# another command replaces them. Each marker with the file that must stand beside it (None: alone), so that a
# user's folder that happens to hold a manifest.json is not taken for a dataset.
OWNED_MARKERS: dict[str, str | None] = {
    ".yawil.lock": None,  # a training or DAgger run, a results folder, a dataset being written (yawil.locking)
    "manifest.json": "episodes",  # a dataset
    "card.json": "model.pt",  # a zoo model
}


def non_finite(value: Any, where: str = "") -> tuple[str, float] | None:
    """The first (field path, e.g. `trajectory[3][1]`, value) in a JSON value holding a NaN or an infinity, else
    None: Python's JSON reads and writes them, other readers refuse them, and no figure may be one."""
    if isinstance(value, float) and not math.isfinite(value):
        return where or "(the record)", value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        name = f"{where}[{key}]" if isinstance(key, int) else f"{where}.{key}" if where else str(key)
        found = non_finite(item, name)
        if found is not None:
            return found
    return None


def is_owned(folder: Path) -> bool:
    """Whether `folder` itself belongs to a yawil stage (holds a marker of `OWNED_MARKERS` with its companion)."""
    return any((folder / marker).exists() and (beside is None or (folder / beside).exists())
               for marker, beside in OWNED_MARKERS.items())


def owning_folder(path: str | os.PathLike[str]) -> Path | None:
    """The nearest folder at or above `path`'s folder that a yawil stage owns (`OWNED_MARKERS`), or None."""
    folder = Path(path).absolute().parent
    return next((p for p in (folder, *folder.parents) if is_owned(p)), None)


def check_output_file(path: str | os.PathLike[str], option: str, force: bool = False,
                      own: tuple[str | os.PathLike[str], ...] = ()) -> Path:
    """Refuse, in one line naming the file, an output file that would replace a file the command did not make
    or land inside a folder a yawil stage owns: an existing file needs `force` (`--force`); a file inside a
    dataset, run, results or zoo folder is refused, new or not, whatever `force` says (its readers find every
    file there: `episodes/` is read recursively). `own`: the paths this command itself writes (its default
    output, e.g. a dataset's stats.png), which it may write or replace there. Checked before any work."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{option} {path}: is a folder; expected the name of a file to write")
    if path.name in OWNED_MARKERS or path.name.startswith(".yawil"):
        raise ValueError(f"{option} {path}: a yawil bookkeeping file; write elsewhere")
    mine = any(path.absolute() == Path(o).absolute() for o in own)
    owner = None if mine else owning_folder(path)
    if owner is not None:
        raise ValueError(f"{option} {path}: inside {owner}, which a yawil dataset, run, results or model owns; "
                         "write the file elsewhere (--force does not write there)")
    if not path.exists() and not path.is_symlink():
        _check_writable_parent(path, option)
        return path
    if not mine and not force:
        raise ValueError(f"{option} {path}: exists; give --force to replace it, or another file name")
    return path


def check_not_inside_owned(path: str | os.PathLike[str], option: str) -> Path:
    """Refuse, in one line, a new stage folder (a dataset, run, results or pipeline folder) inside another
    stage's folder: a dataset collected into another's `episodes/` is read as part of it, and a run inside a
    results folder mixes two products. The stages nest their own sub-folders (DAgger's rounds, select's
    candidates) through their Python calls, not through this check."""
    path = Path(path)
    owner = owning_folder(path)  # from the folder holding `path` upwards: `path` itself may be the stage's own
    if owner is not None:
        raise ValueError(f"{option} {path}: inside {owner}, which a yawil dataset, run, results or model owns; "
                         "give a folder outside it")
    return path


def make_folder(path: str | os.PathLike[str], what: str) -> Path:
    """Create folder `path` (and its parents), refusing in one line a path that is, or lies under, a file: the
    OS says only "[Errno 17] File exists" or "[Errno 20] Not a directory" without naming which."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists() or p.is_symlink():
            if not p.is_dir():
                where = "is a file" if p == path else f"its parent {p} is a file"
                raise ValueError(f"{path}: {where}; expected a folder for the {what}")
            break
    path.mkdir(parents=True, exist_ok=True)
    return path


OUTPUT_MARKER = ".yawil-output"  # in a folder a report, explain or view command wrote: which command


def check_output_folder(path: str | os.PathLike[str], option: str, command: str, force: bool = False) -> Path:
    """Refuse, in one line naming the folder, an output folder whose files a command would replace unasked.

    A folder is fine when it does not exist, is empty, or was written before by the same `command` (its
    `OUTPUT_MARKER` says so: a report is regenerated in place). A user's folder with other files needs `force`
    (same-named files are then replaced); a file, or a folder a yawil stage owns (dataset, run, results, zoo
    model: `OWNED_MARKERS`) or lying inside one, is refused whatever `force` says. Checked before any work."""
    path = Path(path)
    entries = _output_folder_entries(path, option)
    if not entries:
        return path
    made_by = _made_by(path)
    if made_by == command or force:
        return path
    what = f"was written by `yawil {made_by}`" if made_by else f"holds {_entries(entries)} yawil {command} did not write"
    raise ValueError(f"{option} {path}: {what}; give a new or empty folder, or --force to write beside them "
                     "(files of the same name are replaced)")


def check_pipeline_folder(path: str | os.PathLike[str], option: str, command: str,
                          signature: tuple[str, ...] = ()) -> Path:
    """Refuse, in one line, a pipeline's output folder (demo, reproduce, experiment, select) that holds what
    the pipeline did not write: a user's files, a dataset, a run. Fine: a new or empty folder, one marked as
    `command`'s (`claimed_output_folder`), or one holding an entry of `signature` (what the pipeline wrote
    before the mark existed, so older folders resume). Why: these pipelines resume by reading their folder, so
    a foreign folder was written into and its files read as the pipeline's. Checked before any work."""
    path = Path(path)
    entries = _output_folder_entries(path, option)
    if not entries or _made_by(path) == command or entries & set(signature):
        return path
    raise ValueError(f"{option} {path}: holds {_entries(entries)} yawil {command} did not write; give a new or empty folder "
                     f"(a {command} folder is resumed where it stopped)")


def _output_folder_entries(path: Path, option: str) -> set[str]:
    """What an output folder holds (empty when it is new), refusing in one line a file, a folder that a yawil
    stage owns or that lies inside one, a parent this process cannot write in, and a folder it cannot read: the
    part of every folder rule that does not depend on the command."""
    if path.exists() and not path.is_dir():
        raise ValueError(f"{option} {path}: is a file; expected a folder to write into")
    check_not_inside_owned(path, option)  # a new folder there too: its files would be read as the stage's
    if not path.exists():
        _check_writable_parent(path, option)
        return set()
    if is_owned(path):
        raise ValueError(f"{option} {path}: a yawil dataset, run, results or model folder; give a new folder "
                         "outside it (--force does not write there)")
    try:
        return {e.name for e in path.iterdir()}
    except OSError as err:
        raise ValueError(f"{option} {path}: cannot be read ({err.strerror or err})") from None


def _entries(entries: set[str]) -> str:
    return f"{len(entries)} entr{'y' if len(entries) == 1 else 'ies'}"


def _made_by(folder: Path) -> str | None:
    """The command an `OUTPUT_MARKER` in `folder` names, or None."""
    try:
        made_by = json.loads((folder / OUTPUT_MARKER).read_text(encoding="utf-8")).get("command")
    except (OSError, ValueError, AttributeError):
        return None
    return made_by if isinstance(made_by, str) else None


def claim_output_folder(path: str | os.PathLike[str], command: str) -> Path:
    """Create the output folder `check_output_folder` allowed and mark it as `command`'s, so that the same
    command may regenerate its files there later without --force."""
    path = make_folder(path, f"{command} output")
    write_json_atomic(path / OUTPUT_MARKER, {"command": command})
    return path


@contextlib.contextmanager
def claimed_output_folder(path: str | os.PathLike[str], command: str) -> Iterator[Path]:
    """`claim_output_folder` for the block that writes into it. Why: a command refused after the claim (an option
    its work checks, a frame source that is missing) left a new folder holding only the marker. When the block
    ends in an error and the folder holds nothing new but the marker, the marker goes again (or the one there
    before comes back) and so do the folders this call made; a folder the command wrote into stays."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not (p.exists() or p.is_symlink())]  # innermost first
    marker = path / OUTPUT_MARKER
    before = set() if made else {e.name for e in path.iterdir()}
    old = marker.read_bytes() if marker.is_file() else None
    out = claim_output_folder(path, command)
    try:
        yield out
    except BaseException:
        with contextlib.suppress(OSError):
            if {e.name for e in out.iterdir()} == before | {OUTPUT_MARKER}:
                if old is not None:
                    write_atomic(marker, old)
                else:
                    marker.unlink()
                    for p in made:
                        p.rmdir()
        raise


def _check_writable_parent(path: Path, option: str) -> None:
    """The nearest existing folder above a new file must be a folder this process can write in (the writers make
    the missing ones): a file there, or /proc, failed only at the write, after the work. Tried with a file
    made and removed at once: `os.access` says yes to root in /proc and on a read-only mount."""
    for p in path.absolute().parents:
        if p.exists():
            if not p.is_dir():
                raise ValueError(f"{option} {path}: its parent {p} is a file; expected a folder")
            try:
                fd, probe = tempfile.mkstemp(dir=p, prefix=".yawil-probe-")
            except OSError as err:
                raise ValueError(f"{option} {path}: cannot write in {p} ({err.strerror or err})") from None
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(probe)
            return


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes, read in blocks (checkpoints, zoo weights)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def require_free_space(folder: str | os.PathLike[str], need: int, what: str = "") -> None:
    """OSError(ENOSPC) naming `folder` when its disk has less than `need` bytes free: checked before work whose
    output would otherwise be lost at the write (an episode's flush, a training run's checkpoints)."""
    import errno
    import shutil

    folder = Path(folder)
    probe = next((p for p in (folder, *folder.parents) if p.exists()), Path("."))
    free = shutil.disk_usage(probe).free
    if free < need:
        raise OSError(errno.ENOSPC, f"{folder}: the disk is (nearly) full, {free / 2**20:.1f} MiB free, "
                      f"{need / 2**20:.0f} MiB needed{' ' + what if what else ''}; free some space and run the same "
                      "command again (it resumes)")
