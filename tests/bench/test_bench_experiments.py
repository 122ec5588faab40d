"""Square experiments' tables and model choice, and a learned agent driven by the runner."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from yawil.bench.experiments import get_profile, noise_candidates, noise_experiment, table1_markdown
from yawil.bench.runner import AgentSpec, run_benchmark
from yawil.bench.suites import episodes


def test_table1_shape() -> None:
    md = table1_markdown({("full", "yaw-guided"): 32, ("subset1", "cil"): 18}, 32, "paper")
    lines = md.splitlines()
    assert lines[2] == "| Dataset | XY-guided | Yaw-guided | CIL | Sim-yaw IL |"
    assert lines[4] == "| Subset (1): road-option turns | — | — | 18 | — |"
    assert lines[6] == "| Full dataset | — | 32 | — | — |"
    assert "out of 32" in md


def test_noise_candidates(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="experiment square"):
        noise_candidates(tmp_path)
    cells = {"full/yaw-guided": 8, "full/cil": 8, "full/xy-guided": 8, "subset1/simyaw-guided": 7}
    (tmp_path / "table1.json").write_text(json.dumps({"n_tasks": 8, "cells": cells}))
    chosen, note = noise_candidates(tmp_path)
    assert sorted(chosen) == [("full", "cil"), ("full", "yaw-guided")] and "8/8" in note
    cells = {k: 0 for k in cells}
    (tmp_path / "table1.json").write_text(json.dumps({"n_tasks": 8, "cells": cells}))
    chosen, note = noise_candidates(tmp_path)
    assert sorted(chosen) == [("full", "cil"), ("full", "simyaw-guided"), ("full", "yaw-guided")]
    assert "no model passed" in note
    with pytest.raises(ValueError, match="unknown profile"):
        get_profile("huge")
    with pytest.raises(ValueError, match="noise seeds must be >= 1, got 0"):
        noise_experiment(tmp_path, "standard", seeds=0)


def test_learned_agent_episode_with_command_noise(tmp_path: Path, tiny_checkpoint: Any) -> None:
    import torch

    torch.set_num_threads(1)
    ckpt = tiny_checkpoint("cil", speed=(3.0, 2.0)).path  # untrained: it will not reach the goal, the loop is what is tested
    ep = episodes("square", routes="2", seeds=1)
    spec = AgentSpec(str(ckpt), command_noise_p=0.1)
    rec = run_benchmark(ep, spec, tmp_path / "a", progress=False).records[0]
    assert rec["camera"] is True  # on by default for a learned agent
    assert rec["agent"] == str(ckpt.resolve()) and rec["agent_options"]["command_noise_p"] == 0.1
    assert rec["reason"] in ("timeout", "collision_static", "collision_vehicle", "collision_pedestrian", None)
    with pytest.raises(ValueError, match="another --out"):
        run_benchmark(ep, AgentSpec(str(ckpt)), tmp_path / "a", progress=False)  # other noise options


@pytest.mark.slow
def test_learned_agent_is_deterministic_across_runs_and_workers(tmp_path: Path, tiny_checkpoint: Any) -> None:
    ckpt = tiny_checkpoint("yaw-guided", speed=(3.0, 2.0)).path
    eps = episodes("square", routes="2,9", seeds=1)
    spec = AgentSpec(str(ckpt), yaw_noise_deg=20.0)
    one = run_benchmark(eps, spec, tmp_path / "a", progress=False).records
    two = run_benchmark(eps, spec, tmp_path / "b", workers=2, progress=False).records
    by_route = {r["route_id"]: r for r in two}
    for r in one:
        assert by_route[r["route_id"]]["trajectory"] == r["trajectory"]
        assert by_route[r["route_id"]]["steps"] == r["steps"]


def test_models_trained_side_by_side_equal_those_trained_one_by_one(tmp_path: Path) -> None:
    """The standard profile trains two models at once in processes: that must not change a single weight."""
    from dataclasses import replace

    import torch

    from yawil.bench.experiments import train_all
    from yawil.data import write_synthetic_dataset

    data = tmp_path / "data"
    write_synthetic_dataset(data, episodes=4, frames=8, k=15, seed=0)
    p = replace(get_profile("standard"), epochs=1, batch_size=8, max_steps=2, train_workers=2, train_threads=1)
    jobs = [("full", "cil"), ("full", "yaw-guided")]
    logs: list[str] = []
    side = train_all(tmp_path / "side", {"full": data}, jobs, p, 0, logs.append)
    one = train_all(tmp_path / "one", {"full": data}, jobs, replace(p, train_workers=1), 0, logs.append)
    assert set(side) == set(one) == set(jobs)
    for key in jobs:
        a = torch.load(side[key], map_location="cpu", weights_only=False)["state_dict"]
        b = torch.load(one[key], map_location="cpu", weights_only=False)["state_dict"]
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), key
    assert (tmp_path / "side" / "models" / "full" / "cil" / ".done").exists()
    again = train_all(tmp_path / "side", {"full": data}, jobs, p, 0, logs.append)  # done: skipped, same files
    assert again == side and any("done, skipped" in line for line in logs)
