"""Behaviour identity (issue 15, "Done when"), checked against references stored in tests/fixtures/identity/:

- the expert's benchmark records: 6 of the 250 single-seed episodes that `benchmarks/identity_expert.py`
  checks in full (`expert_records.json`: one SHA-256 per episode of the record without wall time);
- rendered frames bit-identical: both towns, five weathers, at the reset pose and 5 steps later, with traffic
  (`frames.json`: SHA-256 of each image);
- a fixed checkpoint (made from seed 0 like `tiny_checkpoint`) gives the same actions on fixed frames through
  the agent, `yawil.explain` and the ONNX export (`actions.json`, to 1e-6).

A reference is rewritten only on purpose, when behaviour is meant to change:

    .venv/bin/python tests/test_identity.py frames actions        # then benchmarks/identity_expert.py --write
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "identity"
BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"

# ----- the expert's records -------------------------------------------------------------------------------------

# The shortest episode of each task (wall time of the reference run), both towns, the dynamic ones with traffic,
# one that times out; ~20 s together.
RECORD_KEYS = (
    "straight/training/ClearNoon/24/0",
    "one_turn/new-town-weather/WetCloudyNoon/4/0",
    "one_turn/new-town-weather/SoftRainSunset/13/0",  # a timeout
    "navigation/training/ClearSunset/3/0",
    "regular/new-town-weather/WetCloudyNoon/20/0",
    "dense/new-town-weather/SoftRainSunset/3/0",
)


def _identity_expert() -> Any:
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import identity_expert
    finally:
        sys.path.remove(str(BENCHMARKS))
    return identity_expert


def test_expert_records_match_the_reference() -> None:
    from yawil.bench.records import episode_key
    from yawil.bench.runner import AgentSpec, EpisodeDriver

    ie = _identity_expert()
    want = ie.load_reference()
    eps = {ep.key: ep for ep in ie.reference_episodes()}
    assert len(eps) == len(want) == 250
    driver = EpisodeDriver(AgentSpec("expert"), camera=False)
    try:
        for key in RECORD_KEYS:
            rec = driver.run(eps[key])
            assert episode_key(rec) == key
            assert ie.record_digest(rec) == want[key], f"{key}: the record differs from the reference"
    finally:
        driver.close()


# ----- rendered frames ------------------------------------------------------------------------------------------

# (town, weather, seed): reset with 10 vehicles and 10 pedestrians, then 5 steps of straight driving.
FRAME_CASES = (
    ("town01", "ClearNoon", 0),
    ("town01", "HardRainNoon", 1),
    ("town01", "SoftRainSunset", 5),
    ("town02", "WetCloudyNoon", 2),
    ("town02", "ClearSunset", 3),
    ("town02", "WetNoon", 4),
)
FRAME_STEPS = 5


def frame_digests() -> dict[str, list[str]]:
    from yawil.sim.town.world import EmbeddedWorld
    from yawil.sim.types import Control, Scenario

    world = EmbeddedWorld()
    out: dict[str, list[str]] = {}
    try:
        for town, weather, seed in FRAME_CASES:
            sc = Scenario(town=town, weather=weather, vehicles=10, pedestrians=10, camera=True, min_route_length=50.0)
            obs = world.reset(sc, seed)
            digests = [hashlib.sha256(np.ascontiguousarray(obs.image).tobytes()).hexdigest()]
            for _ in range(FRAME_STEPS):
                obs = world.step(Control(steer=0.0, throttle=0.5, brake=0.0))
            digests.append(hashlib.sha256(np.ascontiguousarray(obs.image).tobytes()).hexdigest())
            out[f"{town}/{weather}/{seed}"] = digests
    finally:
        world.close()
    return out


def test_rendered_frames_match_the_reference() -> None:
    want = json.loads((FIXTURES / "frames.json").read_text())
    assert frame_digests() == want


# ----- a fixed checkpoint's actions -----------------------------------------------------------------------------

K = 4
GC: dict[str, Any] = {"spacing": 2.0, "count": K, "reference": "route"}
MODELS: dict[str, dict[str, Any]] = {"cil": {}, "yaw-guided": {"guidance_dim": K}}
TOL = 1e-6


def _observations() -> list[Any]:
    """Three fixed frames: seeded images on a route that runs east then turns left, at different poses."""
    from yawil.sim.types import Observation, Pose, RoadOption, Route

    straight = np.stack([np.arange(0.0, 60.0), np.zeros(60)], axis=1)
    turn = np.stack([np.full(40, 59.0), np.arange(1.0, 41.0)], axis=1)
    xy = np.concatenate([straight, turn])
    lane_yaw = np.concatenate([np.zeros(60), np.full(40, np.pi / 2)])
    cases = ((RoadOption.LANEFOLLOW, 3.0, Pose(10.0, 0.3, 0.05), 10), (RoadOption.LEFT, 6.5, Pose(50.0, -0.4, -0.1), 50),
             (RoadOption.STRAIGHT, 0.0, Pose(59.2, 12.0, 1.5), 72))  # fmt: skip
    out = []
    for i, (command, speed, pose, index) in enumerate(cases):
        route = Route(xy=xy, options=np.full(len(xy), int(command), np.int8), lane_yaw=lane_yaw)
        image = np.random.default_rng(100 + i).integers(0, 256, (88, 200, 3), dtype=np.uint8)
        out.append(Observation(
            image=image, speed=speed, pose=pose, route=route, route_index=index, command=command, events=(),
            time=0.1 * i, frame=i, done=False, distance_driven=0.0, town="town01", bounds=(-10.0, -10.0, 110.0, 60.0),
            weather="ClearNoon",
        ))  # fmt: skip
    return out


def checkpoint_actions(folder: Path) -> dict[str, dict[str, list[list[float]]]]:
    """Per model: the agent's network actions and controls, explain's controls and ONNX's actions per frame."""
    import onnxruntime as ort
    import torch

    from yawil.agent import Agent
    from yawil.explain.attention import explain_observation
    from yawil.learn.export import export_onnx

    torch.set_num_threads(1)
    out: dict[str, dict[str, list[list[float]]]] = {}
    for name, cfg in MODELS.items():
        path = _make_checkpoint(folder, name, cfg)
        agent = Agent.from_checkpoint(path, precision="fp32")
        explainer = Agent.from_checkpoint(path, precision="fp32")
        session = ort.InferenceSession(str(export_onnx(path, folder / f"{name}.onnx")),
                                       providers=["CPUExecutionProvider"])
        agent.reset()
        explainer.reset()
        onnx_agent = Agent.from_checkpoint(path, precision="fp32")  # only its inputs: the same preprocessing
        onnx_agent.reset()
        rows: dict[str, list[list[float]]] = {"agent_actions": [], "agent_control": [], "explain_control": [],
                                              "onnx_actions": []}
        for obs in _observations():
            c = agent.act(obs)
            assert agent.last is not None
            rows["agent_actions"].append([float(v) for v in agent.last.actions])
            rows["agent_control"].append([c.steer, c.throttle, c.brake])
            e = explain_observation(explainer, obs)
            rows["explain_control"].append([float(e.steer), float(e.throttle), float(e.brake)])
            x, _, _ = onnx_agent.inputs(obs)
            feed = {i.name: x[i.name].numpy() for i in session.get_inputs()}  # type: ignore[union-attr]
            rows["onnx_actions"].append([float(v) for v in session.run(["actions"], feed)[0][0]])
        out[name] = rows
    return out


