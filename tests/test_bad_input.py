"""Every door a clear error: each sub-command given bad input answers in one line naming the value, exits
non-zero, prints no traceback and leaves nothing behind where it refused before any work."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import Any

import pytest

from yawil.cli import main

# (argv with {t} for the temporary folder, text the one line must contain, a path that must not exist after)
CASES = [
    (["sim", "view", "--town", "town02", "--weather", "Rainy", "--out", "{t}/v"], "unknown weather 'Rainy'", "{t}/v"),
    (["sim", "routes", "--count", "-2"], "--count -2", None),
    (["collect", "--town", "nowhere", "--frames", "10", "--out", "{t}/c"], "unknown town 'nowhere'", "{t}/c"),
    (["collect", "--frames", "10", "--workers", "0", "--out", "{t}/c"], "workers must be >= 1", None),
    (["collect", "--frames", "-5", "--out", "{t}/c"], "frames must be >= 1", None),
    (["collect", "--frames", "10", "--min-route-length", "1e9", "--out", "{t}/c"], "below 1e5 m", "{t}/c"),
    (["collect", "--frames", "10", "--seed", "-1", "--out", "{t}/c"], "--seed -1", "{t}/c"),
    (["dagger", "--model", "cil", "--takeover-lateral", "-1", "--out", "{t}/g"], "takeover_lateral", "{t}/g"),
    (["dagger", "--model", "cil", "--town", "bogus", "--out", "{t}/g"], "unknown town 'bogus'", "{t}/g"),
    (["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "5:2", "--out", "{t}/b"], "selects no route", "{t}/b"),
    (["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "0:1", "--out", "{t}/afile"], "is a file", None),
    (["bench", "--agent", "{t}/afile", "--out", "{t}/b"], "not a readable torch checkpoint", "{t}/b"),
    (["train", "--data", "{t}/none", "--out", "{t}/r"], "does not exist", None),
    (["train", "--data", "{t}", "--out", "{t}/r", "--model-arg", "dropout=abc"], "dropout='abc' must be a number", None),
    (["demo", "--routes", "abc", "--out", "{t}/d"], "--routes 'abc'", "{t}/d"),
    (["report", "{t}", "--out", "{t}/rep"], "no episodes.jsonl", None),
    (["report", "{t}", "{t}/", "--out", "{t}/rep"], "given twice", None),
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--tolerance", "-1", "--check"], "--tolerance -1.0", "{t}/m.onnx"),
    (["export", "{t}/missing.pt", "--onnx", "{t}/m.onnx"], "missing.pt does not exist", "{t}/m.onnx"),
    (["dagger", "--out", "{t}/dg", "--beta", "x"], "--beta", "{t}/dg"),
    (["explain", "--checkpoint", "{t}/missing.pt", "--frames", "{t}", "--out", "{t}/e"], "does not exist", None),
    (["collect", "--frames", "10", "--host", "10.0.0.2", "--out", "{t}/c"], "--host applies to --backend carla", "{t}/c"),
    (["bench", "--suite", "corl2017", "--tasks", "straight", "--port", "3000", "--out", "{t}/b"],
     "--port applies to --backend carla", "{t}/b"),
    (["export", "{t}", "--onnx", "{t}/m.onnx"], "is a folder; expected a checkpoint file", "{t}/m.onnx"),
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--batch", "0"], "--batch 0", "{t}/m.onnx"),
]


@pytest.mark.parametrize("argv, text, absent", CASES, ids=[" ".join(c[0][:2]) + f" {i}" for i, c in enumerate(CASES)])
def test_bad_input_is_one_line(tmp_path: Path, argv: list[str], text: str, absent: str | None) -> None:
    (tmp_path / "afile").write_text("not a checkpoint")
    argv = [a.replace("{t}", str(tmp_path)) for a in argv]
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = main(argv)
        except SystemExit as exit_:  # the commands that end with their own one-line message
            rc = exit_.code if isinstance(exit_.code, int) else 1
            if not isinstance(exit_.code, int):
                err.write(str(exit_.code))
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    assert rc in (1, 2) and len(lines) == 1, lines
    assert text in lines[0] and "Traceback" not in lines[0], lines[0]
    if absent is not None:
        assert not Path(absent.replace("{t}", str(tmp_path))).exists()


def test_the_program_exits_2_for_every_refusal(tmp_path: Path) -> None:
    """Commands that refuse with their own SystemExit line and those that raise ValueError exit alike (2)."""
    import subprocess
    import sys

    for argv, text in ((["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "5:2"], "selects no route"),
                       (["export", str(tmp_path / "none.pt"), "--onnx", str(tmp_path / "m.onnx")], "none.pt")):
        done = subprocess.run([sys.executable, "-m", "yawil.cli", *argv, *(["--out", str(tmp_path / "b")]
                               if argv[0] == "bench" else [])], capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and text in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_select_reads_every_candidate_before_driving_any(tmp_path: Path, tiny_checkpoint: Any) -> None:
    """A bad last candidate is refused in seconds, before the first is driven (it was reached after hours)."""
    import time

    good = tiny_checkpoint("yaw-guided", guidance_dim=15).path
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "last.pt").write_text("not a checkpoint")
    t0 = time.perf_counter()
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(["select", str(good), str(tmp_path / "bad" / "last.pt"), "--out", str(tmp_path / "sel"),
                   "--no-progress"])
    assert rc == 2 and "not a readable torch checkpoint" in err.getvalue()
    assert time.perf_counter() - t0 < 20 and not any((tmp_path / "sel").glob("*/episodes.jsonl"))
