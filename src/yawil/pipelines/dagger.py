"""`yawil dagger`: on-policy data aggregation with the privileged expert (DAgger; docs/training.md, "DAgger").

    round 0: expert data (`yawil collect`) and a policy trained on it (or a checkpoint given with --round0)
    round r: the round r-1 policy drives random training-town routes with the expert beside it; every frame
             is stored with the expert's control as its label (driver, round and the expert's privileged labels
             per frame, dataset schema 2), the expert taking the wheel when the learner strays, stalls or would
             need to brake harder than it can; then training goes on over the aggregate (fine-tuned from the
             last checkpoint, or retrained from scratch), and the next round.

Why: behaviour cloning only ever sees the expert's states, so the learner's own mistakes lead it where it has
no labels (Ross et al. 2011); Learning by Cheating measured NoCrash dense town01 27.7 -> 70.0 % with it. Our
expert labels any state for ~0.5 ms, so every visited frame is a label.

Every stage is resumable at any kill: collection per episode (the manifest), training from `last.pt`, and a
stage marker per finished stage under OUT/stages. The benchmark's world seeds and routes are never driven
(`BENCH_WORLD_SEED_LIMIT`, `yawil.bench.select.BenchmarkRoutes`).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from yawil.cliargs import seed
from yawil.executor import ExecutorConfig, add_executor_arguments, executor_from_args
from yawil.guidance import REFERENCES, GuidanceConfig
from yawil.policy.speed import (
    DRIVE_OPTIONS,
    SPEED_CONTROLS,
    add_speed_control_arguments,
    check_light_hold,
    check_stop_creep,
    check_stop_gate,
    check_stop_hold,
    check_stop_release,
    speed_control_mode,
)
from yawil.stages import read_marker, run_stage, write_marker

TRAIN_MODES = ("finetune", "scratch")
# Benchmark episodes use world seed 1000 * seed + route id (yawil.bench.suites.Episode.world_seed), far below this.
BENCH_WORLD_SEED_LIMIT = 1_000_000
ROUND_SEED_STRIDE = 1000  # round r's episodes are collected with seed + 1000 * r: ids unique across the aggregate


@dataclass(frozen=True)
class DaggerConfig:
    """One DAgger run. Budgets in frames and optimiser steps only, so the result does not depend on the machine."""

    model: str = "yilratt"
    town: str = "town01"
    seed: int = 0
    expert_frames: int = 20_000
    rounds: int = 2
    round_frames: int = 6_000  # on-policy frames stored per round
    episode_frames: int = 0  # > 0: end every episode after this many steps (small runs and tests)
    round0_steps: int = 750  # steps of the round-0 policy (or the steps of the --round0 checkpoint)
    round_steps: int = 375  # steps per round: fine-tune steps, or the extra steps of a retraining from scratch
    train_mode: str = "finetune"
    beta: tuple[float, ...] = (0.0,)  # probability that the expert drives a segment, per round (the last repeats)
    segment_seconds: float = 10.0
    takeover_lateral: float = 2.0
    takeover_decel: float = 4.0
    takeover_stall: float = 4.0
    takeover_seconds: float = 3.0
    batch_size: int = 64
    lr: float = 1e-3
    # fine-tuning rounds' initial rate (None: lr). Why: at 1e-3 a fresh Adam's first steps on the aggregate
    # broke a good round-0 policy's steering (0 of 100 after round 1; docs/experiments.md, 2026-12-02)
    round_lr: float | None = None
    workers: int = 2  # collection processes
    executor: str = "local"  # where they run (yawil.executor): changes no result, so a resume may change it
    ray_address: str | None = None
    threads: int = 0  # torch threads of training (0: all cores)
    train_args: dict[str, Any] = field(default_factory=dict)  # further TrainConfig settings (speed_dropout, ...)
    round0: str | None = None  # an existing round-0 checkpoint (then expert_data must be its data)
    expert_data: str | None = None  # an existing expert dataset instead of collecting one
    # the learner drives throttle and brake from its aux head (as benched): True/"target", "lead" or "stop"
    speed_control: bool | str = False
    stop_release: float = 0.0  # s: the learner's "stop" release, as `yawil bench --stop-release`
    stop_creep: float = 0.0  # m: the release's creep length, as `yawil bench --stop-creep`
    stop_hold: float = 0.0  # s: the learner's "stop" hold, as `yawil bench --stop-hold`
    stop_gate: float = 0.0  # m: the release's lead-distance gate, as `yawil bench --stop-gate`
    light_hold: float = 0.0  # s: the learner's wait at a light it sees, as `yawil bench --light-hold`
    # traffic of the on-policy rounds, per round ((LO, HI) drawn per episode; the last repeats; None: collect's
    # default; one (LO, HI) pair is every round's). Why: dense-traffic failures need the learner's own states in
    # queues, which the default 10-30 vehicles rarely make; per round so a finished run can grow a denser round
    round_vehicles: tuple[tuple[int, int], ...] | None = None
    round_pedestrians: tuple[tuple[int, int], ...] | None = None
    expert_args: dict[str, float] = field(default_factory=dict)  # ExpertConfig settings of the expert (labels, takeovers)
    # the yaw guidance's reference when round 0's data is collected here; rounds always take the expert data's
    guidance_reference: str = GuidanceConfig.reference

    def __post_init__(self) -> None:
        for name in ("round_vehicles", "round_pedestrians"):  # one (LO, HI) pair: every round's
            object.__setattr__(self, name, _per_round_traffic(getattr(self, name)))

        def need(ok: bool, name: str, want: str) -> None:
            if not ok:
                raise ValueError(f"dagger: {name}={getattr(self, name)!r}, expected {want}")

        for name in ("expert_frames", "round_frames", "round_steps", "batch_size", "workers"):
            need(_is_int(getattr(self, name)) and getattr(self, name) >= 1, name, "an integer >= 1")
        for name in ("rounds", "threads", "seed", "round0_steps", "episode_frames"):
            need(_is_int(getattr(self, name)) and getattr(self, name) >= 0, name, "an integer >= 0")
        need(self.train_mode in TRAIN_MODES, "train_mode", f"one of {TRAIN_MODES}")
        need(len(self.beta) >= 1 and all(0.0 <= b <= 1.0 for b in self.beta), "beta", "values in [0, 1]")
        need(self.round0 is not None or self.round0_steps >= 1, "round0_steps", ">= 1 unless --round0 is given")
        need(self.round0 is None or self.expert_data is not None, "round0", "given together with --expert-data")
        need(self.lr > 0 and math.isfinite(self.lr), "lr", "a number > 0")
        need(self.round_lr is None or (self.round_lr > 0 and math.isfinite(self.round_lr)), "round_lr", "a number > 0")
        need(isinstance(self.train_args, dict), "train_args", "a mapping of train settings")
        try:
            mode = speed_control_mode(self.speed_control)
        except ValueError:
            need(False, "speed_control", f"true, false or one of {', '.join(SPEED_CONTROLS)}")
        seconds, metres = "seconds >= 0, > 0 only with speed_control 'stop'", "metres >= 0, > 0 only with a stop_release"
        for name, check, given, want in (("stop_release", check_stop_release, mode, seconds),
                                         ("stop_creep", check_stop_creep, self.stop_release, metres),
                                         ("stop_hold", check_stop_hold, mode, seconds),
                                         ("stop_gate", check_stop_gate, self.stop_release, metres),
                                         ("light_hold", check_light_hold, mode, "seconds >= 0, > 0 only with a speed_control")):
            try:
                check(getattr(self, name), given)  # type: ignore[operator, arg-type]
            except ValueError:
                need(False, name, want)
        need(isinstance(self.expert_args, dict), "expert_args", "a mapping of ExpertConfig settings")
        for name in ("round_vehicles", "round_pedestrians"):
            v = getattr(self, name)
            need(v is None or (len(v) >= 1 and all(len(p) == 2 and all(_is_int(x) for x in p) and 0 <= p[0] <= p[1]
                                                   for p in v)), name,
                 "None or (LO, HI) integers with 0 <= LO <= HI, one pair or one per round")
        need(self.guidance_reference in REFERENCES, "guidance_reference", f"one of {', '.join(REFERENCES)}")
        need(self.expert_data is None or self.guidance_reference == GuidanceConfig.reference, "guidance_reference",
             f"{GuidanceConfig.reference} (the default) with --expert-data (the data's own reference is used)")
        self.expert_config()  # an unknown or invalid expert setting fails here
        self.executor_config()  # and an unknown executor
        from yawil.data.collect import OnPolicy
        from yawil.sim.town.map.layout import resolve_town

        resolve_town(self.town)  # before dagger.json is written: a typo'd town blocked the corrected command
        OnPolicy(round=1, beta=self.beta[0], segment_seconds=self.segment_seconds,  # takeover settings, checked
                 takeover_lateral=self.takeover_lateral, takeover_decel=self.takeover_decel,  # before round 0
                 takeover_stall=self.takeover_stall, takeover_seconds=self.takeover_seconds)
        aux = (self.train_args.get("model_args") or {}).get("aux") is True
        need(not self.speed_control or aux or self.round0 is not None, "speed_control",
             "a model with an aux head (--train-arg 'model_args={\"aux\": true}' --train-arg aux_weight=...)")

    def expert_config(self) -> Any:
        from yawil.expert import ExpertConfig

        return ExpertConfig.from_settings(self.expert_args, "--expert-arg")

    def executor_config(self) -> ExecutorConfig:
        return ExecutorConfig(self.executor, self.ray_address)

    def beta_of(self, r: int) -> float:
        return float(_of_round(self.beta, r))

    def traffic_of(self, r: int) -> dict[str, tuple[int, int]]:
        """Round r's traffic as `collect` takes it (only what is set: the rest is collect's default)."""
        return {key: _of_round(v, r) for key, v in (("vehicles", self.round_vehicles),
                                                   ("pedestrians", self.round_pedestrians)) if v is not None}

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["beta"] = list(self.beta)
        for name in ("round_vehicles", "round_pedestrians"):  # one pair is written flat, as before per-round traffic
            v = getattr(self, name)
            d[name] = None if v is None else list(v[0]) if len(v) == 1 else [list(p) for p in v]
        return d


# settings given per round (the last repeats): a finished run may grow rounds whose values differ from here on
PER_ROUND = ("beta", "round_vehicles", "round_pedestrians")
# the learner's drive: a finished run may grow rounds driven otherwise (a better drive found after its rounds
# reaches other states); each round's dataset and stage marker record the drive that collected it, and a round
# collected in part refuses another (its dataset's config differs)
DRIVE = DRIVE_OPTIONS


def _of_round(values: Sequence[Any], r: int) -> Any:
    """Round r's entry of a per-round setting (rounds count from 1; the last entry repeats)."""
    return values[min(r, len(values)) - 1]


