"""DAgger: who drives each frame (schedule, takeovers), expert labels on learner frames, seeds and routes kept
off the benchmark's, and a tiny end-to-end run that resumes."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from scripted_world import LineWorld, small_cfg
from yawil.bench.select import BenchmarkRoutes, validation_episodes
from yawil.data.collect import CollectConfig, Learner, OnPolicy, collect, plan_episode, run_episode
from yawil.data.manifest import read_manifest
from yawil.data.reader import open_episode
from yawil.data.schema import DRIVERS
from yawil.data.writer import DatasetWriter
from yawil.pipelines.dagger import BENCH_WORLD_SEED_LIMIT, DaggerConfig, DaggerRun
from yawil.sim.types import Control, Observation

AGENT_GC = {"spacing": 2.0, "count": 4, "reference": "route"}  # the guidance of tests/test_agent.py
LEARNER, TAKEOVER, EXPERT = DRIVERS.index("learner"), DRIVERS.index("takeover"), DRIVERS.index("expert")


class Scripted:
    """A learner that always does the same thing (and counts its calls)."""

    def __init__(self, control: Control) -> None:
        self.control, self.calls, self.resets = control, 0, 0

    def reset(self) -> None:
        self.resets += 1

    def act(self, obs: Observation) -> Control:
        self.calls += 1
        return self.control


def _drive(tmp_path: Path, learner: Scripted, onpolicy: OnPolicy, name: str = "d") -> tuple[dict[str, np.ndarray], list[Control], object]:
    world = LineWorld()
    cfg = small_cfg(noise_fraction=0.0)
    writer = DatasetWriter(tmp_path / name, {"guidance": {"count": 15}})
    r = run_episode(world, plan_episode(cfg, 0, 0), cfg, writer, learner=learner, onpolicy=onpolicy)
    writer.close()
    m = read_manifest(tmp_path / name)
    with open_episode(m.path_of(m.episodes[0])) as ep:
        labels = ep.labels()
    return labels, world.applied, r


def test_a_learner_that_strays_hands_over_and_the_labels_stay_the_experts(tmp_path: Path) -> None:
    learner = Scripted(Control(steer=-0.5, throttle=0.5, brake=0.0))  # veers right, off the road
    labels, applied, r = _drive(tmp_path, learner, OnPolicy(round=2, takeover_lateral=1.0, takeover_seconds=1.0))
    drivers = labels["driver"]
    assert (drivers == LEARNER).any() and (drivers == TAKEOVER).any() and not (drivers == EXPERT).any()
    assert r.takeovers >= 1 and r.drivers["learner"] + r.drivers["takeover"] == r.frames_run  # type: ignore[attr-defined]
    assert learner.calls == r.frames_run and learner.resets == 1  # type: ignore[attr-defined]
    assert (labels["round"] == 2).all()
    # learner frames: the car did what the learner said, the label is what the expert would have done
    rows = np.nonzero(drivers == LEARNER)[0]
    assert np.allclose(np.array([applied[f].steer for f in labels["frame"][rows]]), -0.5)
    assert np.all(labels["steer"][rows] > -0.5)  # the expert steers back towards the route
    # takeover frames: the expert's own control drove the car
    rows = np.nonzero(drivers == TAKEOVER)[0]
    assert np.allclose([applied[f].steer for f in labels["frame"][rows]], labels["steer"][rows], atol=1e-6)


def test_a_learner_that_never_brakes_is_stopped_by_the_expert(tmp_path: Path) -> None:
    learner = Scripted(Control(steer=0.0, throttle=1.0, brake=0.0))  # full throttle towards the goal
    labels, applied, r = _drive(tmp_path, learner, OnPolicy(takeover_lateral=50.0, takeover_seconds=30.0))
    assert r.takeovers >= 1  # type: ignore[attr-defined]
    first = int(np.nonzero(labels["driver"] == TAKEOVER)[0][0])
    assert labels["brake"][first] > 0.0 or labels["target_speed"][first] < labels["speed"][first]
    assert (labels["speed_reason"] >= 0).all() and np.isfinite(labels["target_speed"]).all()


def test_a_stalled_learner_is_started_by_the_expert(tmp_path: Path) -> None:
    learner = Scripted(Control(steer=0.0, throttle=0.0, brake=1.0))
    labels, applied, r = _drive(tmp_path, learner, OnPolicy(takeover_stall=2.0, takeover_seconds=2.0))
    first = int(np.nonzero(labels["driver"] == TAKEOVER)[0][0])
    assert 19 <= labels["frame"][first] <= 22  # about 2 s of standing at 10 Hz
    assert labels["throttle"][first] > 0.0


def test_beta_one_is_the_expert_alone_and_the_schedule_is_seeded(tmp_path: Path) -> None:
    learner = Scripted(Control(steer=0.0, throttle=0.0, brake=1.0))
    labels, _, _ = _drive(tmp_path, learner, OnPolicy(beta=1.0), "all")
    assert (labels["driver"] == EXPERT).all()
    mixed = OnPolicy(beta=0.5, segment_seconds=1.0, takeover_stall=100.0)
    a, _, _ = _drive(tmp_path, Scripted(Control(throttle=0.4)), mixed, "a")
    b, _, _ = _drive(tmp_path, Scripted(Control(throttle=0.4)), mixed, "b")
    assert {EXPERT, LEARNER} <= set(a["driver"].tolist())
    for name in a:
        assert np.array_equal(a[name], b[name], equal_nan=True), name


def test_onpolicy_needs_both_parts() -> None:
    with pytest.raises(ValueError, match="both learner and onpolicy"):
        run_episode(LineWorld(), plan_episode(small_cfg(), 0, 0), small_cfg(), None, onpolicy=OnPolicy())
    with pytest.raises(ValueError, match="OnPolicy.beta"):
        OnPolicy(beta=1.5)
    with pytest.raises(ValueError, match="round"):
        OnPolicy(round=0)


def test_dagger_world_seeds_and_routes_are_disjoint_from_the_benchmarks() -> None:
    from yawil.bench.suites import SUITES, episodes

    bench = [ep for suite in SUITES for ep in episodes(suite)]  # every protocol episode of every suite
    assert max(ep.world_seed for ep in bench) < BENCH_WORLD_SEED_LIMIT
    cfg = CollectConfig()
    seeds = [plan_episode(cfg, s, i, BENCH_WORLD_SEED_LIMIT).world_seed for s in (1000, 2000, 1001) for i in range(300)]
    assert min(seeds) >= BENCH_WORLD_SEED_LIMIT
    reject = BenchmarkRoutes("town01")
    assert len(reject.ends) > 0
    for ep in bench:
        if ep.town != "town01":
            continue
        s, g = ep.route.start, ep.route.goal
        assert reject(SimpleNamespace(xy=np.array([[s.x, s.y], [g.x, g.y]])))
        assert not reject(SimpleNamespace(xy=np.array([[s.x + 40.0, s.y], [g.x, g.y]])))
    # the closed-loop validation set of `yawil select` keeps off them too
    val = validation_episodes(routes=2)
    assert len(val) == 8 and min(ep.world_seed for ep in val) >= BENCH_WORLD_SEED_LIMIT
    assert not any(reject.matches((e.route.start.x, e.route.start.y), (e.route.goal.x, e.route.goal.y)) for e in val)
    assert {ep.weather for ep in val} <= set(CollectConfig().weathers)


def test_a_rejecting_town_is_an_error_not_a_hang(tmp_path: Path) -> None:
    learner = Learner(factory=lambda: Scripted(Control()), onpolicy=OnPolicy(), identity="x",
                      reject_route=lambda route: True)
    with pytest.raises(ValueError, match="rejected"):
        collect(tmp_path / "r", town="line", weathers="ClearNoon", episodes=1, progress=False,
                world_factory=LineWorld, config=small_cfg(), learner=learner)


def test_dagger_config_is_checked() -> None:
    with pytest.raises(ValueError, match="train_mode"):
        DaggerConfig(train_mode="sometimes")
    with pytest.raises(ValueError, match="beta"):
        DaggerConfig(beta=(0.5, 2.0))
    with pytest.raises(ValueError, match="round0"):
        DaggerConfig(round0="x.pt")
    with pytest.raises(ValueError, match="round_lr"):
        DaggerConfig(round_lr=0.0)
    assert DaggerConfig(beta=(0.5, 0.25)).beta_of(1) == 0.5 and DaggerConfig(beta=(0.5, 0.25)).beta_of(5) == 0.25
    with pytest.raises(ValueError, match="aux head"):
        DaggerConfig(speed_control=True)  # the target speed comes from the aux head
    assert DaggerConfig(speed_control=True, train_args={"model_args": {"aux": True}, "aux_weight": 0.5}).speed_control
    aux_args = {"model_args": {"aux": True, "lead_stop": True}, "aux_weight": 0.5}
    assert DaggerConfig(speed_control="stop", train_args=aux_args).speed_control == "stop"
    with pytest.raises(ValueError, match="speed_control"):
        DaggerConfig(speed_control="brake", train_args=aux_args)
    assert DaggerConfig(expert_args={"comfort_decel": 1.0}).expert_config().comfort_decel == 1.0
    with pytest.raises(ValueError, match="unknown expert setting"):
        DaggerConfig(expert_args={"softly": 1.0})
    with pytest.raises(ValueError, match="guidance_reference"):
        DaggerConfig(guidance_reference="north")
    with pytest.raises(ValueError, match="guidance_reference"):
        DaggerConfig(guidance_reference="ego", expert_data="data/x")  # given data keep their own reference


def test_a_resume_may_change_the_executor_and_nothing_else(tmp_path: Path) -> None:
    """The run records where its episodes ran; another executor on resume changes no result, so it is allowed
    (and recorded), while a changed setting still is not."""
    from dataclasses import replace

    cfg = DaggerConfig(expert_frames=30, workers=2)
    DaggerRun(tmp_path, cfg).check_config()
    assert json.loads((tmp_path / "dagger.json").read_text())["executor"] == "local"
    DaggerRun(tmp_path, replace(cfg, executor="ray", ray_address="auto")).check_config()
    assert json.loads((tmp_path / "dagger.json").read_text())["ray_address"] == "auto"
    with pytest.raises(ValueError, match="workers: 2 -> 3"):
        DaggerRun(tmp_path, replace(cfg, workers=3)).check_config()
    with pytest.raises(ValueError, match="--executor 'dask'"):
        DaggerConfig(executor="dask")


def test_a_finished_run_may_grow_rounds_with_their_own_traffic(tmp_path: Path) -> None:
    """Per-round settings (beta, traffic; the last repeats): added rounds may differ, the rounds run may not.
    One pair is written flat, as dagger.json held it before traffic was per round, so older folders resume."""
    from dataclasses import replace

    from yawil.pipelines.dagger import _traffic

    cfg = DaggerConfig(expert_frames=30, rounds=1, round_vehicles=(50, 60), round_pedestrians=(30, 40))
    DaggerRun(tmp_path, cfg).check_config()
    saved = json.loads((tmp_path / "dagger.json").read_text())
    assert saved["round_vehicles"] == [50, 60] and saved["round_pedestrians"] == [30, 40]
    grown = replace(cfg, rounds=2, round_vehicles=_traffic("50-60,100-130"), round_pedestrians=((30, 40), (50, 70)),
                    beta=(0.0, 0.5))
    assert grown.traffic_of(1) == {"vehicles": (50, 60), "pedestrians": (30, 40)}
    assert grown.traffic_of(2) == grown.traffic_of(7) == {"vehicles": (100, 130), "pedestrians": (50, 70)}
    DaggerRun(tmp_path, grown).check_config()
    assert json.loads((tmp_path / "dagger.json").read_text())["round_vehicles"] == [[50, 60], [100, 130]]
    with pytest.raises(ValueError, match="round_vehicles"):  # round 1 was driven at 50-60
        DaggerRun(tmp_path, replace(grown, round_vehicles=((40, 60), (100, 130)))).check_config()
    with pytest.raises(ValueError, match="beta"):  # and round 2 is now part of the run
        DaggerRun(tmp_path, replace(grown, rounds=3, beta=(0.0, 0.2, 0.5))).check_config()
    assert DaggerConfig().traffic_of(1) == {}  # none given: collect's default
    with pytest.raises(ValueError, match="round_vehicles"):
        DaggerConfig(round_vehicles=((10, 5),))


def test_a_finished_run_may_grow_rounds_driven_otherwise(tmp_path: Path) -> None:
    """The learner's drive may change for added rounds only; the finished rounds' stage markers keep the drive
    that collected them, so dagger.json taking the new one loses no history."""
    from dataclasses import replace

    aux = {"model_args": {"aux": True}}
    cfg = DaggerConfig(expert_frames=30, rounds=1, speed_control="stop", stop_release=10.0, train_args=aux)
    run = DaggerRun(tmp_path, cfg)
    run.check_config()
    run.stage("data_01").parent.mkdir(parents=True)
    run.stage("data_01").write_text(json.dumps({"frames": 5}))  # a round finished before markers held the drive
    gated = replace(cfg, stop_hold=1.0, stop_gate=25.0)
    with pytest.raises(ValueError, match=r"stop_gate: 0.0 -> 25.0.*give --rounds 2"):
        DaggerRun(tmp_path, gated).check_config()  # round 1 was driven without the gate
    DaggerRun(tmp_path, replace(gated, rounds=2)).check_config()
    assert json.loads((tmp_path / "dagger.json").read_text())["stop_gate"] == 25.0
    marker = json.loads(run.stage("data_01").read_text())
    assert marker["frames"] == 5 and marker["drive"] == {"speed_control": "stop", "stop_release": 10.0,
                                                         "stop_creep": 0.0, "stop_hold": 0.0, "stop_gate": 0.0,
                                                         "light_hold": 0.0}
    assert DaggerRun(tmp_path, replace(gated, rounds=2)).drive()["stop_gate"] == 25.0


def test_the_dagger_learner_drives_as_benched(tiny_checkpoint: Any) -> None:
    """With speed_control the learner's throttle and brake come from its aux head's target speed."""
    from yawil.pipelines.dagger import load_learner

    path, _ = tiny_checkpoint("yilratt", guidance=AGENT_GC, spread=True, aux=True)
    assert load_learner(str(path), 1, True).drive.speed_control == "target"
    assert load_learner(str(path), 1).drive.speed_control is None


def test_a_tiny_dagger_run_end_to_end_and_resumed(tmp_path: Path) -> None:
    """Embedded town01, the small yaw-guided net: round 0 and one on-policy round, then a rerun skips all.

    Ego-referenced guidance, so that the round's frames are seen to follow the expert data's config."""
    cfg = DaggerConfig(model="yaw-guided", expert_frames=30, rounds=1, round_frames=20, episode_frames=40,
                       round0_steps=2, round_steps=2, batch_size=8, workers=1, threads=1, round_lr=2e-4,
                       train_args={"val_fraction": 0.5, "augment": {"enabled": False}}, guidance_reference="ego",
                       round_vehicles=(3, 3), round_pedestrians=(0, 1))
    out = tmp_path / "dg"
    # two expert episodes are needed for a split: 30 frames at <= 40 per episode
    final = DaggerRun(out, cfg, log=lambda m: None, progress=False).run()
    assert final == out / "train" / "round_01" / "last.pt" and final.is_file()
    m = read_manifest(out / "data" / "round_01")
    assert m.frames >= 20 and m.config["learner"]["checkpoint"].endswith("round_00/last.pt")
    assert m.config["learner"]["drive"]["speed_control"] is False  # the drive that collected the round
    assert json.loads((out / "stages" / "data_01.json").read_text())["drive"] == m.config["learner"]["drive"]
    assert (list(m.config["collector"]["vehicles"]), list(m.config["collector"]["pedestrians"])) == ([3, 3], [0, 1])
    assert m.config["guidance"]["reference"] == "ego" == read_manifest(out / "data" / "expert").config["guidance"]["reference"]
    with open_episode(m.path_of(m.episodes[0])) as ep:
        labels = ep.labels()
    assert (labels["round"] == 1).all() and set(labels["driver"].tolist()) <= {LEARNER, TAKEOVER}
    assert all(e.episode >= 1000 * 100_000 for e in m.episodes)  # round seeds keep the ids apart
    marker = json.loads((out / "stages" / "train_01.json").read_text())
    assert marker["steps"] == 2 and marker["init_from"].endswith("round_00/last.pt")
    lrs = [yaml.safe_load((out / "train" / f"round_0{r}" / "config.yaml").read_text())["lr"] for r in (0, 1)]
    assert lrs == [cfg.lr, 2e-4]  # round 0 trains at --lr, the fine-tuning round at --round-lr
    logs: list[str] = []
    DaggerRun(out, cfg, log=logs.append, progress=False).run()
    assert sum("skipped" in line for line in logs) == 4
    with pytest.raises(ValueError, match="other settings"):
        DaggerRun(out, DaggerConfig(**{**cfg.to_dict(), "beta": (0.5,)}), log=lambda m: None).run()
    saved = json.loads((out / "dagger.json").read_text())
    del saved["speed_control"]  # a folder written before the setting existed still resumes
    (out / "dagger.json").write_text(json.dumps(saved))
    DaggerRun(out, cfg, log=lambda m: None, progress=False).run()


def test_select_picks_the_checkpoint_that_drives_best(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                      tiny_checkpoint: Any) -> None:
    """The ranking of `yawil select` (the driving itself is the benchmark runner's, tested there)."""
    import yawil.bench.runner as runner
    from yawil.bench.records import EpisodeLog
    from yawil.bench.select import select_checkpoint

    paths = []
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
        p, _ = tiny_checkpoint("yaw-guided", folder=tmp_path / name, guidance=AGENT_GC, spread=True)
        paths.append(p)
    wins = {"a": 1, "b": 2, "c": 2}
    crashes = {"a": 0, "b": 1, "c": 0}

    def fake(eps, spec, out, **kw):  # type: ignore[no-untyped-def]
        who = Path(spec.agent).parent.name
        with EpisodeLog(out) as log:
            for i, ep in enumerate(eps):
                log.append({"task": ep.task, "condition": ep.condition, "weather": ep.weather, "route_id": ep.route_id,
                            "seed": ep.seed,
                            "success": i < wins[who], "km_driven": 0.1,
                            "collisions": [{"type": "vehicle"}] if i == len(eps) - 1 and crashes[who] else []})

    monkeypatch.setattr(runner, "run_benchmark", fake)
    result = select_checkpoint(paths, tmp_path / "sel", routes=1, progress=False)
    assert result["selected"] == str(paths[2])  # b and c drive 2 of 4, c without a collision
    assert [r["successes"] for r in result["candidates"]] == [1, 2, 2]
    assert json.loads((tmp_path / "sel" / "selection.json").read_text())["selected"] == str(paths[2])


def test_dagger_cli_refuses_bad_options_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.cli import main

    for argv, text in (
        (["--beta", "0.5,x"], "--beta"),
        (["--train-arg", "nonsense=1"], "--train-arg"),
        (["--train-arg", "speed_dropout=2"], "speed_dropout"),
        (["--round0", str(tmp_path / "none.pt")], "round0"),
        (["--expert-arg", "comfort_decel=soft"], "--expert-arg"),
        (["--ray-address", "auto"], "--ray-address 'auto' applies to --executor ray only"),
    ):
        with pytest.raises(SystemExit) as err:
            main(["dagger", "--out", str(tmp_path / "o"), *argv])
        assert text in str(err.value) and "\n" not in str(err.value)


def test_a_round0_of_another_model_is_refused_before_any_collection(tmp_path: Path, tiny_checkpoint: Any,
                                                                    tiny_dataset: Any) -> None:
    import time

    ckpt = tiny_checkpoint("yaw-guided", guidance_dim=15).path
    data = tiny_dataset(episodes=2, frames=5, k=15)
    t0 = time.perf_counter()
    for model, args, text in (("yilratt", {}, "a yaw-guided checkpoint; the rounds train --model yilratt"),
                              ("yaw-guided", {"model_args": {"aux": True}}, "built with aux=")):
        cfg = DaggerConfig(model=model, round0=str(ckpt), expert_data=str(data), rounds=1, train_args=args)
        with pytest.raises(ValueError, match=text):
            DaggerRun(tmp_path / f"dg_{model}", cfg, log=lambda m: None, progress=False).run()
        assert not (tmp_path / f"dg_{model}" / "data").exists()
        assert not (tmp_path / f"dg_{model}" / "dagger.json").exists()  # the corrected command may use the folder
    cfg = DaggerConfig(model="yaw-guided", round0=str(ckpt), expert_data=str(data), rounds=1, speed_control=True)
    with pytest.raises(ValueError, match="needs a model with the aux head"):
        DaggerRun(tmp_path / "dg_speed", cfg, log=lambda m: None, progress=False).run()
    assert time.perf_counter() - t0 < 30
