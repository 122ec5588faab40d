"""K episodes per worker in one batched forward: an episode's record does not depend on K or on its batch-mates."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from yawil.bench.runner import AgentSpec, run_benchmark
from yawil.bench.suites import episodes
from yawil.sim.types import Control, Observation, Scenario

STEPS = 25  # each episode ends (as a world timeout) after this many steps, to keep the test short


class ShortWorld:
    """The embedded world, its episodes cut after STEPS steps (`done`, which the tracker reads as a timeout)."""

    def __init__(self) -> None:
        from yawil.sim import make_world

        self.world = make_world(backend="embedded")
        self.steps = 0

    def reset(self, scenario: Scenario, seed: int) -> Observation:
        self.steps = 0
        return self.world.reset(scenario, seed=seed)

    def step(self, control: Control) -> Observation:
        self.steps += 1
        obs = self.world.step(control)
        return dataclasses.replace(obs, done=True) if self.steps >= STEPS else obs

    def close(self) -> None:
        self.world.close()


def _records(out: Path, eps: list[Any], spec: AgentSpec, k: int) -> dict[str, dict[str, Any]]:
    summary = run_benchmark(eps, spec, out, progress=False, world_factory=ShortWorld, episodes_per_worker=k)
    return {f"{r['task']}/{r['weather']}/{r['route_id']}": {f: v for f, v in r.items() if f != "wall_s"}
            for r in summary.records}


def test_an_episode_drives_the_same_alone_and_among_others(tmp_path: Path, tiny_checkpoint: Any) -> None:
    """Four dense-traffic episodes of both towns, each alone in its batch (K=1), all four in three slots (a slot
    refilled), and in reverse order in two slots (other batch-mates, other batch sizes): every field of every
    record is the same."""
    path, _ = tiny_checkpoint("yaw-guided", dropout=0.0, aux=True, lead_stop=True)
    # ONNX Runtime fp32: rows bit-identical whatever the batch on the CPUs measured (docs/decisions.md)
    spec = AgentSpec(str(path), speed_control="stop", stop_release=1.0, engine="onnxruntime")
    eps = episodes("nocrash", conditions=["training", "new-town-weather"], tasks=["dense"], routes="0:2", seeds=1,
                   weather_rule="cycle")
    alone = _records(tmp_path / "alone", eps, spec, 1)
    three = _records(tmp_path / "three", eps, spec, 3)
    two = _records(tmp_path / "two", list(reversed(eps)), spec, 2)
    assert len(alone) == len(eps) and sum(r["steps"] for r in alone.values()) > 2 * len(eps)
    for key, rec in alone.items():
        assert three[key] == rec, key
        assert two[key] == rec, key


def test_act_batch_is_act_row_by_row(tiny_checkpoint: Any) -> None:
    """Agent.act_batch gives each slot the control `act` gives that episode alone, with its own state (route
    hint, noise stream seeded per episode, speed controller)."""
    from yawil.agent import Agent
    from yawil.sim import make_world

    path, _ = tiny_checkpoint("yaw-guided", dropout=0.0, aux=True, lead_stop=True)
    eps = episodes("nocrash", conditions=["training"], tasks=["regular"], routes="0:3", seeds=1, weather_rule="cycle")
    worlds = [make_world(backend="embedded") for _ in eps]
    obs = [w.reset(ep.scenario(True), seed=ep.world_seed) for w, ep in zip(worlds, eps, strict=True)]
    batch = Agent.from_checkpoint(path, slots=3, speed_control="stop", yaw_noise_deg=5.0, engine="onnxruntime")
    singles = [Agent.from_checkpoint(path, speed_control="stop", yaw_noise_deg=5.0, engine="onnxruntime") for _ in eps]
    for i, ep in enumerate(eps):
        batch.reset(seed=ep.world_seed, slot=i)
        singles[i].reset(seed=ep.world_seed)
    try:
        for _ in range(5):
            got = batch.act_batch(obs, [0, 1, 2])
            want = [a.act(o) for a, o in zip(singles, obs, strict=True)]
            assert got == want
            for i in range(3):
                out, ref = batch.outputs[i], singles[i].last
                assert out is not None and ref is not None
                np.testing.assert_array_equal(out.guidance, ref.guidance)
                assert out.target_speed == ref.target_speed
            obs = [w.step(c) for w, c in zip(worlds, got, strict=True)]
    finally:
        for w in worlds:
            w.close()
    with pytest.raises(ValueError, match="one distinct slot each"):
        batch.act_batch(obs[:2], [1, 1])
    with pytest.raises(ValueError, match="slots=0"):
        Agent.from_checkpoint(path, slots=0)