def _per_round_traffic(v: Any) -> Any:
    """(LO, HI) -> ((LO, HI),); a sequence of pairs -> a tuple of tuples; anything else unchanged (checked later)."""
    if v is None or not isinstance(v, (list, tuple)) or not v:
        return v
    if all(_is_int(x) for x in v):
        return (tuple(v),)
    return tuple(tuple(p) if isinstance(p, (list, tuple)) else p for p in v)


def _round_value(d: dict[str, Any], name: str, r: int) -> Any:
    """Round r's value of a per-round setting of a dagger.json mapping."""
    v = d.get(name)
    if name != "beta":
        v = _per_round_traffic(v)
    if v is None or not isinstance(v, (list, tuple)) or not v:
        return v
    item = _of_round(v, r)
    return tuple(item) if isinstance(item, (list, tuple)) else item


def _traffic(text: str) -> tuple[tuple[int, int], ...]:
    from yawil.data.collect_cli import int_range  # parsed as yawil collect --vehicles parses it

    return tuple(int_range(part.strip()) for part in text.split(","))


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def load_learner(checkpoint: str, threads: int = 1, speed_control: bool | str = False, **release: float) -> Any:
    """The learner of a collection process: the checkpoint's agent on the CPU, with `threads` torch threads,
    driving as it will be benchmarked (`speed_control`: throttle and brake from its target speed; `release`:
    stop_release, stop_creep, stop_hold, stop_gate, light_hold), so that the states it visits are the ones the benchmark will
    see."""
    import torch

    from yawil.agent import Agent

    torch.set_num_threads(threads)
    return Agent.from_checkpoint(checkpoint, device="cpu", speed_control=speed_control, **release)


