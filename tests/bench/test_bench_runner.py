"""The runner's loop and resume on a scripted world (the real world's tests are in test_bench_episode.py)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from yawil.bench.records import EPISODES_FILE
from yawil.bench.runner import AgentSpec, run_benchmark
from yawil.bench.suites import episodes
from yawil.sim.types import Control, Event, EventKind, Observation, Pose, RoadOption, Route, Scenario


class LineWorld:
    """The ego moves `throttle * 2` m per step along a straight 60 m route; a wall waits at x=crash_at."""

    def __init__(self, crash_at: float | None = None) -> None:
        self.crash_at = crash_at
        self.resets: list[int] = []

    def reset(self, scenario: Scenario, seed: int) -> Observation:
        self.resets.append(seed)
        xy = np.stack([np.arange(0, 61, 1.0), np.zeros(61)], axis=1)
        self.route = Route(xy=xy, options=np.full(61, 4, np.int8), lane_yaw=np.zeros(61))
        self.x, self.t, self.frame = 0.0, 0.0, 0
        return self._obs(())

    def _obs(self, events: tuple[Event, ...]) -> Observation:
        return Observation(
            image=None, speed=2.0, pose=Pose(self.x, 0.0, 0.0), route=self.route, route_index=int(self.x),
            command=RoadOption.LANEFOLLOW, events=events, time=self.t, frame=self.frame, done=False,
            distance_driven=self.x, town="town01", bounds=(0, -5, 60, 5), weather="ClearNoon",
        )

    def step(self, control: Control) -> Observation:
        self.x += 2.0 * control.throttle
        self.t += 0.1
        self.frame += 1
        ev: tuple[Event, ...] = ()
        if self.frame == 3:
            ev = (Event(EventKind.LANE_INVASION, self.t, self.x, 0, detail="opposite_lane"),)
        if self.crash_at is not None and self.x >= self.crash_at:
            ev = (Event(EventKind.COLLISION, self.t, self.x, 0.0, other_id=None, other_type="static"),)
        return self._obs(ev)

    def close(self) -> None:
        pass


class Gas:
    def __init__(self, throttle: float = 1.0) -> None:
        self.throttle = throttle

    def reset(self) -> None:
        pass

    def act(self, obs: Observation) -> Control:
        return Control(0.0, self.throttle, 0.0)


def test_success_collision_timeout_and_resume(tmp_path: Path) -> None:
    eps = episodes("corl2017", conditions=["training"], tasks=["straight"], routes="0:3", seeds=1, weather_rule="cycle")
    world = LineWorld()
    spec = AgentSpec("scripted")
    s = run_benchmark(eps[:2], spec, tmp_path, world_factory=lambda: world, agent_factory=lambda seed: Gas(),
                      progress=False)
    assert (s.ran, s.skipped, s.successes) == (2, 0, 2)
    assert world.resets == [0, 1]  # world seed = 1000 * seed + route id
    rec = s.records[0]
    assert rec["success"] and rec["reason"] is None and rec["lane_opposite"] == 1
    assert rec["steps"] == 29 and rec["time_s"] == pytest.approx(2.9)  # at x = 58 m the goal (60 m) is 2 m away
    assert {"suite", "task", "condition", "route_id", "town", "weather", "seed", "agent", "km_driven",
            "lane_offroad", "red_lights", "lights_passed", "collisions", "trajectory", "route_xy"} <= set(rec)
    # resume: the first two are skipped, the third runs; a crash ends it with the collision's kind
    world2 = LineWorld(crash_at=10.0)
    s2 = run_benchmark(eps, spec, tmp_path, world_factory=lambda: world2, agent_factory=lambda seed: Gas(),
                       progress=False)
    assert (s2.ran, s2.skipped, s2.successes) == (1, 2, 0)
    assert world2.resets == [2]
    assert s2.records[0]["reason"] == "collision_static" and s2.records[0]["collisions"][0]["type"] == "static"
    lines = (tmp_path / EPISODES_FILE).read_text().splitlines()
    assert [json.loads(x)["route_id"] for x in lines] == [0, 1, 2]


def test_timeout_when_the_agent_does_not_move(tmp_path: Path) -> None:
    ep = episodes("corl2017", conditions=["training"], tasks=["straight"], routes="0", seeds=1)[0]
    s = run_benchmark([ep], AgentSpec("scripted"), tmp_path, world_factory=LineWorld,
                      agent_factory=lambda seed: Gas(0.0), progress=False)
    rec = s.records[0]
    assert rec["reason"] == "timeout" and rec["time_s"] == pytest.approx(ep.timeout_s, abs=0.1)


def test_an_agent_that_stops_for_good_is_blocked_one_that_creeps_is_not(tmp_path: Path) -> None:
    """The `blocked` end: BLOCKED_S without PROGRESS_M of route progress, long before NoCrash's timeout."""
    from yawil.bench.metrics import BLOCKED_S

    ep = episodes("nocrash", conditions=["training"], tasks=["empty"], routes="0", seeds=1, weather_rule="cycle")[0]
    assert ep.timeout_s > 2 * BLOCKED_S
    s = run_benchmark([ep], AgentSpec("scripted"), tmp_path / "a", world_factory=LineWorld,
                      agent_factory=lambda seed: Gas(0.0), progress=False)
    rec = s.records[0]
    assert rec["reason"] == "blocked" and rec["time_s"] == pytest.approx(BLOCKED_S)
    assert rec["max_stall_s"] == pytest.approx(BLOCKED_S)
    # 1.2 cm a step: a metre every 8.4 s, slow but moving on: it reaches the goal
    s = run_benchmark([ep], AgentSpec("scripted"), tmp_path / "b", world_factory=LineWorld,
                      agent_factory=lambda seed: Gas(0.006), progress=False)
    assert s.records[0]["success"] and s.records[0]["max_stall_s"] < 10.0


