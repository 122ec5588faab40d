"""The collection loop: noise labels, frame thinning, collision policy, resume, workers, the CLI.

Most tests drive a small scripted world (a straight road, the real ego dynamics, a synthetic image) so
they check the collector's own logic in well under a second; the last ones use the embedded simulator.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from scripted_world import LineWorld, crash_world, line_world, small_cfg
from yawil.data.collect import (
    CollectConfig,
    SteeringNoise,
    collect,
    episode_id,
    plan_episode,
    run_episode,
)
from yawil.data.manifest import read_manifest

# ---------------------------------------------------------------------------------------------- unit tests


def test_noise_fraction_and_bursts_are_seeded() -> None:
    def run(seed: int) -> np.ndarray:
        n = SteeringNoise(0.1, 0.5, (0.5, 1.0), np.random.default_rng(seed))
        return np.array([n() for _ in range(20000)])

    a, b = run(3), run(3)
    assert np.array_equal(a, b)
    assert 0.08 < np.mean(a != 0.0) < 0.12
    assert np.abs(a).max() <= 0.5
    starts = np.flatnonzero((a[1:] != 0) & (a[:-1] == 0))
    lengths = [int(np.argmax(a[s + 1 :] == 0)) for s in starts[:50]]
    assert min(lengths) >= 5 and max(lengths) <= 10 + 10  # 0.5-1 s bursts (back-to-back bursts may merge)


def test_plan_is_a_function_of_seed_and_index() -> None:
    cfg = small_cfg(vehicles=(10, 30), pedestrians=(5, 20))
    p = plan_episode(cfg, 2, 7)
    assert p == plan_episode(cfg, 2, 7)
    assert p.episode_id == episode_id(2, 7) == 200_007
    assert 10 <= p.vehicles <= 30 and 5 <= p.pedestrians <= 20
    assert [plan_episode(cfg, 0, i).weather for i in range(4)] == ["ClearNoon", "WetNoon"] * 2
    with pytest.raises(ValueError, match="index"):
        episode_id(0, 100_000)


def test_bad_config_is_an_error() -> None:
    with pytest.raises(ValueError, match="weather"):
        small_cfg(weathers=("Sunny",))
    with pytest.raises(ValueError, match="on_collision"):
        small_cfg(on_collision="ignore")
    with pytest.raises(ValueError, match="vehicles"):
        small_cfg(vehicles=(5, 2))
    with pytest.raises(ValueError, match="budget"):
        collect("/nonexistent", frames=None, episodes=None)


def test_labels_are_the_experts_control_not_the_noisy_one(tmp_path: Path) -> None:
    world = LineWorld()
    cfg = small_cfg()
    from yawil.data.collect import dataset_config
    from yawil.data.writer import DatasetWriter
    from yawil.expert import ExpertConfig
    from yawil.guidance import GuidanceConfig

    writer = DatasetWriter(tmp_path / "ds", dataset_config(cfg, GuidanceConfig(), ExpertConfig()))
    r = run_episode(world, plan_episode(cfg, 0, 0), cfg, writer)
    assert r.outcome == "goal" and r.frames_kept == r.frames_run > 100
    with h5py.File(tmp_path / "ds" / "episodes" / "ep_000000.h5") as f:
        steer, noise, frame = f["steer"][:], f["noise"][:].astype(bool), f["frame"][:]
        lft = f["lane_follow_turn"][:].astype(bool)
        assert f["guidance_yaw"].shape == (len(steer), 15) and f["image"].shape == (len(steer), 88, 200, 3)
    applied = np.array([world.applied[i].steer for i in frame])
    assert noise.any() and (~noise).any()
    assert np.allclose(applied[~noise], steer[~noise], atol=1e-6)  # quiet frames: what was applied
    assert np.all(np.abs(applied[noise] - steer[noise]) > 1e-6)  # noisy frames: the label is the expert's
    assert lft.any() and not lft[:50].any()  # the curve at the end is a lane-follow turn, the straight is not


def test_straight_thinning(tmp_path: Path) -> None:
    cfg = small_cfg(noise_fraction=0.0, straight_keep=0.25)
    r = run_episode(LineWorld(), plan_episode(cfg, 0, 1), cfg, None)
    assert r.outcome == "goal"
    assert r.frames_kept < 0.8 * r.frames_run  # about 3/4 of the long straight dropped


@pytest.mark.parametrize(("policy", "outcome"), [("trim", "collision"), ("keep", "collision"), ("discard", "discarded(collision)")])
def test_collision_policy(tmp_path: Path, policy: str, outcome: str) -> None:
    s = collect(tmp_path / policy, town="line", weathers="ClearNoon", episodes=1, progress=False,
                world_factory=crash_world, config=small_cfg(on_collision=policy))
    assert s.outcomes == {outcome: 1}
    m = read_manifest(tmp_path / policy)
    if policy == "discard":
        assert m.episodes == []
    else:
        kept = m.episodes[0].frames
        assert kept == (150 - 20 if policy == "trim" else 150)
        assert m.episodes[0].outcome == "collision"


def test_resume_never_duplicates_and_results_are_deterministic(tmp_path: Path) -> None:
    cfg = small_cfg()
    s1 = collect(tmp_path / "a", town="line", weathers="ClearNoon,WetNoon", episodes=2, progress=False,
                 world_factory=line_world, config=cfg)
    assert s1.episodes_written == 2
    s2 = collect(tmp_path / "a", town="line", weathers="ClearNoon,WetNoon", episodes=3, progress=False,
                 world_factory=line_world, config=cfg)
    assert s2.episodes_skipped == 2 and s2.episodes_written == 1
    m = read_manifest(tmp_path / "a")
    assert sorted(m.episode_ids()) == [0, 1, 2]
    # a fresh run of the same command gives the same bytes of labels
    collect(tmp_path / "b", town="line", weathers="ClearNoon,WetNoon", episodes=3, progress=False,
            world_factory=line_world, config=cfg)
    for ep in ("ep_000000.h5", "ep_000002.h5"):
        with h5py.File(tmp_path / "a" / "episodes" / ep) as fa, h5py.File(tmp_path / "b" / "episodes" / ep) as fb:
            for name in ("steer", "throttle", "brake", "noise", "guidance_yaw", "image"):
                assert np.array_equal(fa[name][:], fb[name][:])
    with pytest.raises(ValueError, match="config differs"):
        collect(tmp_path / "a", town="line", weathers="ClearNoon", episodes=1, progress=False, world_factory=line_world,
                config=cfg)


def test_resume_recollects_damaged_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Truncated, missing and header-zeroed files are not 'already present': a resume collects them again,
    identically (episodes are deterministic in their seed), and the dataset checks OK afterwards."""
    from yawil.data.check import check_dataset

    cfg = small_cfg()
    kw = dict(town="line", weathers="ClearNoon,WetNoon", episodes=3, progress=False, world_factory=line_world, config=cfg)
    collect(tmp_path / "a", **kw)
    eps = tmp_path / "a" / "episodes"
    before = {p.name: p.read_bytes() for p in eps.glob("ep_*.h5")}
    with open(eps / "ep_000000.h5", "r+b") as f:
        f.truncate(os.path.getsize(eps / "ep_000000.h5") - 500)
    (eps / "ep_000001.h5").unlink()
    with open(eps / "ep_000002.h5", "r+b") as f:
        f.write(b"\0" * 512)
    assert not check_dataset(tmp_path / "a").ok
    capsys.readouterr()
    s = collect(tmp_path / "a", **kw)
    assert (s.episodes_written, s.episodes_skipped) == (3, 0)
    assert capsys.readouterr().err.count("collect: re-collecting episodes/ep_00000") == 3
    assert check_dataset(tmp_path / "a").ok
    with h5py.File(eps / "ep_000002.h5") as fa:
        assert len(fa["image"]) == read_manifest(tmp_path / "a").entry(2).frames
    assert {p.name for p in eps.glob("ep_*.h5")} == set(before)