# ------------------------------------------------------------------------------------------------- loop
class DaggerRun:
    """The folders of a run and its stages; `run()` does what is left."""

    def __init__(self, out: Path, cfg: DaggerConfig, log: Callable[[str], None] = print, progress: bool = True) -> None:
        self.out, self.cfg, self.log, self.progress = Path(out), cfg, log, progress

    # where things live
    def expert_data(self) -> Path:
        return Path(self.cfg.expert_data) if self.cfg.expert_data else self.out / "data" / "expert"

    def round_data(self, r: int) -> Path:
        return self.out / "data" / f"round_{r:02d}"

    def round_run(self, r: int) -> Path:
        return self.round_folder(self.out, r)

    @staticmethod
    def round_folder(out: Path, r: int) -> Path:
        """Round r's training folder of the run in `out` (also for those who name a run's checkpoint before it exists)."""
        return Path(out) / "train" / f"round_{r:02d}"

    def policy(self, r: int) -> Path:
        """The checkpoint that round r ends with (round 0: the given one or the trained one)."""
        if r == 0 and self.cfg.round0:
            return Path(self.cfg.round0)
        return self.round_run(r) / "last.pt"

    def guidance(self) -> GuidanceConfig:
        """The expert data's guidance config: the rounds' frames must be sampled the same way to be trained together."""
        from yawil.data.dataset import guidance_config_of

        return GuidanceConfig.from_dict(guidance_config_of([self.expert_data()]))

    def stage(self, name: str) -> Path:
        return self.out / "stages" / f"{name}.json"

    def data_roots(self, r: int) -> list[str]:
        return [str(self.expert_data())] + [str(self.round_data(i)) for i in range(1, r + 1)]

    # the run
    def check_config(self) -> None:
        """A run folder belongs to one config: resuming with another would mix two experiments."""
        from yawil.fileio import write_json_atomic

        path = self.out / "dagger.json"
        mine = self.cfg.to_dict()
        saved = read_marker(path)  # the same JSON-object file as a stage marker
        if saved is not None:
            # more rounds may be added to a finished run, with their own per-round values (the rounds it has keep
            # theirs); where the episodes run (the executor) changes no result
            growable = {"rounds", "executor", "ray_address", *PER_ROUND, *DRIVE}
            defaults = DaggerConfig().to_dict()  # a setting added later reads as its default in older folders
            saved = {**{k: v for k, v in defaults.items() if k not in saved}, **saved}
            diff = sorted(k for k in set(saved) | set(mine) if k not in growable and saved.get(k) != mine.get(k))
            had = int(saved["rounds"]) if _is_int(saved.get("rounds")) else 0
            diff += [k for k in PER_ROUND
                     if any(_round_value(saved, k, r) != _round_value(mine, k, r) for r in range(1, had + 1))]
            if diff:
                raise ValueError(
                    f"{path}: this folder holds a DAgger run with other settings ({', '.join(f'{k}: {saved.get(k)!r} -> {mine.get(k)!r}' for k in diff)}); "
                    "use another --out"
                )
            redrive = [k for k in DRIVE if saved.get(k) != mine.get(k)]
            if redrive and int(mine["rounds"]) <= had:
                raise ValueError(
                    f"{path}: the learner's drive ({', '.join(f'{k}: {saved.get(k)!r} -> {mine.get(k)!r}' for k in redrive)}) "
                    f"may change only for rounds added to the run (it has {had}; give --rounds {had + 1} or more)")
            if redrive:
                self.keep_drive({k: saved.get(k) for k in DRIVE}, had)
        self.out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, mine)

    def keep_drive(self, drive: dict[str, Any], rounds: int) -> None:
        """Before dagger.json takes a new drive, the finished rounds' stage markers that do not say which drive
        collected them (written before markers held it) are given the one they had, so the run keeps its history."""
        for r in range(1, rounds + 1):
            marker = read_marker(self.stage(f"data_{r:02d}"))
            if marker is not None and "drive" not in marker:
                write_marker(self.stage(f"data_{r:02d}"), {**marker, "drive": drive})

    def run(self) -> Path:
        from yawil.locking import folder_lock

        with folder_lock(self.out, "DAgger run"):
            return self._run()

    def check_round0(self) -> None:
        """--round0 must be the model the rounds train (name and the --train-arg model_args it was built with):
        the rounds start from its weights, so a mismatch would fail only after a round's collection."""
        from yawil.policy.checkpoint import load_checkpoint

        assert self.cfg.round0 is not None
        ckpt = load_checkpoint(self.cfg.round0, map_location="cpu")
        if ckpt["model_name"] != self.cfg.model:
            raise ValueError(f"--round0 {self.cfg.round0}: a {ckpt['model_name']} checkpoint; the rounds train "
                             f"--model {self.cfg.model}")
        if self.cfg.speed_control and not ckpt["model_config"].get("aux"):
            raise ValueError(f"--round0 {self.cfg.round0}: --speed-control needs a model with the aux head; this "
                             "checkpoint has none (trained without --model-arg aux=true)")
        wanted = self.cfg.train_args.get("model_args") or {}
        differ = {k: (ckpt["model_config"].get(k), v) for k, v in wanted.items() if ckpt["model_config"].get(k) != v}
        if differ:
            raise ValueError(f"--round0 {self.cfg.round0}: built with " + ", ".join(
                f"{k}={a!r}" for k, (a, _) in differ.items()) + "; --train-arg model_args asks for " + ", ".join(
                f"{k}={b!r}" for k, (_, b) in differ.items()))

    def _run(self) -> Path:
        cfg = self.cfg
        # the inputs first, before the folder records this config: a refused command must not block its own
        # corrected version (dagger.json would hold the refused settings)
        if cfg.expert_data is not None:
            from yawil.data.check import check_dataset

            if not (self.expert_data() / "manifest.json").is_file():
                raise ValueError(f"--expert-data {self.expert_data()}: not a yawil dataset (no manifest.json)")
            report = check_dataset(self.expert_data(), images=False)
            if not report.ok:
                raise ValueError(f"--expert-data {self.expert_data()}: fails yawil data check: "
                                 + "; ".join(report.lines()[-3:]))
        if cfg.round0 is not None:
            if not Path(cfg.round0).is_file():
                raise ValueError(f"--round0 {cfg.round0}: no such checkpoint")
            self.check_round0()
        self.check_config()
        t0 = time.perf_counter()
        if cfg.expert_data is None:
            run_stage(self.stage("expert_data"), self.collect_expert, self.log, "round 0: expert data")
        if cfg.round0 is None:
            run_stage(self.stage("train_00"), lambda: self.train(0), self.log, "round 0: training")
        for r in range(1, cfg.rounds + 1):
            run_stage(self.stage(f"data_{r:02d}"), functools.partial(self.collect_round, r), self.log,
                      f"round {r}: on-policy data (beta {cfg.beta_of(r)})")
            run_stage(self.stage(f"train_{r:02d}"), functools.partial(self.train, r), self.log, f"round {r}: training")
        final = self.policy(cfg.rounds)
        self.log(f"dagger: {cfg.rounds} round(s) done in {time.perf_counter() - t0:.0f} s; policy {final}")
        return final

    def collect_expert(self) -> dict[str, Any]:
        from yawil.data.collect import collect

        s = collect(self.expert_data(), town=self.cfg.town, weathers="train", frames=self.cfg.expert_frames,
                    workers=self.cfg.workers, seed=self.cfg.seed, progress=self.progress, desc="round 0",
                    max_episode_frames=self.cfg.episode_frames, expert_config=self.cfg.expert_config(),
                    executor=self.cfg.executor_config(), guidance=GuidanceConfig(reference=self.cfg.guidance_reference))
        return {"frames": s.dataset_frames, "episodes": s.episodes_written + s.episodes_skipped}

    def collect_round(self, r: int) -> dict[str, Any]:
        from yawil.bench.select import BenchmarkRoutes
        from yawil.data.collect import Learner, OnPolicy, collect

        cfg = self.cfg
        policy = self.policy(r - 1)
        onpolicy = OnPolicy(round=r, beta=cfg.beta_of(r), segment_seconds=cfg.segment_seconds,
                            takeover_lateral=cfg.takeover_lateral, takeover_decel=cfg.takeover_decel,
                            takeover_stall=cfg.takeover_stall, takeover_seconds=cfg.takeover_seconds)
        drive = self.drive()
        learner = Learner(factory=functools.partial(load_learner, str(policy), 1, **drive), onpolicy=onpolicy,
                          identity=str(policy.resolve()), drive=drive, min_world_seed=BENCH_WORLD_SEED_LIMIT,
                          reject_route=BenchmarkRoutes(cfg.town))
        # No steering noise (the learner makes its own mistakes); the second before a collision is not a label.
        traffic: dict[str, Any] = dict(cfg.traffic_of(r))  # only what is set: collect's defaults for the rest
        s = collect(self.round_data(r), town=cfg.town, weathers="train", frames=cfg.round_frames, workers=cfg.workers,
                    seed=cfg.seed + ROUND_SEED_STRIDE * r, progress=self.progress, learner=learner, desc=f"round {r}",
                    noise_fraction=0.0, trim_seconds=1.0, max_episode_frames=cfg.episode_frames,
                    expert_config=cfg.expert_config(), executor=cfg.executor_config(), guidance=self.guidance(),
                    **traffic)
        self.log(f"round {r}: {s.frames_written} frames stored this run; frames driven by "
                 f"{json.dumps(s.drivers)}; {s.takeovers} takeovers; outcomes {json.dumps(s.outcomes)}")
        return {"frames": s.dataset_frames, "drivers": s.drivers, "takeovers": s.takeovers, "outcomes": s.outcomes,
                "policy": str(policy), "drive": drive}

    def drive(self) -> dict[str, Any]:
        """The learner's drive settings, as `load_learner` and `yawil bench` take them."""
        return {k: getattr(self.cfg, k) for k in DRIVE}

    def train(self, r: int) -> dict[str, Any]:
        from yawil.learn.config import TrainConfig
        from yawil.learn.loop import train

        cfg = self.cfg
        base = {"model": cfg.model, "batch_size": cfg.batch_size, "lr": cfg.lr, "seed": cfg.seed,
                "threads": cfg.threads, "progress": self.progress, **cfg.train_args}
        if r == 0 or cfg.train_mode == "scratch":
            steps = cfg.round0_steps + r * cfg.round_steps
            init = None
        else:
            steps, init = cfg.round_steps, str(self.policy(r - 1))
            if cfg.round_lr is not None:
                base["lr"] = cfg.round_lr
        run_dir = self.round_run(r)
        tc = TrainConfig.from_dict({**base, "data": self.data_roots(r), "out": str(run_dir), "max_steps": steps,
                                    "init_from": init}, "dagger")
        result = train(tc, resume=(run_dir / "last.pt").is_file())
        last = result.metrics[-1] if result.metrics else {}
        return {"steps": result.steps, "val_loss": last.get("val_loss"), "best_val": result.best_val,
                "data": self.data_roots(r), "init_from": init}


