"""Inputs that used to be taken without a word and give a wrong result (issue 40): each is now refused in one
line naming the file, field or value and what was expected, before anything is written."""

from __future__ import annotations

import contextlib
import io
import json
import os
import warnings
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
import yaml

from yawil.cli import main


def run_cli(argv: list[str]) -> tuple[int, list[str], str]:
    """(exit status, the non-empty lines on stderr, stdout) of `yawil ARGV`, warnings made errors."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a raw warning on stderr is not the one clear line
        try:
            rc = main(argv)
        except SystemExit as exit_:
            rc = exit_.code if isinstance(exit_.code, int) else 2
            if not isinstance(exit_.code, int):
                err.write(str(exit_.code))
    return rc, [line for line in err.getvalue().splitlines() if line.strip()], out.getvalue()


# ----- 1. a benchmark record with a figure that is not a finite number >= 0
def _results(folder: Path, bad_line: int | None = None, text: str = "") -> Path:
    from yawil.bench.records import EPISODES_FILE, PROTOCOL, check_run_info

    check_run_info(folder, {"agent": "expert", "agent_options": {}, "label": "expert"})
    lines = []
    for rid in range(3):
        rec = {"protocol": PROTOCOL, "suite": "nocrash", "task": "regular", "condition": "training",
               "weather": "ClearNoon", "route_id": rid, "seed": 0, "success": True, "reason": None,
               "km_driven": 0.5, "lane_opposite": 0, "lane_offroad": 0, "red_lights": 0, "lights_passed": 1,
               "trajectory": [[0, 0], [10, 0]], "route_xy": [[0, 0], [10, 0]]}
        lines.append(json.dumps(rec, separators=(",", ":")))
    if bad_line is not None:
        lines[bad_line - 1] = lines[bad_line - 1].replace(*text.split("|"))
    (folder / EPISODES_FILE).write_text("\n".join(lines) + "\n")
    return folder / EPISODES_FILE


@pytest.mark.parametrize("change, message", [
    ('"km_driven":0.5|"km_driven":Infinity', "line 2: km_driven=inf, expected a finite number"),
    ('"km_driven":0.5|"km_driven":NaN', "line 2: km_driven=nan, expected a finite number"),
    ('"km_driven":0.5|"km_driven":1e999', "line 2: km_driven=inf, expected a finite number"),
    ('"km_driven":0.5|"km_driven":-1', "line 2, record 2: km_driven=-1, expected a number >= 0"),
    ('[10,0]],"route_xy"|[10,NaN]],"route_xy"', "line 2: trajectory[1][1]=nan, expected a finite number"),
])
def test_report_refuses_a_figure_that_is_not_a_finite_number(tmp_path: Path, change: str, message: str) -> None:
    path = _results(tmp_path / "res", 2, change)
    rc, lines, _ = run_cli(["report", str(tmp_path / "res"), "--out", str(tmp_path / "rep")])
    assert rc == 2 and len(lines) == 1 and f"{path}: {message}" in lines[0], lines
    assert not (tmp_path / "rep").exists()  # refused before any of the report was written


def test_read_records_names_the_line_of_a_non_finite_number(tmp_path: Path) -> None:
    from yawil.bench.records import read_records

    path = _results(tmp_path, 3, '"lights_passed":1|"lights_passed":-Infinity')
    with pytest.raises(ValueError, match=r"episodes.jsonl: line 3: lights_passed=-inf, expected a finite number"):
        read_records(path)
    assert len(read_records(_results(tmp_path))) == 3


# ----- 2. a zoo card holding NaN or Infinity
def test_zoo_pack_refuses_a_card_with_a_non_finite_number(tmp_path: Path) -> None:
    card = tmp_path / "card.json"
    card.write_text('{"summary": "x", "validation": {"val_loss": 0.1, "by_task": [1.0, NaN]}}')
    (tmp_path / "afile").write_text("not a checkpoint")
    rc, lines, _ = run_cli(["zoo", "pack", str(tmp_path / "afile"), "--name", "m", "--data", str(tmp_path),
                            "--card", str(card), "--out", str(tmp_path / "z")])
    assert rc == 2 and len(lines) == 1, lines
    assert f"--card {card}: validation.by_task[1]=nan, expected a finite number" in lines[0], lines
    assert not (tmp_path / "z").exists()


# ----- 3. --resume with a step budget the run is already past
def test_resume_below_the_runs_step_is_refused_before_any_work(tmp_path: Path, tiny_dataset: Any) -> None:
    from yawil import models
    from yawil.learn.config import TrainConfig
    from yawil.learn.setup import check_budget
    from yawil.policy.checkpoint import Norm, make_checkpoint, save_checkpoint

    run = tmp_path / "run"
    run.mkdir()
    cfg = TrainConfig(model="cil", data=[str(tiny_dataset())], out=str(run), max_steps=5, progress=False)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    model = models.create("cil", seed=0)
    save_checkpoint(make_checkpoint(model, Norm(2.5, 1.5, (), ()), {"spacing": 2.0, "count": 15, "reference": "route"},
                                    cfg.to_dict(), 0, 5, position={"step": 5}), run / "last.pt")
    before = (run / "config.yaml").read_text()
    rc, lines, _ = run_cli(["train", "--resume", "--max-steps", "3", "--out", str(run), "--no-progress"])
    assert rc == 2 and len(lines) == 1, lines
    assert f"--max-steps 3: the run at {run} is already at step 5; give more steps" in lines[0]
    assert (run / "config.yaml").read_text() == before and not (run / "tb").exists()
    check_budget({"position": {"step": 5}}, cfg, run)  # the budget reached: a finished run, resumed unchanged


# ----- 4. every loss weight 0
def test_every_loss_weight_zero_is_refused(tmp_path: Path, tiny_dataset: Any) -> None:
    from yawil.learn.config import TrainConfig

    with pytest.raises(ValueError, match="every loss weight is 0 .*nothing would be learned"):
        TrainConfig(alpha=0.0, beta=0)
    TrainConfig(alpha=0.0, beta=0.0, aux_weight=1.0, model_args={"aux": True})  # the aux loss alone learns
    rc, lines, _ = run_cli(["train", "--model", "cil", "--data", str(tiny_dataset()), "--out", str(tmp_path / "r"),
                            "--alpha", "0", "--beta", "0"])
    assert rc == 2 and len(lines) == 1 and "every loss weight is 0" in lines[0], lines
    assert not (tmp_path / "r").exists()


# ----- 5. an aux weight for a model without an aux head: refused before the run folder is made
def test_aux_weight_without_an_aux_head_leaves_no_folder(tmp_path: Path, tiny_dataset: Any) -> None:
    from yawil.models.registry import has_aux_head

    rc, lines, _ = run_cli(["train", "--model", "cil", "--data", str(tiny_dataset()), "--out", str(tmp_path / "r"),
                            "--aux-weight", "0.5", "--no-progress"])
    assert rc == 2 and len(lines) == 1 and "aux_weight=0.5 but model cil has no aux head" in lines[0], lines
    assert not (tmp_path / "r").exists()
    assert has_aux_head("yilratt", aux=True) and not has_aux_head("yilratt") and not has_aux_head("cil", aux=False)


# ----- 6. data check: NaN privileged labels beside a known reason, guidance settings against the manifest's
def test_data_check_names_nan_target_speed_and_a_contradicting_guidance(tmp_path: Path) -> None:
    from yawil.data.manifest import read_manifest, write_manifest
    from yawil.data.synthetic import write_synthetic_dataset

    m = write_synthetic_dataset(tmp_path / "d", episodes=3, frames=5, k=3)
    p0, p1, p2 = (m.path_of(e) for e in m.episodes)
    with h5py.File(p0, "r+") as f:
        f["target_speed"][2] = np.nan
    with h5py.File(p1, "r+") as f:
        config = json.loads(f.attrs["config"])
        config["guidance"]["reference"] = "ego"
        f.attrs["config"] = json.dumps(config)
    with h5py.File(p2, "r+") as f:  # a frame made without an expert: every privileged label unknown
        f["speed_reason"][1] = -1
        for name in ("target_speed", "lead_distance", "lead_speed"):
            f[name][1] = np.nan
    m = read_manifest(tmp_path / "d")
    m.episodes[2].bytes = p2.stat().st_size  # rewritten in place, not damaged
    write_manifest(m)
    rc, _, out = run_cli(["data", "check", str(tmp_path / "d")])
    assert rc == 1 and "2 bad" in out, out
    assert ("BAD episodes/ep_000000.h5\n    target_speed: NaN at 1 row(s) whose speed_reason is known, first row 2"
            in out), out
    assert "BAD episodes/ep_000001.h5\n    guidance reference='ego' in its attributes, the manifest says 'route'" in out
    assert "ep_000002" not in out


# ----- 7. stats and subset of a dataset with a damaged episode
@pytest.mark.parametrize("command", ["stats", "subset"])
def test_stats_and_subset_name_a_damaged_episode(tmp_path: Path, command: str, tiny_dataset: Any) -> None:
    import shutil

    shutil.copytree(tiny_dataset(episodes=3, frames=5, k=3), tmp_path / "d")
    bad = tmp_path / "d" / "episodes" / "ep_000001.h5"
    with open(bad, "r+b") as f:
        f.truncate(os.path.getsize(bad) - 1000)
    out = tmp_path / ("s.png" if command == "stats" else "sub")
    argv = ["data", "stats", str(tmp_path / "d"), "--out", str(out)] if command == "stats" else \
        ["data", "subset", str(tmp_path / "d"), "--only", "all", "--out", str(out)]
    rc, lines, _ = run_cli(argv)
    assert rc == 2 and len(lines) == 1 and f"{bad}: cannot open as HDF5 (truncated or corrupt?)" in lines[0], lines
    assert not out.exists() and not list(tmp_path.glob(".sub*"))


def test_subset_names_an_episode_whose_images_do_not_decode(tmp_path: Path) -> None:
    from yawil.data.synthetic import write_synthetic_dataset

    m = write_synthetic_dataset(tmp_path / "d", episodes=2, frames=6, k=3)
    bad = m.path_of(m.episodes[1])
    with h5py.File(bad, "r") as f:  # overwrite the compressed bytes of one image chunk
        offset = f["image"].id.get_chunk_info(3).byte_offset
    with open(bad, "r+b") as f:
        f.seek(offset + 16)
        f.write(b"\xff" * 1024)
    rc, lines, _ = run_cli(["data", "subset", str(tmp_path / "d"), "--only", "all", "--out", str(tmp_path / "s")])
    assert rc == 2 and len(lines) == 1 and f"{bad}: image rows 0-5 cannot be decoded" in lines[0], lines
    assert not (tmp_path / "s").exists()


# ----- 8. an observation with a NaN speed or an unknown command
def _observation(**change: Any) -> Any:
    from yawil.sim.types import Observation, Pose, RoadOption, Route

    xy = np.stack([np.arange(0.0, 60.0), np.zeros(60)], axis=1)
    route = Route(xy=xy, options=np.full(60, int(RoadOption.LANEFOLLOW), np.int8), lane_yaw=np.zeros(60))
    values: dict[str, Any] = dict(
        image=np.zeros((88, 200, 3), np.uint8), speed=3.0, pose=Pose(10.0, 0.3, 0.05), route=route, route_index=10,
        command=RoadOption.LANEFOLLOW, events=(), time=0.0, frame=0, done=False, distance_driven=0.0, town="town01",
        bounds=(-10.0, -10.0, 110.0, 60.0), weather="ClearNoon")
    return Observation(**{**values, **change})


@pytest.mark.parametrize("name", ["yaw-guided", "cil"])
def test_agent_refuses_a_nan_speed_or_an_unknown_command(tiny_checkpoint: Any, name: str) -> None:
    from yawil.agent import Agent

    agent = Agent.from_checkpoint(tiny_checkpoint(name, guidance_dim=15).path if name != "cil"
                                  else tiny_checkpoint(name).path)
    with pytest.raises(ValueError, match=r"observation speed=nan: expected a finite number \(m/s\)"):
        agent.act(_observation(speed=float("nan")))
    with pytest.raises(ValueError, match=r"observation command=9: expected a road option, one of \[-1, 1, 2, 3, 4\]"):
        agent.act(_observation(command=9))
    agent.act(_observation(command=4, speed=0))  # plain ints are road options too


# ----- 9. channels_last and render_backend checked where they are given
def test_channels_last_takes_a_switch_or_a_bool_and_render_backend_is_checked_at_once() -> None:
    import gymnasium

    import yawil  # noqa: F401  (registers the environments)
    from yawil.policy.runtime import resolve_runtime

    with pytest.raises(ValueError, match=r"channels_last: expected one of \('auto', 'on', 'off'\) or true/false, "
                                         "got 'maybe'"):
        resolve_runtime("cpu", "fp32", "maybe")  # type: ignore[arg-type]
    assert resolve_runtime("cpu", "fp32", False).channels_last is False
    assert resolve_runtime("cpu", "fp32", True).channels_last and resolve_runtime("cpu", "fp32", "auto").channels_last
    with pytest.raises(ValueError, match="render_backend must be one of 'software', 'opengl', got 'bogus'"):
        gymnasium.make("yawil/Square-v0", camera=False, render_backend="bogus")
