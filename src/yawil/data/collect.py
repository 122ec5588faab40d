"""Data collection: episodes (yawil.data.episode) run in one process or a pool of them, each process with its
own world and writer, until the dataset holds the frame or episode budget.

A second run of the same command resumes: episodes already in the manifest are skipped, never duplicated,
and damaged episode files are collected again. Rules and options: docs/expert.md.
"""

from __future__ import annotations

import os
import queue
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from yawil.data.collect_config import COLLISION_POLICIES, CollectConfig, OnPolicy
from yawil.data.episode import (
    EPISODE_STRIDE,
    Driver,
    EpisodePlan,
    EpisodeResult,
    SteeringNoise,
    episode_id,
    expert_labels,
    plan_episode,
    run_episode,
)
from yawil.data.manifest import read_manifest
from yawil.data.writer import DatasetWriter
from yawil.expert import ExpertConfig
from yawil.guidance import GuidanceConfig
from yawil.sim.types import Route, World


# -------------------------------------------------------------------------------------------- orchestration
@dataclass
class CollectSummary:
    out: str
    episodes_written: int = 0
    frames_written: int = 0
    episodes_skipped: int = 0  # already in the dataset (resume)
    episodes_discarded: int = 0
    outcomes: dict[str, int] = field(default_factory=dict)
    drivers: dict[str, int] = field(default_factory=dict)  # frames run per driver (on-policy rounds)
    takeovers: int = 0
    dataset_frames: int = 0
    seconds: float = 0.0

    @property
    def frames_per_second(self) -> float:
        return self.frames_written / self.seconds if self.seconds > 0 else 0.0


def dataset_config(cfg: CollectConfig, guidance: GuidanceConfig, expert_config: ExpertConfig,
                   learner: Learner | None = None) -> dict[str, Any]:
    d: dict[str, Any] = {"guidance": guidance.to_dict(), "collector": cfg.to_dict(), "expert": expert_config.to_dict()}
    if learner is not None:
        d["learner"] = {"checkpoint": learner.identity, "onpolicy": asdict(learner.onpolicy),
                        "min_world_seed": learner.min_world_seed}
    return d


def _learner_args(spec: Learner | None, driver: Driver | None) -> dict[str, Any]:
    if spec is None:
        return {}
    return {"learner": driver, "onpolicy": spec.onpolicy, "reject_route": spec.reject_route}


WorldFactory = Callable[[], World]


def embedded_world() -> World:
    """The default world factory: the embedded simulator (imported here, so each spawned worker loads it)."""
    from yawil.sim import make_world

    world: World = make_world(backend="embedded")
    return world


# per-process state of a worker
_WORKER: dict[str, Any] = {}


@dataclass(frozen=True)
class Learner:
    """What an on-policy collection needs beyond the expert's: who shares the wheel, and how.

    `factory` makes the learner in each process (picklable: a module-level function or a partial of one);
    `reject_route` (picklable too) turns down routes that must not be driven; world seeds start at
    `min_world_seed`. The dataset config records `identity` (the checkpoint) and `onpolicy`.
    """

    factory: Callable[[], Driver]
    onpolicy: OnPolicy
    identity: str
    min_world_seed: int = 0
    reject_route: Callable[[Route], bool] | None = None


def _worker_init(out: str, cfg: CollectConfig, guidance: GuidanceConfig, expert_config: ExpertConfig,
                 progress: Any, world_factory: WorldFactory, learner: Learner | None = None) -> None:
    _WORKER.update(cfg=cfg, guidance=guidance, expert=expert_config, progress=progress, learner_spec=learner,
                   writer=DatasetWriter(out, dataset_config(cfg, guidance, expert_config, learner)),
                   world=world_factory(), learner=learner.factory() if learner is not None else None)


def _worker_episode(seed: int, index: int) -> EpisodeResult:
    w = _WORKER
    spec: Learner | None = w["learner_spec"]
    plan = plan_episode(w["cfg"], seed, index, spec.min_world_seed if spec is not None else 0)
    if w["writer"].has_episode(plan.episode_id):
        return EpisodeResult(plan.episode_id, index, "skipped")
    pending = [0]

    def tick(n: int) -> None:
        pending[0] += n
        if pending[0] >= 50:
            w["progress"].put((plan.episode_id, pending[0]))
            pending[0] = 0

    result = run_episode(w["world"], plan, w["cfg"], w["writer"], w["guidance"], w["expert"], on_frame=tick,
                         **_learner_args(spec, w["learner"]))
    if pending[0]:
        w["progress"].put((plan.episode_id, pending[0]))
    return result


