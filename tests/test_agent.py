"""The driving agent: training preprocessing on Observations, stored normalisation, branches, attention,
post-processing, noise options."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from yawil.agent import Agent, PostProcess, SpeedControl
from yawil.guidance import GuidanceConfig, compute_guidance
from yawil.learn.sampling import prepare_batch
from yawil.policy.runtime import resolve_runtime
from yawil.sim.types import Control, Observation, Pose, RoadOption, Route

torch.set_num_threads(2)
K = 4
GC: dict[str, Any] = {"spacing": 2.0, "count": K, "reference": "route"}


def observation(command: RoadOption = RoadOption.LANEFOLLOW, speed: float = 3.0, seed: int = 0) -> Observation:
    """The ego 10 m along a straight 100 m route heading east, then a left turn."""
    straight = np.stack([np.arange(0.0, 60.0), np.zeros(60)], axis=1)
    turn = np.stack([np.full(40, 59.0), np.arange(1.0, 41.0)], axis=1)
    xy = np.concatenate([straight, turn])
    lane_yaw = np.concatenate([np.zeros(60), np.full(40, np.pi / 2)])
    route = Route(xy=xy, options=np.full(len(xy), int(command), np.int8), lane_yaw=lane_yaw)
    image = np.random.default_rng(seed).integers(0, 256, (88, 200, 3), dtype=np.uint8)
    return Observation(
        image=image, speed=speed, pose=Pose(10.0, 0.3, 0.05), route=route, route_index=10, command=command,
        events=(), time=0.0, frame=0, done=False, distance_driven=0.0, town="town01",
        bounds=(-10.0, -10.0, 110.0, 60.0), weather="ClearNoon",
    )  # fmt: skip


def test_guided_agent_uses_training_preprocessing(tiny_checkpoint: Any) -> None:
    path, norm = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K, dropout=0.0)
    agent = Agent.from_checkpoint(path, precision="fp32")
    agent.reset()
    obs = observation()
    x, g_raw, cmd = agent.inputs(obs)
    assert cmd is None and x["command"] is None and g_raw is not None
    expected, _ = compute_guidance(
        obs.route.xy, obs.route.lane_yaw, (10.0, 0.3), 0.05, obs.bounds, GuidanceConfig(**GC)
    )
    np.testing.assert_allclose(g_raw, expected.yaw, atol=0)
    # the same frame as a dataset sample goes through the trainer's preprocessing
    sample = {
        "image": torch.from_numpy(obs.image).permute(2, 0, 1)[None],
        "speed": torch.tensor([[obs.speed]], dtype=torch.float32),
        "action": torch.zeros(1, 3),
        "command": torch.zeros(1, dtype=torch.int64),
        "guidance_yaw": torch.from_numpy(g_raw.copy())[None],
    }
    b = prepare_batch(sample, norm, "yaw", False, resolve_runtime("cpu", "fp32", "auto"))
    assert x["image"] is not None and x["speed"] is not None
    assert torch.equal(x["image"], b.image) and torch.equal(x["speed"], b.speed)
    assert x["guidance"] is not None and b.guidance is not None and torch.equal(x["guidance"], b.guidance)
    assert float(x["speed"]) == pytest.approx((3.0 - 2.5) / 1.5)

    control = agent.act(obs)
    assert isinstance(control, Control) and control.validate() is control
    assert agent.last is not None and agent.last.control == control
    with torch.no_grad():
        ref = agent.model(b.image, b.speed, guidance=b.guidance)
    np.testing.assert_allclose(agent.last.actions, ref.actions[0].numpy(), atol=1e-6)
    assert agent.last.speed == pytest.approx(float(ref.speed[0, 0]) * 1.5 + 2.5, abs=1e-5)
    assert agent.states[0].hint is not None  # the projection hint is kept for the next frame


def test_branched_agent_follows_the_command(tiny_checkpoint: Any) -> None:
    path, _ = tiny_checkpoint("cil", guidance=GC, spread=True, dropout=0.0)
    agent = Agent.from_checkpoint(path, precision="fp32")
    for option, index in ((RoadOption.LEFT, 1), (RoadOption.STRAIGHT, 3), (RoadOption.VOID, 0)):
        agent.act(observation(option))
        assert agent.last is not None and agent.last.command == index and agent.last.guidance is None
        assert agent.last.branches is not None
        np.testing.assert_allclose(agent.last.actions, agent.last.branches[index], atol=0)


def test_yilratt_agent_exposes_attention(tiny_checkpoint: Any) -> None:
    path, _ = tiny_checkpoint("yilratt", guidance=GC, spread=True, guidance_dim=K)
    agent = Agent.from_checkpoint(path)  # default precision: bf16 where the CPU has it
    agent.act(observation())
    assert agent.last is not None and len(agent.last.attention) >= 1
    for a in agent.last.attention:
        assert a.ndim == 2 and a.dtype == np.float32 and abs(float(a.sum()) - 1.0) < 1e-2


def test_post_processing() -> None:
    post = PostProcess(brake_threshold=0.1, max_speed=8.0)
    assert post(np.array([1.7, 0.6, 0.05]), 3.0) == Control(1.0, 0.6, 0.0)  # clip; small brake dropped
    assert post(np.array([-0.2, 0.6, 0.5]), 3.0) == Control(-0.2, 0.0, 0.5)  # braking cuts throttle
    assert post(np.array([0.0, 0.9, 0.0]), 9.0) == Control(0.0, 0.0, 0.0)  # speed guard
    assert post(np.array([np.nan, -1.0, 2.0]), 1.0) == Control(0.0, 0.0, 1.0)
    assert PostProcess(exclusive_brake=False)(np.array([0.0, 0.6, 0.5]), 1.0) == Control(0.0, 0.6, 0.5)
    with pytest.raises(ValueError, match="brake_threshold"):
        PostProcess(brake_threshold=2.0)


def test_noise_options_are_seeded(tiny_checkpoint: Any) -> None:
    path, _ = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K)
    clean = Agent.from_checkpoint(path, precision="fp32")
    noisy = Agent.from_checkpoint(path, precision="fp32", yaw_noise_deg=20.0, seed=3)
    obs = observation()
    g0 = clean.inputs(obs)[1]
    g1 = noisy.inputs(obs)[1]
    noisy.reset(seed=3)
    g2 = noisy.inputs(obs)[1]
    assert g0 is not None and g1 is not None and g2 is not None
    assert not np.allclose(g0, g1) and np.array_equal(g1, g2)

    cpath, _ = tiny_checkpoint("cil", guidance=GC, spread=True)
    always = Agent.from_checkpoint(cpath, precision="fp32", command_noise_p=1.0, seed=1)
    given = [always.inputs(observation(RoadOption.LEFT))[2] for _ in range(5)]
    assert all(c is not None and c != 1 for c in given)
    # a noise the model cannot receive is refused, not silently ignored
    with pytest.raises(ValueError, match="takes no guidance"):
        Agent.from_checkpoint(cpath, yaw_noise_deg=10.0)
    with pytest.raises(ValueError, match="takes no command"):
        Agent.from_checkpoint(path, command_noise_p=0.1)


def test_bad_observation_and_checkpoint(tmp_path: Path, tiny_checkpoint: Any) -> None:
    path, _ = tiny_checkpoint("cil", guidance=GC, spread=True)
    agent = Agent.from_checkpoint(path)
    obs = observation()
    assert obs.image is not None
    with pytest.raises(ValueError, match="no camera image"):
        agent.act(Observation(**{**obs.__dict__, "image": None}))
    with pytest.raises(ValueError, match="uint8"):
        agent.act(Observation(**{**obs.__dict__, "image": obs.image.astype(np.float32)}))
    with pytest.raises(FileNotFoundError):
        Agent.from_checkpoint(tmp_path / "none.pt")


def test_speed_control_drives_the_predicted_target_speed(tiny_checkpoint: Any) -> None:
    """With an aux head and speed_control, throttle and brake follow the head's target speed, not the net's."""
    path, norm = tiny_checkpoint("yilratt", guidance=GC, spread=True, guidance_dim=K, dropout=0.0, aux=True)
    plain = Agent.from_checkpoint(path, precision="fp32")
    ctl = Agent.from_checkpoint(path, precision="fp32", speed_control=True)
    obs = observation(speed=3.0)
    plain.reset()
    ctl.reset()
    c0, c1 = plain.act(obs), ctl.act(obs)
    assert plain.last is not None and ctl.last is not None and ctl.last.target_speed is not None
    assert c0.steer == pytest.approx(c1.steer)  # steering stays the net's
    target = ctl.last.target_speed
    t_want, b_want = SpeedControl()(target, 3.0)  # type: ignore[misc]
    assert c1.throttle == pytest.approx(t_want) and c1.brake == pytest.approx(b_want if b_want >= 0.1 else 0.0)
    with pytest.raises(ValueError, match="aux head"):
        Agent.from_checkpoint(tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K)[0], speed_control=True)


def test_lead_speed_control_caps_the_target_by_the_predicted_lead(tiny_checkpoint: Any) -> None:
    """speed_control="lead": the target speed is the least of the head's and the expert's braking rule on the
    head's predicted lead vehicle; with no lead predicted (distance near LEAD_RANGE) it is the head's own."""
    from yawil.agent import LEAD_DECEL, LEAD_SEEN
    from yawil.expert import hazard_speed

    path, _ = tiny_checkpoint("yilratt", guidance=GC, spread=True, guidance_dim=K, dropout=0.0, aux=True)
    target = Agent.from_checkpoint(path, precision="fp32", speed_control="target", engine="torch")
    lead = Agent.from_checkpoint(path, precision="fp32", speed_control="lead", engine="torch")
    assert Agent.from_checkpoint(path, precision="fp32", speed_control=True).drive.speed_control == "target"
    obs = observation(speed=3.0)
    for d_scaled, capped in ((0.04, True), (0.99, False)):  # a lead predicted 2 m ahead; none
        for agent in (target, lead):
            last = [m for m in agent.model.aux_head.modules() if isinstance(m, torch.nn.Linear)][-1]
            with torch.no_grad():
                last.weight[1:3].zero_()  # the lead outputs become constants: distance, and a standing lead
                last.bias[1] = d_scaled
                last.bias[2] = float(agent.norm.speed(torch.tensor([[0.0]]))[0, 0])
            agent.reset()
            agent.act(obs)
        a, b = target.last, lead.last
        assert a is not None and b is not None and a.target_speed is not None and b.target_speed is not None
        assert a.lead_distance == b.lead_distance and a.lead_distance is not None and b.lead_speed is not None
        assert (a.lead_distance < LEAD_SEEN) is capped and b.lead_speed == pytest.approx(0.0, abs=1e-4)
        want = min(a.target_speed, hazard_speed(a.lead_distance, 0.0, LEAD_DECEL)) if capped else a.target_speed
        assert b.target_speed == pytest.approx(want)
    with pytest.raises(ValueError, match="speed_control"):
        Agent.from_checkpoint(path, speed_control="brake")


def test_hazard_speed_is_the_experts_braking_rule() -> None:
    from yawil.expert import hazard_speed

    assert hazard_speed(8.0, 0.0, 2.0) == pytest.approx(math.sqrt(32.0))  # stop at 8 m braking at 2 m/s^2
    assert hazard_speed(0.0, 0.0, 2.0) == 0.0
    assert hazard_speed(10.0, 3.0, 2.0) == pytest.approx(min(math.sqrt(9.0 + 40.0), 3.0 + 5.0))  # settle behind
    assert hazard_speed(-2.0, 3.0, 2.0) == pytest.approx(2.0)  # too close behind a mover: slower than it


def test_stop_speed_control_stops_while_the_lead_stop_output_fires(tiny_checkpoint: Any) -> None:
    """speed_control="stop": the target speed is 0 while P(standing vehicle close ahead) > 0.5, else the
    head's own; refused for a model without the lead-stop output."""
    path, _ = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K, dropout=0.0, aux=True,
                              lead_stop=True)
    target = Agent.from_checkpoint(path, precision="fp32", speed_control="target", engine="torch")
    stop = Agent.from_checkpoint(path, precision="fp32", speed_control="stop", engine="torch")
    obs = observation(speed=3.0)
    for logit, fires in ((4.0, True), (-4.0, False)):
        for agent in (target, stop):
            last = [m for m in agent.model.aux_head.modules() if isinstance(m, torch.nn.Linear)][-1]
            with torch.no_grad():
                last.weight[4].zero_()
                last.bias[4] = logit
            agent.reset()
            control = agent.act(obs)
        a, b = target.last, stop.last
        assert a is not None and b is not None and b.lead_stop is not None and a.target_speed is not None
        assert b.lead_stop == pytest.approx(float(torch.sigmoid(torch.tensor(logit))))
        assert b.target_speed == (0.0 if fires else pytest.approx(a.target_speed))
        if fires:
            assert control.throttle == 0.0 and control.brake > 0.5  # at 3 m/s towards a target of 0
    plain, _ = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K, dropout=0.0, aux=True)
    with pytest.raises(ValueError, match="lead_stop=true"):
        Agent.from_checkpoint(plain, speed_control="stop")


