"""Data collection: episodes (yawil.data.episode) run in this process or on workers (yawil.executor: local
processes, each with its own world committing to the dataset, or Ray actors shipping each finished episode file
back to this process, which stores it), until the dataset holds the frame or episode budget.

A second run of the same command resumes: episodes already in the manifest are skipped, never duplicated,
and damaged episode files are collected again. Rules and options: docs/expert.md.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from yawil.data.collect_config import COLLISION_POLICIES, DEFAULT_FRAMES, CollectConfig, OnPolicy
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
from yawil.data.manifest import EpisodeEntry, read_manifest
from yawil.data.writer import DatasetWriter, _pid_alive
from yawil.executor import Executor, ExecutorConfig, Report, for_worker, open_executor
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
        if learner.drive:  # only when given, so that datasets collected before it still resume
            d["learner"]["drive"] = dict(learner.drive)
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


@dataclass(frozen=True)
class Learner:
    """What an on-policy collection needs beyond the expert's: who shares the wheel, and how.

    `factory` makes the learner in each process (picklable: a module-level function or a partial of one);
    `reject_route` (picklable too) turns down routes that must not be driven; world seeds start at
    `min_world_seed`. The dataset config records `identity` (the checkpoint), `onpolicy` and `drive` (the
    learner's drive settings, where given: a resume with another drive is refused, as with another checkpoint).
    """

    factory: Callable[[], Driver]
    onpolicy: OnPolicy
    identity: str
    drive: dict[str, Any] = field(default_factory=dict)
    min_world_seed: int = 0
    reject_route: Callable[[Route], bool] | None = None


# ------------------------------------------------------------------------------------------------ workers
@dataclass(frozen=True)
class ShippedEpisode:
    """A finished episode file on its way from a worker that cannot write the dataset (a Ray actor, maybe on
    another machine) to the one process that does: the file's bytes and its manifest entry (None: discarded)."""

    result: EpisodeResult
    entry: EpisodeEntry | None
    data: bytes = b""


@dataclass(frozen=True)
class EpisodeWork:
    """Makes each worker of a collection (picklable, for spawned processes and Ray actors): its world (the
    rank-th factory when there is one per worker), its learner, and where its episodes go: `out`, the dataset
    each local worker commits to itself, or None to ship each finished file back (`ShippedEpisode`)."""

    out: str | None
    cfg: CollectConfig
    guidance: GuidanceConfig
    expert: ExpertConfig
    seed: int
    world_factory: WorldFactory | Sequence[WorldFactory] = embedded_world
    learner: Learner | None = None

    def __call__(self, rank: int, report: Report) -> CollectWorker:
        return CollectWorker(self, rank, report)


SCRATCH_PREFIX = "yawil-episode-"


def _remove_dead_scratch(folder: Path) -> None:
    """Remove the episode datasets of workers that were killed in the middle of one (their pid is gone)."""
    import re
    import shutil

    for p in folder.glob(f"{SCRATCH_PREFIX}*"):
        m = re.match(rf"{SCRATCH_PREFIX}(\d+)-", p.name)
        if m and not _pid_alive(int(m.group(1))):
            shutil.rmtree(p, ignore_errors=True)


class CollectWorker:
    """One process's world and learner, kept for all its episodes; a task is an episode index."""

    def __init__(self, work: EpisodeWork, rank: int, report: Report) -> None:
        self.work, self.report = work, report
        self.config = dataset_config(work.cfg, work.guidance, work.expert, work.learner)
        self.writer = DatasetWriter(work.out, self.config) if work.out is not None else None
        self.world = for_worker(work.world_factory, rank)()
        self.driver = work.learner.factory() if work.learner is not None else None

    def run(self, index: int) -> EpisodeResult | ShippedEpisode:
        w = self.work
        plan = plan_episode(w.cfg, w.seed, index, w.learner.min_world_seed if w.learner is not None else 0)
        if self.writer is not None:
            if self.writer.has_episode(plan.episode_id):  # committed meanwhile by another process
                return EpisodeResult(plan.episode_id, index, "skipped")
            return self._drive(plan, self.writer)
        import tempfile

        # the usual writer, in a dataset of its own that lives as long as the episode, named for this process so
        # that what a killed worker leaves is removed by the next episode on the same machine
        _remove_dead_scratch(Path(tempfile.gettempdir()))
        with tempfile.TemporaryDirectory(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-") as scratch:
            result = self._drive(plan, DatasetWriter(scratch, self.config))
            m = read_manifest(scratch)
            if not m.episodes:
                return ShippedEpisode(result, None)
            return ShippedEpisode(result, m.episodes[0], m.path_of(m.episodes[0]).read_bytes())

    def _drive(self, plan: EpisodePlan, writer: DatasetWriter) -> EpisodeResult:
        w, pending = self.work, [0]

        def tick(n: int) -> None:  # progress in batches: a queue message per frame would cost more than the frame
            pending[0] += n
            if pending[0] >= 50:
                self.report((plan.episode_id, pending[0]))
                pending[0] = 0

        result = run_episode(self.world, plan, w.cfg, writer, w.guidance, w.expert, on_frame=tick,
                             **_learner_args(w.learner, self.driver))
        if pending[0]:
            self.report((plan.episode_id, pending[0]))
        return result

    def close(self) -> None:
        self.world.close()


def collect(
    out: str | os.PathLike[str],
    town: str = "town01",
    weathers: Sequence[str] | str = "train",
    frames: int | None = DEFAULT_FRAMES,
    workers: int = 1,
    seed: int = 0,
    episodes: int | None = None,
    config: CollectConfig | None = None,
    guidance: GuidanceConfig | None = None,
    expert_config: ExpertConfig | None = None,
    progress: bool = True,
    world_factory: WorldFactory | Sequence[WorldFactory] = embedded_world,
    learner: Learner | None = None,
    desc: str = "collect",
    verify: bool = False,
    executor: ExecutorConfig = ExecutorConfig(),
    **overrides: Any,
) -> CollectSummary:
    """Collect expert episodes into the dataset at `out` until it holds `frames` frames (or `episodes` done).

    `weathers` is a set name ("train", "test", "all") or names. `config` fields can also be given as keyword
    overrides (e.g. vehicles=(30, 30)). Resumable: run it again and it continues where it stopped.
    `world_factory` makes each worker's simulator (a list: one factory per worker, as one CARLA server each);
    with workers > 1 or Ray it must be picklable (a module-level function, a partial of one). `learner` makes
    it an on-policy (DAgger) collection. `executor` says where the workers run (yawil.executor): the dataset
    is the same whichever it is and however many workers.
    One process at a time writes a dataset (yawil.locking). On resume, episode files that are missing,
    truncated or unreadable are dropped and collected again (`verify`: decode every image too).
    """
    from yawil.locking import folder_lock

    executor.check()
    if isinstance(world_factory, (list, tuple)) and len(world_factory) != workers:
        raise ValueError(f"{len(world_factory)} world factories for {workers} workers: give one per worker")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"--seed {seed!r}: expected an integer >= 0")
    if world_factory is embedded_world:  # a typo'd town must not leave a dataset behind that blocks the rerun
        from yawil.sim.town.map.layout import resolve_town

        resolve_town(town)
    with folder_lock(out, "dataset"):
        return _collect(out, town, weathers, frames, workers, seed, episodes, config, guidance, expert_config,
                        progress, world_factory, learner, desc, verify, executor, **overrides)


def _collect(
    out: str | os.PathLike[str], town: str, weathers: Sequence[str] | str, frames: int | None, workers: int,
    seed: int, episodes: int | None, config: CollectConfig | None, guidance: GuidanceConfig | None,
    expert_config: ExpertConfig | None, progress: bool, world_factory: WorldFactory | Sequence[WorldFactory],
    learner: Learner | None, desc: str, verify: bool, executor: ExecutorConfig, **overrides: Any,
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
    # local workers commit to the dataset themselves (as they always did); Ray workers ship their files here
    work = EpisodeWork(out if executor.kind == "local" else None, cfg, gcfg, ecfg, seed, world_factory, learner)
    try:
        with open_executor(executor, workers, work, None if bar is None else (lambda item: bar.frame(*item))) as pool:
            _run(pool, todo(), budget_left, lambda r: _finish(r, writer, account, bar, summary))
    finally:
        if bar is not None:
            bar.close()
        writer.close()
    summary.seconds = time.perf_counter() - t0
    return summary


def _run(pool: Executor, indices: Iterator[int], budget_left: Callable[[int, float], bool],
         finish: Callable[[EpisodeResult | ShippedEpisode], int]) -> None:
    """At most one episode per worker in flight, and none started once the episodes in flight (at the mean
    size of those kept so far) would fill the frame budget. Any exception (a worker's, or Ctrl-C) stops the
    workers at once: their episodes in progress are lost, committed ones are kept."""
    kept: list[int] = []
    exhausted = False
    while True:
        mean = float(np.mean(kept)) if kept else 0.0
        while not exhausted and len(pool) < pool.workers and budget_left(len(pool), mean):
            i = next(indices, None)
            if i is None:
                exhausted = True
                break
            pool.submit(i, i)
        if not len(pool):
            return
        for _, value in pool.results():
            n = finish(value)
            if n:
                kept.append(n)


def _finish(value: EpisodeResult | ShippedEpisode, writer: DatasetWriter, account: Callable[[EpisodeResult], None],
            bar: _Progress | None, summary: CollectSummary) -> int:
    """A finished episode: a shipped file is stored (atomically, then listed), then counted. Returns its frames."""
    if isinstance(value, ShippedEpisode):
        if value.entry is not None:
            writer.add_episode_file(value.entry, value.data)
        value = value.result
    account(value)
    if bar is not None:
        bar.episode(value, summary)
    return value.frames_kept


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