def _make_checkpoint(folder: Path, name: str, cfg: dict[str, Any]) -> Path:
    """As conftest's `tiny_checkpoint(name, guidance=GC, spread=True, **cfg)`: the model of seed 0."""
    from yawil import models
    from yawil.policy.checkpoint import Norm, make_checkpoint, save_checkpoint

    model = models.create(name, seed=0, **cfg)
    dim = model.guidance_dim if model.guidance else 0
    norm = Norm(2.5, 1.5, tuple(np.linspace(-0.1, 0.1, dim)), tuple(np.linspace(0.5, 1.5, dim)))
    path = folder / f"{name}.pt"
    save_checkpoint(make_checkpoint(model, norm, GC, {"model": name}), path)
    return path


def test_checkpoint_actions_match_the_reference(tmp_path: Path) -> None:
    want = json.loads((FIXTURES / "actions.json").read_text())
    got = checkpoint_actions(tmp_path)
    assert sorted(got) == sorted(want)
    for name in want:
        for field in ("agent_actions", "agent_control", "explain_control"):
            np.testing.assert_allclose(got[name][field], want[name][field], rtol=0, atol=TOL, err_msg=f"{name} {field}")
        # the same network through onnxruntime: the stored torch actions (float32 kernels differ slightly)
        np.testing.assert_allclose(got[name]["onnx_actions"], want[name]["agent_actions"], rtol=0, atol=1e-5,
                                   err_msg=f"{name} onnx")
        np.testing.assert_allclose(got[name]["onnx_actions"], want[name]["onnx_actions"], rtol=0, atol=TOL,
                                   err_msg=f"{name} onnx against its own reference")
        # explain drives the agent: its controls are the agent's
        np.testing.assert_array_equal(got[name]["explain_control"], got[name]["agent_control"])


if __name__ == "__main__":  # rewrite references: python tests/test_identity.py frames actions
    import tempfile

    from yawil.fileio import write_json_atomic

    FIXTURES.mkdir(parents=True, exist_ok=True)
    if "frames" in sys.argv[1:]:
        write_json_atomic(FIXTURES / "frames.json", frame_digests())
    if "actions" in sys.argv[1:]:
        with tempfile.TemporaryDirectory() as tmp:
            write_json_atomic(FIXTURES / "actions.json", checkpoint_actions(Path(tmp)))
    if not {"frames", "actions"} & set(sys.argv[1:]):
        pytest.fail("name what to rewrite: frames, actions", pytrace=False)