def test_stop_release_times_a_creep_after_standing_held_by_the_class_alone() -> None:
    """StopRelease: `patience` s standing with the class the only reason -> `creep` s released, then armed
    again; moving, or a head that would stand anyway (a red light), restarts the count."""
    from yawil.agent import StopRelease

    r = StopRelease(patience=1.0, creep=0.5, dt=0.1)
    seq = [r.released(0.0, True) for _ in range(20)]
    assert seq[:9] == [False] * 9  # 0.9 s standing: still held
    assert seq[9:14] == [True] * 5  # the 10th step (1.0 s) starts a 0.5 s creep
    assert seq[14:] == [False] * 6  # armed again, counting afresh
    r.reset()
    for held in ([r.released(0.0, True) for _ in range(5)], [r.released(2.0, True)], [r.released(0.0, False)]):
        assert not any(held)
    assert r.stood == 0  # moving or a standing head restart the count
    assert not any(r.released(0.0, True) for _ in range(9))


def test_stop_creep_ends_once_the_car_has_moved_its_distance() -> None:
    """StopRelease(creep_distance=d): the creep ends, and the class counts again, on the step the car has driven
    d metres (a creep toward a real queue stops short of it); a creep that moves less runs its full time."""
    from yawil.agent import StopRelease

    r = StopRelease(patience=1.0, creep=2.0, creep_distance=0.5, dt=0.1)
    assert not any(r.released(0.0, True) for _ in range(9)) and r.released(0.0, True)  # the creep starts
    moving = [r.released(1.0, True) for _ in range(8)]  # 0.1 m a step
    assert moving[:4] == [True] * 4 and moving[4] is False  # the 5th step reaches 0.5 m: armed again
    assert r.creep_left == 0 and r.stood == 0
    slow = StopRelease(patience=1.0, creep=2.0, creep_distance=5.0, dt=0.1)
    assert [slow.released(0.0, True) for _ in range(10)][-1]
    assert all(slow.released(0.2, True) for _ in range(19)) and not slow.released(0.0, False)  # 0.38 m: full 2 s
    with pytest.raises(ValueError, match="stop_creep"):
        from yawil.policy.drive import DriveSettings

        DriveSettings(speed_control="stop", stop_creep=1.0)  # a creep length without a release