# -------------------------------------------------------------------------------------------------- CLI
def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "dagger", help="on-policy data aggregation with the expert (DAgger rounds)", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    d = DaggerConfig()
    p.add_argument("--out", required=True, help="run folder (data/, train/, stages/, dagger.json)")
    p.add_argument("--model", default=d.model, help=f"model name (default {d.model})")
    p.add_argument("--town", default=d.town, help=f"training town (default {d.town})")
    p.add_argument("--seed", type=seed, default=d.seed, help="seed of collection and training (default 0)")
    p.add_argument("--expert-frames", type=int, default=d.expert_frames, help=f"round-0 expert frames (default {d.expert_frames})")
    p.add_argument("--rounds", type=int, default=d.rounds, help=f"on-policy rounds (default {d.rounds})")
    p.add_argument("--round-frames", type=int, default=d.round_frames, help=f"frames per round (default {d.round_frames})")
    p.add_argument("--round-vehicles", type=_traffic, default=None, metavar="N|LO-HI[,...]",
                   help="vehicles of the on-policy rounds' episodes, per round, comma-separated; the last repeats "
                        "(default: yawil collect's)")
    p.add_argument("--round-pedestrians", type=_traffic, default=None, metavar="N|LO-HI[,...]",
                   help="pedestrians of the on-policy rounds' episodes, per round, as --round-vehicles "
                        "(default: yawil collect's)")
    p.add_argument("--episode-frames", type=int, default=d.episode_frames,
                   help="end every episode after this many steps (default 0: no limit)")
    p.add_argument("--round0-steps", type=int, default=d.round0_steps, help=f"round-0 training steps (default {d.round0_steps})")
    p.add_argument("--round-steps", type=int, default=d.round_steps, help=f"training steps per round (default {d.round_steps})")
    p.add_argument("--train-mode", choices=TRAIN_MODES, default=d.train_mode,
                   help="finetune: go on from the last policy; scratch: retrain on the aggregate (default finetune)")
    p.add_argument("--beta", default=",".join(str(b) for b in d.beta),
                   help="probability per segment that the expert drives, per round, comma-separated; the last repeats (default 0)")
    p.add_argument("--segment-seconds", type=float, default=d.segment_seconds, help="length of a beta segment; 0: per episode")
    p.add_argument("--takeover-lateral", type=float, default=d.takeover_lateral, help="m off the route before the expert takes over")
    p.add_argument("--takeover-decel", type=float, default=d.takeover_decel,
                   help="m/s^2 of braking the learner would need before the expert takes over")
    p.add_argument("--takeover-stall", type=float, default=d.takeover_stall, help="s standing while the expert would drive")
    p.add_argument("--takeover-seconds", type=float, default=d.takeover_seconds, help="s the expert keeps the wheel")
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--lr", type=float, default=d.lr, help=f"initial learning rate (default {d.lr:g})")
    p.add_argument("--round-lr", type=float, default=None,
                   help="initial learning rate of the fine-tuning rounds (default: --lr)")
    p.add_argument("--workers", type=int, default=d.workers, help="collection processes (default 2)")
    add_executor_arguments(p)
    p.add_argument("--threads", type=int, default=d.threads, help="torch threads of training (default 0: all cores)")
    p.add_argument("--train-arg", action="append", default=[], metavar="KEY=VALUE",
                   help="a further train setting (JSON value), e.g. --train-arg speed_dropout=0.3")
    p.add_argument("--round0", default=None, help="use this checkpoint as the round-0 policy (with --expert-data)")
    p.add_argument("--expert-data", default=None, help="use this expert dataset as round 0's data")
    add_speed_control_arguments(p, "the learner, as yawil bench drives it: ")
    p.add_argument("--expert-arg", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting of the expert's ExpertConfig for its data, labels and takeovers (as yawil collect)")
    p.add_argument("--guidance-reference", choices=REFERENCES, default=d.guidance_reference,
                   help="yaw guidance reference of the expert data collected here (as yawil collect); with "
                        "--expert-data the data's own (default route)")
    p.add_argument("--no-progress", action="store_true")
    return p


def _floats(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"{option}: expected comma-separated numbers, got {text!r}") from None


def _expert_args(items: Sequence[str]) -> dict[str, float]:
    from yawil.expert import ExpertConfig

    return ExpertConfig.parse_items(items)  # the values are checked by DaggerConfig


def _train_args(items: Sequence[str]) -> dict[str, Any]:
    from yawil.learn.cli import _key_values
    from yawil.learn.config import TrainConfig

    known = {f.name for f in fields(TrainConfig)} - {"model", "data", "out", "max_steps", "init_from"}
    out = _key_values(list(items), "--train-arg")
    unknown = sorted(set(out) - known)
    if unknown:
        raise ValueError(f"--train-arg: unknown setting(s) {unknown}; known: {sorted(known)}")
    return out


def run(args: argparse.Namespace) -> int:
    try:
        cfg = DaggerConfig(
            model=args.model, town=args.town, seed=args.seed, expert_frames=args.expert_frames, rounds=args.rounds,
            round_frames=args.round_frames, episode_frames=args.episode_frames, round0_steps=args.round0_steps, round_steps=args.round_steps,
            train_mode=args.train_mode, beta=_floats(args.beta, "--beta"), segment_seconds=args.segment_seconds,
            takeover_lateral=args.takeover_lateral, takeover_decel=args.takeover_decel,
            takeover_stall=args.takeover_stall, takeover_seconds=args.takeover_seconds, batch_size=args.batch_size,
            lr=args.lr, round_lr=args.round_lr, workers=args.workers, executor=executor_from_args(args).kind, ray_address=args.ray_address,
            threads=args.threads, train_args=_train_args(args.train_arg),
            round0=args.round0, expert_data=args.expert_data, speed_control=args.speed_control,
            stop_release=args.stop_release, stop_creep=args.stop_creep, stop_hold=args.stop_hold,
            stop_gate=args.stop_gate, light_hold=args.light_hold,
            round_vehicles=args.round_vehicles, round_pedestrians=args.round_pedestrians,
            expert_args=_expert_args(args.expert_arg), guidance_reference=args.guidance_reference,
        )
        from yawil.learn.config import TrainConfig

        TrainConfig.from_dict({"model": cfg.model, **cfg.train_args}, "--train-arg")  # bad values fail before any work
        from yawil.fileio import check_not_inside_owned

        check_not_inside_owned(args.out, "--out")
        DaggerRun(Path(args.out), cfg, log=lambda m: print(f"[dagger {time.strftime('%H:%M:%S')}] {m}", flush=True),
                  progress=not args.no_progress).run()
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        raise SystemExit(f"yawil dagger: {err}") from None
    return 0
