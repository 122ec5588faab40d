"""Every door a clear error: each sub-command given bad input answers in one line naming the value, exits
non-zero, prints no traceback and leaves nothing behind where it refused before any work."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import Any

import pytest

from yawil.cli import main

ONE_EPISODE = ["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "0:1", "--condition", "training",
               "--seeds", "1", "--weather-rule", "cycle", "--no-progress"]
# (argv with {t} for the temporary folder, text the one line must contain, a path that must not exist after)
CASES = [
    (["sim", "view", "--town", "town02", "--weather", "Rainy", "--out", "{t}/v"], "unknown weather 'Rainy'", "{t}/v"),
    (["sim", "routes", "--count", "-2"], "--count -2", None),
    (["collect", "--town", "nowhere", "--frames", "10", "--out", "{t}/c"], "unknown town 'nowhere'", "{t}/c"),
    (["collect", "--frames", "10", "--workers", "0", "--out", "{t}/c"], "workers must be >= 1", None),
    (["collect", "--frames", "-5", "--out", "{t}/c"], "frames must be >= 1", None),
    (["collect", "--frames", "10", "--min-route-length", "1e9", "--out", "{t}/c"], "below 1e5 m", "{t}/c"),
    (["dagger", "--model", "cil", "--takeover-lateral", "-1", "--out", "{t}/g"], "takeover_lateral", "{t}/g"),
    (["dagger", "--model", "cil", "--town", "bogus", "--out", "{t}/g"], "unknown town 'bogus'", "{t}/g"),
    (["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "5:2", "--out", "{t}/b"], "selects no route", "{t}/b"),
    (["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "0:1", "--out", "{t}/afile"], "is a file", None),
    (["bench", "--agent", "{t}/afile", "--out", "{t}/b"], "not a readable torch checkpoint", "{t}/b"),
    (["train", "--data", "{t}/none", "--out", "{t}/r"], "does not exist", None),
    (["train", "--data", "{t}", "--out", "{t}/r", "--model-arg", "dropout=abc"], "dropout='abc' must be a number", None),
    (["demo", "--routes", "abc", "--out", "{t}/d"], "--routes 'abc'", "{t}/d"),
    (["report", "{t}", "--out", "{t}/rep"], "no episodes.jsonl", "{t}/rep"),  # refused after the claim: no folder
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
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--check", "--batch", "100000"], "--batch 100000", "{t}/m.onnx"),
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--opset", "999"], "--opset 999: expected 17 to", "{t}/m.onnx"),
    # a user's file where a route file would go is never replaced (nor is a file taken for the folder)
    (["bench", "routes", "--town", "town01", "--routes-dir", "{t}/afile"], "is a file; expected a folder", None),
    # options that did nothing where they were given (each case bounded: a regression fails in seconds, not hours)
    ([*ONE_EPISODE, "--town", "town02", "--out", "{t}/b"], "--town town02: applies to bench routes", "{t}/b"),
    ([*ONE_EPISODE, "--seed", "3", "--out", "{t}/b"], "--seed 3: applies to bench routes", "{t}/b"),
    ([*ONE_EPISODE, "--label", " ", "--out", "{t}/b"], "--label ' '", "{t}/b"),
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--data", "{t}"], "applies to --check", "{t}/m.onnx"),
    (["trace", "straight/training/ClearNoon/99/0", "--agent", "expert", "--out", "{t}/t.csv", "--tail", "-3"],
     "--tail -3", "{t}/t.csv"),
    (["zoo", "check", "nosuchmodel", "--out", "{t}/z"], "--out applies to zoo pack only", "{t}/z"),
    (["reproduce", "--install", "--dry-run", "--out", "{t}/rp"], "--install applies to --profile zoo", "{t}/rp"),
    ([*ONE_EPISODE, "--engine", "openvino", "--out", "{t}/b"], "--engine openvino: applies to learned agents", "{t}/b"),
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--tolerance", "0.1"], "--tolerance 0.1: applies to --check",
     "{t}/m.onnx"),
    (["export", "{t}/afile", "--onnx", "{t}/m.onnx", "--batch", "8"], "--batch 8: applies to --check", "{t}/m.onnx"),
    (["bench", "routes", "--agent", "zoo:x", "--routes-dir", "{t}/r"], "--agent zoo:x: not read by bench routes", "{t}/r"),
    (["bench", "validate", "--workers", "2"], "--workers 2: not read by bench validate", None),
    (["explain", "--checkpoint", "{t}/afile", "--frames", "{t}", "--town", "town01", "--out", "{t}/e"],
     "--town town01: applies to --episode and --faithfulness --episode, not to --frames", "{t}/e"),
    (["explain", "--failures", "{t}", "--class-task", "dense", "--count", "3", "--out", "{t}/e"],
     "--count 3: applies to --frames and --faithfulness --frames, not to --failures", "{t}/e"),
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


def _one_line(argv: list[str]) -> tuple[int, str]:
    """`main(argv)`'s exit status and its one line of stderr (a SystemExit's message counted as one)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = main(argv)
        except SystemExit as exit_:
            rc = exit_.code if isinstance(exit_.code, int) else 2
            if not isinstance(exit_.code, int):
                err.write(str(exit_.code))
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    return rc, lines[0]