def test_bad_agent_and_workers(tmp_path: Path) -> None:
    eps = episodes("corl2017", conditions=["training"], tasks=["straight"], routes="0", seeds=1)
    with pytest.raises(ValueError, match="checkpoint"):
        run_benchmark(eps, AgentSpec(str(tmp_path / "missing.pt")), tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="workers"):
        run_benchmark(eps, AgentSpec("expert"), tmp_path / "b", workers=0, progress=False)
    with pytest.raises(ValueError, match="not to the expert"):
        run_benchmark(eps, AgentSpec("expert", yaw_noise_deg=10), tmp_path / "c", progress=False)
    (tmp_path / "x.pt").write_bytes(b"")
    with pytest.raises(ValueError, match="--yaw-noise 'both'"):
        AgentSpec(str(tmp_path / "x.pt"), yaw_noise_deg=10, yaw_noise_mode="both").validate()
    # a reading is part of the agent's options (so a resume cannot mix readings) only where its noise is on
    # and so is the engine with its precision (yawil.policy.engine), which changes the numbers
    engine = AgentSpec("a").engine_label()
    assert engine in ("torch-bf16", "onnxruntime-fp32")
    assert AgentSpec("a", yaw_noise_deg=10, yaw_noise_mode="independent").options() == {
        "yaw_noise_deg": 10, "command_noise_p": 0.0, "yaw_noise_mode": "independent", "engine": engine}
    assert AgentSpec("a", yaw_noise_mode="independent").options() == {"yaw_noise_deg": 0.0, "command_noise_p": 0.0,
                                                                       "engine": engine}
    # the expert's settings: named in the options (a resume cannot mix experts), for the expert only
    spec = AgentSpec("expert", expert_args=("comfort_decel=1.5",)).validate()
    assert spec.options()["expert"] == {"comfort_decel": 1.5}
    assert spec.build(0).config.comfort_decel == 1.5  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="unknown expert setting"):
        AgentSpec("expert", expert_args=("nope=1",)).validate()
    with pytest.raises(ValueError, match="--agent expert only"):
        AgentSpec(str(tmp_path / "x.pt"), expert_args=("comfort_decel=1.5",)).validate()


def test_the_eval100_preset_is_the_fixed_recipe_comparison_set() -> None:
    from yawil.bench.cli import _split, apply_preset
    from yawil.bench.suites import episodes
    from yawil.cli import build_parser

    args = build_parser().parse_args(["bench", "--preset", "eval100", "--agent", "expert"])
    apply_preset(args)
    eps = episodes(args.suite, _split(args.condition), None, args.routes, args.seeds, weather_rule=args.weather_rule)
    assert len(eps) == 100 and {e.seed for e in eps} == {0} and args.weather_rule == "cycle"
    assert {e.task for e in eps} == {"straight", "one_turn", "navigation", "regular", "dense"}
    assert {e.condition for e in eps} == {"training", "new-town-weather"}
    clash = build_parser().parse_args(["bench", "--preset", "eval100", "--seeds", "3"])
    with pytest.raises(ValueError, match="fixes --seeds"):
        apply_preset(clash)
    plain = build_parser().parse_args(["bench"])
    apply_preset(plain)
    assert plain.suite == "nocrash"


def test_record_writes_a_video_per_episode(tmp_path: Path) -> None:
    """`yawil bench --record` (it crashed on the bird's-eye map's bare Figure: issue "Every door a clear error")."""
    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.bench.suites import episodes

    eps = episodes("corl2017", ["training"], ["straight"], routes="0:1", seeds=1, weather_rule="cycle")
    run_benchmark(eps, AgentSpec("expert"), tmp_path / "r", record=True, progress=False)
    videos = list((tmp_path / "r" / "videos").iterdir())
    assert len(videos) == 1 and videos[0].stat().st_size > 10_000


def test_the_agents_device(tmp_path: Path, tiny_checkpoint: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """--device: the model on that device, named in the options only when not cpu (earlier records still
    match), cuda without a CUDA device refused in one line before any episode."""
    import torch

    from yawil.bench.runner import agent_device
    from yawil.cli import main

    ckpt = str(tiny_checkpoint("cil").path)
    spec = AgentSpec(ckpt, device="cpu").validate()
    assert "device" not in spec.options() and spec.options() == AgentSpec(ckpt).options()
    agent = spec.build(0)
    assert {p.device.type for p in agent.model.parameters()} == {"cpu"}  # type: ignore[attr-defined]
    assert AgentSpec(ckpt, device="cuda").options()["device"] == "cuda"
    assert "device" not in AgentSpec("expert", device="cuda").options()  # the expert has no model
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert (agent_device("cpu"), agent_device("auto")) == ("cpu", "cpu")
    with pytest.raises(ValueError, match=r"^--device cuda: torch sees no CUDA device"):
        AgentSpec(ckpt, device="cuda").validate()
    with pytest.raises(ValueError, match="expected cpu or cuda"):
        AgentSpec(ckpt, device="gpu").validate()
    with pytest.raises(SystemExit) as stop:
        main(["bench", "--suite", "corl2017", "--agent", ckpt, "--device", "cuda", "--routes", "0", "--seeds", "1",
              "--out", str(tmp_path / "r"), "--no-progress"])
    assert str(stop.value) == "yawil bench: --device cuda: torch sees no CUDA device here; use --device cpu (or auto)"
    assert not (tmp_path / "r").exists()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert agent_device("auto") == "cuda"
