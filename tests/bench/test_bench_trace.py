"""`yawil trace`: one episode frame by frame, the agent beside the shadowing expert."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from yawil.bench.runner import AgentSpec
from yawil.bench.trace import COLUMNS, find_episode, trace_episode


def test_the_expert_shadowing_itself_agrees_on_every_frame(tmp_path: Path) -> None:
    ep = find_episode("straight/training/ClearNoon/0/0")
    assert (ep.task, ep.condition, ep.weather, ep.route_id, ep.seed) == ("straight", "training", "ClearNoon", 0, 0)
    res = trace_episode(ep, AgentSpec("expert"), tmp_path / "t.csv", camera=False)
    with open(tmp_path / "t.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == COLUMNS and len(rows) == res.frames > 50 and res.success
    for r in rows:  # the same deterministic driver in the same state: the same decision
        assert (r["steer"], r["throttle"], r["brake"]) == (r["expert_steer"], r["expert_throttle"], r["expert_brake"])
    assert rows[-1]["expert_reason"] == "goal" and float(rows[-1]["speed"]) < float(rows[len(rows) // 2]["speed"])


def test_episode_keys_are_checked() -> None:
    with pytest.raises(ValueError, match="expected task/condition/weather/route/seed"):
        find_episode("straight/training/0")
    with pytest.raises(ValueError, match="not an episode of suite"):
        find_episode("straight/training/MidRainyNoon/0/0")  # a test weather, not a training one