def test_frame_budget_stops_early(tmp_path: Path) -> None:
    s = collect(tmp_path / "f", town="line", weathers="ClearNoon", frames=10, progress=False,
                world_factory=line_world, config=small_cfg())
    assert s.episodes_written == 1 and s.dataset_frames >= 10
    s2 = collect(tmp_path / "f", town="line", weathers="ClearNoon", frames=10, progress=False,
                 world_factory=line_world, config=small_cfg())
    assert s2.episodes_written == 0  # the budget is already met: nothing to do


def test_two_workers_match_one(tmp_path: Path) -> None:
    cfg = small_cfg()
    collect(tmp_path / "one", town="line", weathers="ClearNoon,WetNoon", episodes=3, workers=1, progress=False,
            world_factory=line_world, config=cfg)
    s = collect(tmp_path / "two", town="line", weathers="ClearNoon,WetNoon", episodes=3, workers=2, progress=True,
                world_factory=line_world, config=cfg)
    assert s.episodes_written == 3
    one, two = read_manifest(tmp_path / "one"), read_manifest(tmp_path / "two")
    assert sorted(one.episode_ids()) == sorted(two.episode_ids()) == [0, 1, 2]
    for e in one.episodes:
        assert two.entry(e.episode).frames == e.frames and two.entry(e.episode).noise_frames == e.noise_frames


# --------------------------------------------------------------------------------------- embedded world


def test_two_tiny_episodes_in_the_embedded_world(tmp_path: Path) -> None:
    from yawil.data.reader import open_episode

    cfg = CollectConfig(town="town02", weathers=("WetNoon",), vehicles=(5, 5), pedestrians=(5, 5), min_route_length=0.0,
                        noise_fraction=0.3, max_episode_frames=40, straight_keep=1.0)
    s = collect(tmp_path / "real", town="town02", weathers="WetNoon", episodes=2, progress=False, config=cfg)
    assert s.episodes_written == 2 and s.outcomes == {"frame_limit": 2}
    m = read_manifest(tmp_path / "real")
    assert sorted(m.episode_ids()) == [0, 1] and m.frames == s.frames_written > 0
    ep = open_episode(m.path_of(m.episodes[0]))
    rec = ep[len(ep) - 1]
    assert rec.image.shape == (88, 200, 3) and rec.image.std() > 5.0  # a rendered picture, not a blank
    assert rec.guidance_yaw.shape == (15,) and rec.guidance_xy.shape == (30,)
    again = collect(tmp_path / "real", town="town02", weathers="WetNoon", episodes=2, progress=False, config=cfg)
    assert again.episodes_written == 0 and again.episodes_skipped == 2
