"""Failures explained (yawil.explain.failures): a failed benchmark episode re-driven with its heat maps, the pure
numbers on synthetic inputs with known answers, and the refusals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from yawil.cli import main
from yawil.explain import failures as fl
from yawil.sim.semantic import CLASS_ID

KEY = "dense/training/WetNoon/1/0"  # town01, 50 vehicles: a car at full throttle rear-ends one within ~5 s


def _full_throttle(path: Path, **cfg: Any) -> Path:
    """An untrained YILRatt whose action head says steer 0, full throttle, no brake: it fails fast."""
    import torch

    from yawil import models
    from yawil.guidance import GuidanceConfig
    from yawil.policy.checkpoint import Norm, make_checkpoint, save_checkpoint

    model = models.create("yilratt", seed=0, **cfg)
    with torch.no_grad():
        model.action[2].weight.zero_()
        model.action[2].bias.copy_(torch.tensor([0.0, 10.0, -10.0]))
    dim = model.guidance_dim
    norm = Norm(2.5, 1.5, tuple(np.zeros(dim)), tuple(np.ones(dim)))
    save_checkpoint(make_checkpoint(model, norm, GuidanceConfig().to_dict(), {"model": "yilratt"}), path)
    return path


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A results folder of one failed episode, driven by `yawil bench`'s runner."""
    import torch

    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.bench.trace import find_episode

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("failures")
    ckpt = _full_throttle(root / "full.pt")
    out = root / "results"
    run_benchmark([find_episode(KEY, "nocrash")], AgentSpec(str(ckpt)), out, progress=False)
    return out


def _records(folder: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines()]


