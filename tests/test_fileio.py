"""yawil.fileio.atomic_path: the temporary name for writers that take a file name (plots, videos, ONNX)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from yawil.fileio import atomic_path


def test_atomic_path_keeps_the_extension_and_gives_the_usual_mode(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        target = tmp_path / "sub" / "plot.png"
        with atomic_path(target) as tmp:
            assert tmp.parent == target.parent and tmp.name.startswith(".plot.png.") and tmp.suffix == ".png"
            assert not target.exists()
            tmp.write_bytes(b"new")
        assert target.read_bytes() == b"new" and target.stat().st_mode & 0o777 == 0o640
        assert [p.name for p in target.parent.iterdir()] == ["plot.png"]
    finally:
        os.umask(old)


def test_atomic_path_leaves_the_old_file_on_an_error(tmp_path: Path) -> None:
    target = tmp_path / "clip.gif"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("writer failed")
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["clip.gif"]


def test_video_written_whole_with_the_usual_mode(tmp_path: Path) -> None:
    from yawil.video import read_video_frames, write_video

    old = os.umask(0o022)
    try:
        frames = [np.full((9, 11, 3), 40 * i, np.uint8) for i in range(3)]
        path = write_video(frames, tmp_path / "v.gif", fps=5)
        assert read_video_frames(path) == 3 and path.stat().st_mode & 0o777 == 0o644
        assert [p.name for p in tmp_path.iterdir()] == ["v.gif"]
    finally:
        os.umask(old)


def test_a_failed_atomic_write_names_the_file_asked_for(tmp_path: Path) -> None:
    """An OSError while writing names the target, never the temporary file (`.plot.png.x1y2.tmp.png`)."""
    import errno

    from yawil.fileio import atomic_file

    target = tmp_path / "plot.png"
    with pytest.raises(OSError, match=r"writing .*plot\.png failed: No space left") as err, atomic_path(target) as tmp:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
    assert err.value.errno == errno.ENOSPC and ".tmp" not in str(err.value) and list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError, match=r"writing .*data\.json failed"), atomic_file(tmp_path / "data.json"):
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", "/x/.data.json.123.tmp")
