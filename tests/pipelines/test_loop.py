"""The whole loop, small: collect in the embedded simulator -> train -> agent from the checkpoint drives.

This is the end-to-end check of sim -> expert -> data -> train -> agent -> bench. It uses CIL (a small
network) so that it stays within seconds; YILRatt runs the same code path (see `make demo`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from yawil.agent import Agent
from yawil.bench.runner import AgentSpec, run_benchmark
from yawil.bench.suites import episodes
from yawil.data import DrivingDataset, read_manifest
from yawil.data.collect import collect
from yawil.learn.config import TrainConfig
from yawil.learn.loop import train


def test_collect_train_drive(tmp_path: Path) -> None:
    data = tmp_path / "data"
    summary = collect(data, town="town02", weathers="train", episodes=2, workers=1, seed=0, progress=False,
                      max_episode_frames=100, vehicles=(0, 0), pedestrians=(0, 0))  # fmt: skip
    manifest = read_manifest(data)
    assert len(manifest.episode_ids()) == 2
    assert summary.dataset_frames == manifest.frames > 60
    ds = DrivingDataset(data)
    sample = ds[0]
    assert tuple(sample["image"].shape) == (3, 88, 200)

    cfg = TrainConfig(model="cil", data=[str(data)], out=str(tmp_path / "run"), epochs=2, batch_size=32,
                      seed=0, progress=False, threads=1, val_fraction=0.5)  # fmt: skip
    result = train(cfg)
    losses = [m["train_loss"] for m in result.metrics]
    assert len(losses) == 2 and losses[-1] < losses[0]
    best = tmp_path / "run" / "best.pt"
    assert best.is_file()

    agent = Agent.from_checkpoint(best)
    eps = episodes("all", ["new-town-weather"], ["straight"], routes="19", seeds=1, weather_rule="cycle")
    run = run_benchmark(eps, AgentSpec(str(best)), tmp_path / "results", workers=1, progress=False)
    assert run.ran == 1
    rec = run.records[0]
    assert rec["agent"] == str(best.resolve()) or "agent" in rec
    assert np.isfinite(rec["km_driven"]) and rec["km_driven"] >= 0.0
    assert agent.name == "cil"