def _copy(results: Path, dest: Path, records: list[dict[str, Any]], **run: Any) -> Path:
    shutil.copytree(results, dest)
    (dest / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    if run:
        info = json.loads((dest / "run.json").read_text())
        (dest / "run.json").write_text(json.dumps({**info, **run}))
    return dest


def test_a_failure_is_redriven_and_written(results: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = _records(results)[0]
    assert not rec["success"] and rec["reason"] == "collision_vehicle"
    other = {**rec, "weather": "ClearNoon", "route_id": 0, "reason": "timeout", "collisions": []}  # never driven
    folder = _copy(results, tmp_path / "two", [rec, other])
    out = tmp_path / "out"
    assert main(["explain", "--failures", str(folder), "--max-failures", "1", "--seconds", "2", "--strip", "3",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"| {KEY} | collision_vehicle {rec['time_s']} s | collision_vehicle" in printed and " ok |" in printed
    data = json.loads((out / "failures.json").read_text())
    assert data["format"] == fl.FORMAT and data["meta"]["failed"] == 2 and data["meta"]["explained"] == 1
    assert data["meta"]["engine"] == rec["agent_options"]["engine"]
    (f,) = data["failures"]
    assert f["key"] == KEY and f["agrees"] and f["redriven"]["steps"] == rec["steps"]
    assert f["redriven"]["collisions"][0]["id"] == rec["collisions"][0]["id"]
    w = f["window"]
    assert w["last_step"] == rec["steps"] - 1 and w["last_step"] - w["first_step"] == 19  # 2 s: 20 frames
    assert all(len(w[k]) == 20 for k in fl.SERIES)
    assert f["layers"] == ["attention layer 1", "attention layer 2", "attention layer 3"]
    # the expert, shadowing a car that speeds into the one ahead, brakes for it; the agent never does
    b = f["braking"]
    assert b["expert_brakes"] > 0 and b["expert_brakes_for_hit"] > 0 and b["agent_brakes_when_expert_brakes"] == 0
    last = [r for r in f["classes"] if r["frames"] == "last 1 s"]
    assert [r["layer"] for r in last] == f["layers"] and all(r["count"] == 10 for r in last)
    assert all(r["share"]["vehicle"] > 0 and r["lift"]["vehicle"] >= 0 for r in last)
    assert (out / f["files"]["figure"]).stat().st_size > 0
    with np.load(out / f["files"]["frames"]) as z:
        assert z["images"].shape == (20, 88, 200, 3) and z["ids"].shape == (20, 88, 200)
        assert z["map_0"].shape[0] == 20 and z["steps"].tolist() == list(range(w["first_step"], w["last_step"] + 1))
    md = (out / "failures.md").read_text()
    assert f"## 1. {KEY}" in md and "as the record" in md and f"]({f['files']['figure']})" in md
    assert "| last 1 s (10) | attention layer 1 |" in md


def test_no_failure_says_so(results: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = _records(results)[0]
    ok = _copy(results, tmp_path / "ok", [{**rec, "success": True, "reason": None, "collisions": []}],
               agent=str(tmp_path / "gone.pt"))  # nothing to explain: the agent is never loaded
    assert main(["explain", "--failures", str(ok), "--out", str(tmp_path / "o1")]) == 0
    assert "no failed episode to explain" in capsys.readouterr().out
    data = json.loads((tmp_path / "o1" / "failures.json").read_text())
    assert data["failures"] == [] and data["meta"]["failed"] == 0
    assert "No failed episode" in (tmp_path / "o1" / "failures.md").read_text()
    assert main(["explain", "--failures", str(results), "--failure-reasons", "collision_pedestrian,timeout",
                 "--out", str(tmp_path / "o2")]) == 0
    assert "no failed episode with reason collision_pedestrian, timeout" in capsys.readouterr().out
    assert json.loads((tmp_path / "o2" / "failures.json").read_text())["meta"]["failed"] == 1


def test_an_agent_that_cannot_be_loaded_is_one_line(results: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    recs = _records(results)
    gone = _copy(results, tmp_path / "gone", recs, agent=str(tmp_path / "gone.pt"))
    assert main(["explain", "--failures", str(gone), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "gone.pt" in err and "give --checkpoint" in err
    assert not (tmp_path / "o").exists()  # refused before anything was written
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    assert main(["explain", "--failures", str(gone), "--checkpoint", str(tmp_path / "junk.pt"),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "junk.pt" in err and "cannot be loaded" in err
    expert = _copy(results, tmp_path / "expert", recs, agent="expert")
    assert main(["explain", "--failures", str(expert), "--out", str(tmp_path / "o")]) == 2
    assert "no heat maps" in capsys.readouterr().err
    assert main(["explain", "--failures", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "no run.json" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--checkpoint is required"):
        main(["explain", "--frames", str(tmp_path), "--out", str(tmp_path / "o")])


def test_the_agent_drives_with_the_records_options(tmp_path: Path) -> None:
    ckpt = _full_throttle(tmp_path / "aux.pt", aux=True, lead_stop=True)
    info = {"agent": str(ckpt), "agent_options": {"speed_control": "stop", "stop_release": 10.0, "stop_creep": 3.0,
                                                  "yaw_noise_deg": 0.0, "engine": "torch-fp16"}}
    of = fl.load_agent_of(info)
    drive = of.agent.drive
    assert (drive.speed_control, drive.stop_release, drive.stop_creep) == ("stop", 10.0, 3.0)
    assert of.agent.attention and of.notes and "torch-fp16 does not run here" in of.notes[0]  # CUDA's, on a CPU
    other = fl.load_agent_of({**info, "agent_sha256": "0" * 64}, checkpoint=str(ckpt))
    assert any("not the checkpoint that drove" in n for n in other.notes)


def test_agreement() -> None:
    rec = {"success": False, "reason": "collision_vehicle", "steps": 100, "time_s": 10.0,
           "collisions": [{"type": "vehicle", "id": 7, "rear_end": True}]}
    ok, text = fl.agreement(rec, {**rec, "steps": 104, "time_s": 10.4})
    assert ok and "as the record (+4 steps)" in text and "hit vehicle 7 (rear-end)" in text
    for other in ({**rec, "steps": 100 + fl.AGREE_STEPS + 1}, {**rec, "reason": "timeout", "collisions": []},
                  {**rec, "collisions": [{"type": "vehicle", "id": 8}]}, {**rec, "success": True, "reason": None}):
        ok, text = fl.agreement(rec, other)
        assert not ok and "differs from the record" in text and "the record: collision_vehicle at 10.0 s" in text


def _series(n: int) -> dict[str, list[Any]]:
    s: dict[str, list[Any]] = {k: [0.0] * n for k in fl.SERIES}
    s["step"] = list(range(n))
    s["time"] = [round(0.1 * i, 2) for i in range(n)]
    s["command"] = [4] * n  # LANEFOLLOW
    s["expert_reason"] = ["cruise"] * n
    s["expert_agent"] = [None] * n
    s["target_speed"] = [8.0] * n
    s["expert_target_speed"] = [8.0] * n
    return s


def test_braking_summary_known_answers() -> None:
    s = _series(30)
    for i in range(20, 30):  # the expert brakes for vehicle 5 over the last second; the agent on 3 of those
        s["expert_brake"][i], s["expert_reason"][i], s["expert_agent"][i], s["expert_target_speed"][i] = \
            1.0, "vehicle", 5, 0.0
    s["expert_brake"][15], s["expert_reason"][15] = 0.5, "curve"  # braking for a bend: not a hazard
    for i in (27, 28, 29):
        s["brake"][i] = 0.6
    b = fl.braking_summary(s, 10, hit=5)
    assert b["frames"] == 20 and b["expert_brakes"] == 10 and b["expert_from_s"] == pytest.approx(1.0)
    assert b["expert_reasons"] == {"vehicle": 10} and b["expert_brakes_for_hit"] == 10
    assert b["agent_brakes_when_expert_brakes"] == 3 and b["agent_brake_share"] == pytest.approx(0.3)
    assert b["first_agent_brake_s"] == pytest.approx(0.3)
    assert b["agent_target_mean"] == 8.0 and b["expert_target_mean"] == 0.0 and b["at_first"]["expert_target"] == 0
    assert b["at_last"]["agent_brake"] == 0.6 and b["at_last"]["expert_target"] == 0.0 and b["min_speed"] == 0.0
    assert "braked on 3 of them" in fl.braking_text(b) and "at the last frame 8.0 m/s / 0.0 m/s" in fl.braking_text(b)
    quiet = fl.braking_summary(_series(30), 0)
    assert quiet["expert_brakes"] == 0 and "expert_from_s" not in quiet and "would not have braked" in \
        fl.braking_text(quiet)


def test_class_rows_known_answers() -> None:
    n, veh, road = 20, CLASS_ID["vehicle"], CLASS_ID["road"]
    ids = np.full((88, 200), road, dtype=np.uint8)
    ids[40:60, 80:120] = veh
    on_vehicle = (ids == veh).astype(np.float32)  # all the mass on the vehicle, at image resolution
    s = _series(25)
    for i in range(20, 25):
        s["expert_brake"][i], s["expert_reason"][i] = 1.0, "vehicle"
    kept = fl.Kept(("layer 1", "layer 2"), s, list(range(5, 25)), [np.zeros((88, 200, 3), np.uint8)] * n, [ids] * n,
                   [[on_vehicle, np.ones((6, 13), np.float32)]] * n)
    rows = fl.class_rows(kept)
    assert [(r["frames"], r["count"], r["layer"]) for r in rows] == [
        ("last 1 s", 10, "layer 1"), ("last 1 s", 10, "layer 2"), ("expert brakes", 5, "layer 1"),
        ("expert brakes", 5, "layer 2")]
    share = float((ids == veh).mean())
    assert rows[0]["lift"]["vehicle"] == pytest.approx(1 / share, abs=0.01) and rows[0]["mass"]["vehicle"] == 1.0
    assert rows[0]["lift"]["passable"] == 0.0 and rows[0]["lift"]["pedestrian"] is None  # absent: no lift
    assert rows[1]["lift"]["vehicle"] == pytest.approx(1.0) == rows[1]["lift"]["passable"]  # a uniform map
    assert "| expert brakes (5) | layer 1 |" in fl.class_table(rows)
