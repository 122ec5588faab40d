"""Attention by class (yawil.explain.by_class): synthetic maps with known answers, the situation rules, the
frames gathered by driving, the written outputs."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from yawil.explain import by_class as bc
from yawil.sim.semantic import CLASS_ID, CLASSES
from yawil.sim.types import RoadOption

H, W = 88, 200
ROAD, SKY, LANE, VEH, PED = (CLASS_ID[c] for c in ("road", "sky", "lane_marking", "vehicle", "pedestrian"))


def _scene(n: int = 1) -> np.ndarray:
    """Frames of sky above road, a lane line and a vehicle; frame i > 0 without the vehicle."""
    ids = np.full((n, H, W), SKY, dtype=np.uint8)
    ids[:, 40:] = ROAD
    ids[:, 60:, 98:102] = LANE
    ids[0, 45:55, 20:40] = VEH
    return ids


def _col(t: bc.ByClass, name: str) -> int:
    return t.columns.index(name)


def test_all_mass_on_one_class_gives_one_over_its_share() -> None:
    ids = _scene()
    att = (ids[0] == VEH).astype(np.float64)  # at image resolution: upsampling is the identity
    t = bc.by_class_table([att[None]], ids, ["free"], bootstrap=0)
    share = float((ids == VEH).mean())
    lift = t.lift[0, 0]
    assert lift[_col(t, "vehicle")] == pytest.approx(1.0 / share)
    assert t.mass[0, 0, _col(t, "vehicle")] == pytest.approx(1.0)
    assert t.spread[0, 0] == pytest.approx(share)  # uniform over the vehicle's pixels
    for name in ("road", "sky", "lane_marking", "passable"):
        assert lift[_col(t, name)] == pytest.approx(0.0, abs=1e-12)
    assert t.share[0, _col(t, "vehicle")] == pytest.approx(share)


def test_uniform_map_gives_lift_one_for_present_classes_and_nan_for_absent_ones() -> None:
    ids = _scene(3)
    uniform = np.ones((3, 6, 13))  # a coarse map: a constant upsamples to a constant
    t = bc.by_class_table([uniform, np.ones((3, H, W))], ids, ["free", "free", "turning"], bootstrap=0)
    present = {"sky", "road", "lane_marking", "vehicle", "passable"}
    for li in range(2):
        for si, sit in enumerate(t.situations):
            if sit not in ("all", "free", "turning"):
                assert t.frames[si] == 0 and np.isnan(t.lift[li, si]).all()
                continue
            for k, col in enumerate(t.columns):
                if col in present and t.share[si, k] > 0:
                    assert t.lift[li, si, k] == pytest.approx(1.0) == pytest.approx(t.prior[li, si, k])
                elif col not in present:
                    assert math.isnan(t.lift[li, si, k]), col
    assert t.spread[0, 0] == pytest.approx(1.0) and t.spread[1, 0] == pytest.approx(1.0)  # uniform: all of it
    # the turning frame has no vehicle: its lift is undefined there, its share and mass 0
    si = t.situations.index("turning")
    k = _col(t, "vehicle")
    assert math.isnan(t.lift[0, si, k]) and t.share[si, k] == 0 and t.mass[0, si, k] == 0
    assert t.present[t.situations.index("all"), k] == pytest.approx(1 / 3)


def test_frames_without_the_class_drop_out_of_its_lift() -> None:
    ids = _scene(2)
    att = np.stack([(ids[0] == VEH).astype(float), np.ones((H, W))])  # frame 1 has no vehicle
    t = bc.by_class_table([att], ids, ["free", "free"], bootstrap=0)
    s0 = float((ids[0] == VEH).mean())
    si, k = t.situations.index("free"), _col(t, "vehicle")
    assert t.share[si, k] == pytest.approx(s0 / 2)  # mean over both frames
    assert t.mass[0, si, k] == pytest.approx(0.5)
    assert t.lift[0, si, k] == pytest.approx(1.0 / s0)  # as frame 0 alone
    # the road: frame 0 puts nothing there, frame 1 as much as its share
    r = _col(t, "road")
    road = [(ids[f] == ROAD).mean() for f in range(2)]
    assert t.lift[0, si, r] == pytest.approx((0 + road[1]) / (road[0] + road[1]))


def test_prior_is_the_lift_of_where_the_layer_looks_on_average() -> None:
    """A map fixed in place scores its prior; a map that follows a moving vehicle scores above it."""
    ids = np.full((2, H, W), ROAD, dtype=np.uint8)
    ids[0, 40:50, 10:30] = VEH
    ids[1, 40:50, 150:170] = VEH
    fixed = np.zeros((2, H, W))
    fixed[:, 40:50, 10:30] = 1.0  # where the vehicle is in frame 0 only
    following = (ids == VEH).astype(float)
    t = bc.by_class_table([fixed, following], ids, ["free", "free"], bootstrap=0)
    k = _col(t, "vehicle")
    share = float((ids[0] == VEH).mean())
    assert t.lift[0, 0, k] == pytest.approx(t.prior[0, 0, k]) == pytest.approx(0.5 / share)
    assert t.lift[1, 0, k] == pytest.approx(1.0 / share)
    assert t.prior[1, 0, k] == pytest.approx(0.5 / share)  # its mean map is half on each place
    data = t.to_dict()
    assert data["rows"][0]["prior"]["vehicle"] == pytest.approx(0.5 / share)
    assert "## Lift / prior" in bc.markdown(t)


def test_coarse_map_lands_on_its_region() -> None:
    """A map at layer-3 resolution peaked on the bottom rows puts most of its mass on the road."""
    ids = _scene()
    att = np.zeros((1, 6, 13))
    att[0, 4:] = 1.0
    t = bc.by_class_table([att], ids, ["free"], bootstrap=0)
    assert t.lift[0, 0, _col(t, "road")] > 1.5 and t.lift[0, 0, _col(t, "sky")] < 0.1
    assert t.mass[0, 0, : len(CLASSES)].sum() == pytest.approx(1.0)


def test_situation_split_counts_and_flags() -> None:
    n = 7
    labels = ["free", "free", "turning", "brake_vehicle", "brake_vehicle", "brake_vehicle", "brake_light"]
    ids = _scene(n)
    flags = {"agent_brakes": [0, 0, 0, 1, 1, 0, np.nan]}
    t = bc.by_class_table([np.ones((n, 3, 3))], ids, labels, groups=[0, 0, 0, 0, 1, 1, 1], flags=flags,
                          bootstrap=50)
    counts = dict(zip(t.situations, t.frames.tolist(), strict=True))
    assert counts == {"all": 7, "free": 2, "turning": 1, "brake_vehicle": 3, "brake_pedestrian": 0,
                      "brake_light": 1, "other": 0}
    assert sum(counts.values()) - counts["all"] == n
    assert t.episodes[t.situations.index("brake_vehicle")] == 2
    assert t.flags["agent_brakes"][t.situations.index("brake_vehicle")] == pytest.approx(2 / 3)
    assert math.isnan(t.flags["agent_brakes"][t.situations.index("brake_light")])
    # a uniform map's lift is 1 in every resample: the interval is [1, 1]; one episode gives none
    si = t.situations.index("brake_vehicle")
    assert t.lift_lo[0, si, _col(t, "road")] == pytest.approx(1.0)
    assert t.lift_hi[0, si, _col(t, "road")] == pytest.approx(1.0)
    assert np.isnan(t.lift_lo[0, t.situations.index("free")]).all()


def test_bad_inputs_raise() -> None:
    ids = _scene(2)
    with pytest.raises(ValueError, match="unknown labels"):
        bc.by_class_table([np.ones((2, 3, 3))], ids, ["free", "cruising"])
    with pytest.raises(ValueError, match="maps\\[0\\]"):
        bc.by_class_table([np.ones((3, 3, 3))], ids, ["free", "free"])
    with pytest.raises(ValueError, match="integer"):
        bc.by_class_table([np.ones((2, 3, 3))], ids.astype(float), ["free", "free"])
    with pytest.raises(ValueError, match="layer_names"):
        bc.by_class_table([np.ones((2, 3, 3))], ids, ["free", "free"], layer_names=["a", "b"])
    with pytest.raises(ValueError, match="brake"):
        bc.SituationRules(brake=1.5)


@pytest.mark.parametrize(("brake", "reason", "command", "steer", "expected"), [
    (0.0, "cruise", RoadOption.LANEFOLLOW, 0.0, "free"),
    (0.0, "curve", RoadOption.STRAIGHT, 0.05, "free"),
    (0.0, "cruise", RoadOption.LEFT, 0.0, "turning"),
    (0.0, "cruise", RoadOption.LANEFOLLOW, -0.3, "turning"),
    (0.3, "curve", RoadOption.RIGHT, 0.4, "turning"),  # braking into a turn: turning
    (0.5, "vehicle", RoadOption.LANEFOLLOW, 0.0, "brake_vehicle"),
    (1.0, "junction", RoadOption.LEFT, 0.0, "brake_vehicle"),  # braking wins over turning
    (0.2, "pedestrian", RoadOption.LANEFOLLOW, 0.0, "brake_pedestrian"),
    (1.0, "red_light", RoadOption.LANEFOLLOW, 0.0, "brake_light"),
    (0.4, "yellow_light", RoadOption.STRAIGHT, 0.0, "brake_light"),
    (0.04, "vehicle", RoadOption.LANEFOLLOW, 0.0, "other"),  # below the brake threshold: following
    (0.5, "goal", RoadOption.LANEFOLLOW, 0.0, "other"),
    (0.2, "cruise", RoadOption.LANEFOLLOW, 0.0, "other"),
])  # fmt: skip
def test_situation_rules(brake: float, reason: str, command: int, steer: float, expected: str) -> None:
    assert bc.label_situation(brake, reason, int(command), steer) == expected


def _fake_maps(obs: Any) -> list[np.ndarray]:
    """A deterministic map source from the image (two layers, coarse and fine)."""
    grey = obs.image.astype(np.float64).mean(axis=2)
    return [grey[::8, ::8], grey[::4, ::4] ** 2]


class _Source:
    def __init__(self) -> None:
        self.seeds: list[int] = []
        self.last_brake = 0.25

    def reset(self, seed: int) -> None:
        self.seeds.append(seed)

    def __call__(self, obs: Any) -> list[np.ndarray]:
        return _fake_maps(obs)


def test_gather_frames_is_aligned_and_deterministic() -> None:
    from yawil.bench.suites import episodes

    eps = episodes("square", routes="0,1", seeds=1)
    src = _Source()
    a = bc.gather_frames(src, eps, every=3, max_steps=8)
    b = bc.gather_frames(_fake_maps, eps, every=3, max_steps=8)
    assert src.seeds == [e.world_seed for e in eps]
    assert len(a) == 6 and a.step.tolist() == [0, 3, 6] * 2 and a.episode.tolist() == [0, 0, 0, 1, 1, 1]
    assert a.ids.shape == (6, H, W) and a.ids.dtype == np.uint8
    assert [m.shape for m in a.maps] == [(6, 11, 25), (6, 22, 50)]
    for arr in (a.expert_brake, a.expert_steer, a.expert_reason, a.command, a.speed, a.agent_brake):
        assert arr.shape == (6,)
    assert a.agent_brake.tolist() == [0.25] * 6 and np.isnan(b.agent_brake).all()
    assert a.episode_keys == [e.key for e in eps]
    np.testing.assert_array_equal(a.ids, b.ids)
    for x, y in zip(a.maps, b.maps, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.expert_brake, b.expert_brake)
    np.testing.assert_array_equal(a.expert_steer, b.expert_steer)
    assert a.ids[:, 70:].max() > 0 and (a.ids == ROAD).any()
    assert bc.gather_frames(_fake_maps, eps[:1], every=1, max_frames=2).step.tolist() == [0, 1]
    t = a.table(bootstrap=10)
    assert t.frames[0] == 6 and "agent_brakes" in t.flags and "standing" in t.flags


def test_agent_maps_and_outputs(tmp_path: Path, tiny_checkpoint: Any, capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.agent import Agent
    from yawil.bench.suites import episodes

    agent = Agent.from_checkpoint(tiny_checkpoint("yilratt").path)
    eps = episodes("square", routes="0", seeds=1)
    act = bc.gather_frames(bc.AgentMaps(agent, "activation"), eps, every=2, max_steps=4)
    assert act.layer_names[0] == "activation stage 1" and len(act) == 2

    p = argparse.ArgumentParser()
    bc.add_by_class_arguments(p)
    args = p.parse_args(["--by-class", "--class-suite", "square", "--class-condition", "square", "--class-task",
                         "square", "--class-routes", "0", "--class-every", "2", "--class-max-frames", "2"])
    out = tmp_path / "out"
    assert bc.run_from_args(agent, args, out) == 0
    assert "| attention layer 1 | all | 2 |" in capsys.readouterr().out
    frames = bc.Frames.load(out / "frames.npz")
    assert frames.layer_names == ("attention layer 1", "attention layer 2", "attention layer 3")
    assert all(m.shape[0] == 2 for m in frames.maps) and np.isfinite(frames.agent_brake).all()
    assert frames.episode_keys == [eps[0].key] and frames.step.tolist() == [0, 2]
    data = json.loads((out / "by_class.json").read_text())
    assert data["format"] == bc.FORMAT and len(data["rows"]) == 3 * 7
    assert data["meta"]["maps"] == "AgentMaps(auto)" and data["meta"]["frames"] == 2
    ped = next(r for r in data["rows"] if r["situation"] == "brake_pedestrian")
    assert ped["frames"] == 0 and ped["lift"]["road"] is None  # NaN as null
    md = (out / "by_class.md").read_text()
    assert "| attention layer 1 | all | 2 |" in md and "## Mass % (share %)" in md
    assert (out / "by_class.png").stat().st_size > 0


def test_arguments_parse() -> None:
    p = argparse.ArgumentParser()
    bc.add_by_class_arguments(p.add_argument_group("by class"))
    args = p.parse_args(["--by-class", "--class-routes", "0:2", "--class-every", "5", "--class-max-frames", "9"])
    assert args.by_class and args.class_routes == "0:2" and args.class_every == 5 and args.class_task == "dense"
    assert args.class_max_frames == 9
    assert bc.EpisodePlan(routes="0:2", every=5).episodes()[1].key == "dense/training/WetNoon/1/0"
    d = p.parse_args([])
    assert bc.EpisodePlan(suite=d.class_suite, condition=d.class_condition, task=d.class_task, routes=d.class_routes,
                          seeds=d.class_seeds, every=d.class_every, max_frames=d.class_max_frames) == bc.EpisodePlan()
    assert (d.class_brake, d.class_steer) == (bc.SituationRules().brake, bc.SituationRules().steer)