def collect(
    out: str | os.PathLike[str],
    town: str = "town01",
    weathers: Sequence[str] | str = "train",
    frames: int | None = 200_000,
    workers: int = 1,
    seed: int = 0,
    episodes: int | None = None,
    config: CollectConfig | None = None,
    guidance: GuidanceConfig | None = None,
    expert_config: ExpertConfig | None = None,
    progress: bool = True,
    world_factory: WorldFactory = embedded_world,
    learner: Learner | None = None,
    desc: str = "collect",
    verify: bool = False,
    **overrides: Any,
) -> CollectSummary:
    """Collect expert episodes into the dataset at `out` until it holds `frames` frames (or `episodes` done).

    `weathers` is a set name ("train", "test", "all") or names. `config` fields can also be given as keyword
    overrides (e.g. vehicles=(30, 30)). Resumable: run it again and it continues where it stopped.
    `world_factory` makes each process's simulator; with workers > 1 it must be picklable (a module-level
    function), as spawned processes import it. `learner` makes it an on-policy (DAgger) collection.
    One process at a time writes a dataset (yawil.locking). On resume, episode files that are missing,
    truncated or unreadable are dropped and collected again (`verify`: decode every image too).
    """
    from yawil.locking import folder_lock

    if world_factory is embedded_world:  # a typo'd town must not leave a dataset behind that blocks the rerun
        from yawil.sim.town.map.layout import resolve_town

        resolve_town(town)
    with folder_lock(out, "dataset"):
        return _collect(out, town, weathers, frames, workers, seed, episodes, config, guidance, expert_config,
                        progress, world_factory, learner, desc, verify, **overrides)