def test_explain_refused_after_the_claim_leaves_no_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A refusal from the work (here the deletion test's --ks) came after the output folder was claimed: a new
    folder holding only .yawil-output stayed, and its parents with it."""
    from yawil.agent import Agent

    monkeypatch.setattr(Agent, "from_checkpoint", classmethod(lambda cls, path, **kw: object()))
    out = tmp_path / "new" / "e"
    rc, line = _one_line(["explain", "--checkpoint", "x.pt", "--frames", str(tmp_path), "--faithfulness",
                          "--ks", "abc", "--out", str(out)])
    assert rc == 2 and "--ks 'abc'" in line
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()  # a user's empty folder stays, without the marker
    rc, _ = _one_line(["explain", "--checkpoint", "x.pt", "--frames", str(tmp_path), "--faithfulness",
                       "--ks", "abc", "--out", str(tmp_path / "mine")])
    assert rc == 2 and list((tmp_path / "mine").iterdir()) == []


def _results(folder: Path) -> Path:
    from yawil.bench.records import PROTOCOL, EpisodeLog, check_run_info

    check_run_info(folder, {"agent": "expert", "agent_options": {}, "label": "expert"})
    with EpisodeLog(folder) as log:
        log.append({"protocol": PROTOCOL, "suite": "nocrash", "task": "regular", "condition": "training",
                    "weather": "ClearNoon", "route_id": 1, "seed": 0, "success": True, "reason": None,
                    "km_driven": 0.5, "lane_opposite": 0, "lane_offroad": 0, "red_lights": 0, "lights_passed": 1,
                    "trajectory": [[0, 0], [10, 0]], "route_xy": [[0, 0], [10, 0]]})
    return folder


def test_report_refuses_a_trajectory_episode_the_results_do_not_hold(tmp_path: Path) -> None:
    """An unknown --trajectory episode was dropped silently (the report had no such figure)."""
    results = _results(tmp_path / "r")
    for spec in ("training=regular/7/0", "training=dense/1/0", "training=regular/WetNoon/1/0",
                 "new-town-weather=regular/1/0"):
        rc, line = _one_line(["report", str(results), "--out", str(tmp_path / "rep"), "--trajectory", spec])
        assert rc == 2 and f"--trajectory {spec}: no such episode" in line and "episodes.jsonl" in line, line
        assert not (tmp_path / "rep").exists()
    assert "e.g. training=regular/ClearNoon/1/0" in _one_line(
        ["report", str(results), "--out", str(tmp_path / "rep"), "--trajectory", "training=regular/7/0"])[1]


def test_data_stats_writes_no_new_file_into_a_dataset(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A new --out inside a dataset (its episodes/ is read by rglob) or a run was allowed; the default
    DIR/stats.png stays the command's own."""
    data = tmp_path / "data"
    (data / "episodes").mkdir(parents=True)
    (data / "manifest.json").write_text('{"episodes": []}')
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / ".yawil.lock").write_text("")
    for out in (data / "episodes" / "x.h5", data / "plot.png", tmp_path / "run" / "stats.png"):
        rc, line = _one_line(["data", "stats", str(data), "--out", str(out)])
        assert rc == 2 and f"--out {out}: inside" in line, line
        assert not out.exists()
    monkeypatch.setattr("yawil.data.stats.write_stats", lambda dirs, out: out)  # the figure itself is not the point
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["data", "stats", str(data)]) == 0
        assert main(["data", "stats", str(data), "--out", str(data / "stats.png")]) == 0


def test_data_subset_under_a_file_names_the_users_path(tmp_path: Path, tiny_dataset: Any) -> None:
    """The error named the temporary folder the subset is built in (afile/.sub.tmp-PID/episodes)."""
    (tmp_path / "afile").write_text("x")
    rc, line = _one_line(["data", "subset", str(tiny_dataset()), "--only", "all", "--out", str(tmp_path / "afile" / "sub")])
    assert rc == 2 and f"--out {tmp_path / 'afile' / 'sub'}: its parent" in line and ".tmp-" not in line, line


def test_bench_names_a_run_json_yawil_did_not_write(tmp_path: Path) -> None:
    """A user's run.json in --out was read as results of benchmark protocol 1."""
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "run.json").write_text('{"name": "my run"}')
    rc, line = _one_line(["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "0:1",
                          "--out", str(tmp_path / "b"), "--no-progress"])
    assert rc == 2 and "not a yawil results record" in line and "protocol" not in line, line
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["run.json"]


def test_bench_routes_never_replaces_a_users_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`bench routes --routes-dir` over a folder holding a user's town01.json refused it only after replacing it."""
    mine = tmp_path / "town01.json"
    mine.write_text('{"mine": 1}')
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "routes", "--town", "town01", "--routes-dir", str(tmp_path)])
    assert "is not a yawil route file" in str(exit_.value.code) and mine.read_text() == '{"mine": 1}'


def test_explain_count_beyond_the_dataset_is_refused_before_the_agent(tmp_path: Path, tiny_dataset: Any,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    from yawil.agent import Agent

    def never(cls: Any, path: Any, **kw: Any) -> Any:
        raise AssertionError("the agent was built before --count was checked")

    monkeypatch.setattr(Agent, "from_checkpoint", classmethod(never))
    data = tiny_dataset(episodes=2, frames=5)
    (tmp_path / "x.pt").write_bytes(b"weights")
    rc, line = _one_line(["explain", "--checkpoint", str(tmp_path / "x.pt"), "--frames", str(data), "--count", "11",
                          "--out", str(tmp_path / "e")])
    assert rc == 2 and "--count 11" in line and "holds 10 frames" in line, line
    assert not (tmp_path / "e").exists()