@pytest.mark.parametrize("release", [0.0, 0.5])
def test_stop_speed_control_releases_a_car_the_class_alone_holds(tiny_checkpoint: Any, release: float) -> None:
    """speed_control="stop" with stop_release: the firing class holds a standing car `stop_release` s, then the
    head's target speed drives it for STOP_CREEP s; without a release it stands for ever."""
    from yawil.agent import STOP_CREEP
    from yawil.sim.types import DT

    path, _ = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K, dropout=0.0, aux=True,
                              lead_stop=True)
    agent = Agent.from_checkpoint(path, precision="fp32", speed_control="stop", stop_release=release, engine="torch")
    last = [m for m in agent.model.aux_head.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight[[0, 4]] = 0.0
        last.bias[4] = 4.0  # fires on every frame
        last.bias[0] = float(agent.norm.speed(torch.tensor([[5.0]]))[0, 0])  # the head would drive at 5 m/s
    agent.reset()
    obs = observation(speed=0.0)
    released = []
    for _ in range(int(round((release + STOP_CREEP) / DT)) + 20):
        control = agent.act(obs)
        assert agent.last is not None and agent.last.head_target_speed == pytest.approx(5.0, abs=1e-3)
        released.append(control.throttle > 0.0)
    n_hold = int(round(release / DT)) - 1
    if release:
        assert not any(released[:n_hold]) and all(released[n_hold:n_hold + int(round(STOP_CREEP / DT))])
    else:
        assert not any(released)
    with pytest.raises(ValueError, match="stop_release"):
        Agent.from_checkpoint(path, speed_control="target", stop_release=5.0)
    with pytest.raises(ValueError, match="stop_release"):
        Agent.from_checkpoint(path, speed_control="stop", stop_release=-1.0)


def test_a_zoo_model_drives_as_its_card_says_unless_told_otherwise() -> None:
    """`Agent.from_checkpoint("zoo:NAME")` takes the card's drive settings (those behind its figures), so that a
    Python user drives the model `yawil bench --agent zoo:NAME` drives; any drive option given replaces them."""
    from yawil.policy.drive import DriveSettings
    from yawil.zoo import read_card

    card = read_card("yilratt-dagger-ego")["drive"]
    agent = Agent.from_checkpoint("zoo:yilratt-dagger-ego", engine="torch")
    assert (agent.drive.speed_control, agent.drive.stop_release) == (card["speed_control"], card["stop_release"])
    plain = Agent.from_checkpoint("zoo:yilratt-dagger-ego", engine="torch", speed_control=False)
    assert plain.drive == DriveSettings()
    with pytest.raises(ValueError, match="unknown drive option"):
        Agent.from_checkpoint("zoo:yilratt-dagger-ego", engine="torch", speed_controll="stop")


def test_load_agent_gym_action_and_drive_episode(tiny_checkpoint: Any) -> None:
    """The public entry points: load_agent sets threads and builds the agent; gym_action drives a gym env with the
    agent's own guidance; drive_episode returns the benchmark's record of one episode."""
    from yawil.agent import gym_action, load_agent
    from yawil.bench.runner import drive_episode
    from yawil.bench.suites import episodes
    from yawil.expert import Expert
    from yawil.gym_env import YawilDriveEnv

    path, _ = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K, dropout=0.0)
    before = torch.get_num_threads()
    agent = load_agent(path, threads=1, engine="torch")
    assert torch.get_num_threads() == 1
    torch.set_num_threads(before)
    with pytest.raises(ValueError, match="threads=0"):
        load_agent(path, threads=0)
    env = YawilDriveEnv(town="square", camera=True)
    env.reset(seed=0)
    action = gym_action(agent, env)
    assert action.shape == (3,) and env.action_space.contains(action)
    env.step(action)
    env.close()
    with pytest.raises(ValueError, match="after reset"):
        gym_action(agent, YawilDriveEnv(town="square", camera=False))
    ep = episodes("square", routes="2", seeds=1)[0]
    record = drive_episode(Expert(), ep, camera=False)
    assert record["success"] is True and record["reason"] is None and record["km_driven"] > 0.05