def _collect(
    out: str | os.PathLike[str], town: str, weathers: Sequence[str] | str, frames: int | None, workers: int,
    seed: int, episodes: int | None, config: CollectConfig | None, guidance: GuidanceConfig | None,
    expert_config: ExpertConfig | None, progress: bool, world_factory: WorldFactory, learner: Learner | None,
    desc: str, verify: bool, **overrides: Any,
) -> CollectSummary:
    from yawil.sim.weather import weather_set

    if frames is None and episodes is None:
        raise ValueError("collect needs a budget: frames or episodes")
    if frames is not None and frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if episodes is not None and not 1 <= episodes <= EPISODE_STRIDE:
        raise ValueError(f"episodes must be in [1, {EPISODE_STRIDE}], got {episodes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    names = weather_set(weathers) if isinstance(weathers, str) else tuple(weathers)
    cfg = replace(config or CollectConfig(), town=town, weathers=tuple(names), **overrides)
    gcfg = guidance or GuidanceConfig()
    ecfg = expert_config or ExpertConfig()
    out = str(out)
    t0 = time.perf_counter()
    writer = DatasetWriter(out, dataset_config(cfg, gcfg, ecfg, learner))  # creates, or checks the config on resume
    from yawil.data.check import remove_bad_episodes

    for line in remove_bad_episodes(out, images=verify):  # a damaged episode is collected again, not skipped
        print(f"collect: re-collecting {line}", file=sys.stderr)
    manifest = read_manifest(out)
    done = set(manifest.episode_ids())
    summary = CollectSummary(out=out, dataset_frames=manifest.frames)
    limit = episodes if episodes is not None else EPISODE_STRIDE

    def todo() -> Iterator[int]:
        for i in range(limit):
            if episode_id(seed, i) in done:
                summary.episodes_skipped += 1
                continue
            yield i

    def budget_left(in_flight: int, mean_frames: float) -> bool:
        return frames is None or summary.dataset_frames + in_flight * mean_frames < frames

    def account(r: EpisodeResult) -> None:
        summary.outcomes[r.outcome] = summary.outcomes.get(r.outcome, 0) + 1
        if r.outcome == "skipped":
            summary.episodes_skipped += 1
        elif r.outcome.startswith("discarded"):
            summary.episodes_discarded += 1
        else:
            summary.episodes_written += 1
            summary.frames_written += r.frames_kept
            summary.takeovers += r.takeovers
            for name, n in r.drivers.items():
                summary.drivers[name] = summary.drivers.get(name, 0) + n
            summary.dataset_frames += r.frames_kept

    bar = _Progress(frames, summary.dataset_frames, desc) if progress else None
    indices = todo()
    try:
        if workers == 1:
            world = world_factory()
            driver = learner.factory() if learner is not None else None
            try:
                for i in indices:
                    if not budget_left(0, 0.0):
                        break
                    plan = plan_episode(cfg, seed, i, learner.min_world_seed if learner is not None else 0)
                    tick = None if bar is None else (lambda n, ep=plan.episode_id: bar.frame(ep, n))
                    r = run_episode(world, plan, cfg, writer, gcfg, ecfg, on_frame=tick, **_learner_args(learner, driver))
                    account(r)
                    if bar is not None:
                        bar.episode(r, summary)
            finally:
                world.close()
        else:
            _run_pool(out, cfg, gcfg, ecfg, seed, workers, indices, budget_left, account, bar, summary, world_factory,
                      learner)
    finally:
        if bar is not None:
            bar.close()
        writer.close()
    summary.seconds = time.perf_counter() - t0
    return summary


def _run_pool(out: str, cfg: CollectConfig, gcfg: GuidanceConfig, ecfg: ExpertConfig, seed: int, workers: int,
              indices: Iterator[int], budget_left: Callable[[int, float], bool], account: Callable[[EpisodeResult], None],
              bar: _Progress | None, summary: CollectSummary, world_factory: WorldFactory,
              learner: Learner | None = None) -> None:
    """N spawn-context processes, each with its own world and writer; at most N episodes in flight.

    Any exception (a worker's, or Ctrl-C) terminates the workers at once: their episodes in progress are
    lost (their temporary files are removed by the next writer on this dataset), committed ones are kept.
    """
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    progress_q: Any = ctx.Queue() if bar is not None else _NullQueue()
    kept: list[int] = []
    pool = ctx.Pool(workers, initializer=_worker_init,
                    initargs=(out, cfg, gcfg, ecfg, progress_q, world_factory, learner))
    running: dict[int, Any] = {}  # index -> AsyncResult
    exhausted = False
    try:
        while True:
            mean = float(np.mean(kept)) if kept else 0.0
            while not exhausted and len(running) < workers and budget_left(len(running), mean):
                i = next(indices, None)
                if i is None:
                    exhausted = True
                    break
                running[i] = pool.apply_async(_worker_episode, (seed, i))
            if not running:
                break
            next(iter(running.values())).wait(0.25)
            if bar is not None:
                bar.drain(progress_q)
            for i in [i for i, res in running.items() if res.ready()]:
                r: EpisodeResult = running.pop(i).get()  # re-raises a worker's exception here
                account(r)
                if r.frames_kept:
                    kept.append(r.frames_kept)
                if bar is not None:
                    bar.episode(r, summary)
        pool.close()
        pool.join()
    except BaseException:
        pool.terminate()
        pool.join()
        raise


class _NullQueue:
    def put(self, item: tuple[int, int]) -> None:
        pass


class _Progress:
    """A tqdm bar of stored frames: live counts from the episodes in progress, corrected at each episode's end
    (a trimmed collision takes frames back)."""

    def __init__(self, frames: int | None, have: int, desc: str = "collect") -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=frames, initial=min(have, frames) if frames else have, unit="frame", unit_scale=True,
                        desc=desc, dynamic_ncols=True, smoothing=0.05)
        self.live: dict[int, int] = {}

    def frame(self, episode: int, n: int) -> None:
        self.live[episode] = self.live.get(episode, 0) + n
        self.bar.update(n)
        if self.bar.total and self.bar.n > self.bar.total:  # episodes are stored whole: the budget is a floor
            self.bar.total = self.bar.n

    def drain(self, q: Any) -> None:
        while True:
            try:
                episode, n = q.get_nowait()
            except queue.Empty:
                return
            self.frame(episode, n)

    def episode(self, r: EpisodeResult, summary: CollectSummary) -> None:
        self.bar.update(r.frames_kept - self.live.pop(r.episode_id, 0))
        self.bar.set_postfix(episodes=summary.episodes_written, last=r.outcome, refresh=True)

    def close(self) -> None:
        self.bar.close()


def collect_paths(out: str | os.PathLike[str]) -> list[Path]:
    """Episode files of a dataset, in id order (a small helper for the demo and the benchmark)."""
    m = read_manifest(out)
    return [m.path_of(e) for e in sorted(m.episodes, key=lambda e: e.episode)]


__all__ = [
    "COLLISION_POLICIES",
    "EPISODE_STRIDE",
    "CollectConfig",
    "CollectSummary",
    "EpisodePlan",
    "EpisodeResult",
    "Learner",
    "OnPolicy",
    "SteeringNoise",
    "expert_labels",
    "collect",
    "collect_paths",
    "episode_id",
    "plan_episode",
    "run_episode",
    "dataset_config",
    "embedded_world",
]
