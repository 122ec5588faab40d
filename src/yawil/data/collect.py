"""Data collection: the expert drives random routes, the world renders, the writer stores one file per episode.

The paper's recipe (Sec. IV): the expert drives, a steering perturbation is applied 10% of the time so the
data shows recoveries, and the label is always the expert's own control, never the perturbed one.

Determinism: episode `index` of a run with `seed` has the id `seed * EPISODE_STRIDE + index`, and everything
about it (traffic counts, weather, world seed, noise bursts, frame thinning) derives from
`numpy.random.default_rng([seed, index])`, so an episode's frames depend only on (seed, index), never on
the number of workers or on which episodes were already done. A second run of the same command resumes:
episodes already in the manifest are skipped, never duplicated. Rules and options: docs/expert.md.
"""

from __future__ import annotations

import math
import os
import queue
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from yawil.data.manifest import read_manifest
from yawil.data.schema import DRIVERS, LEAD_RANGE, LIGHT_RANGE, SPEED_REASONS, FrameRecord
from yawil.data.writer import DatasetWriter, EpisodeWriter
from yawil.expert import Expert, ExpertConfig, ExpertState
from yawil.guidance import GuidanceConfig, compute_guidance
from yawil.sim.route_geometry import RouteGeometry
from yawil.sim.types import DT, Control, EventKind, Observation, RoadOption, Route, Scenario, World
from yawil.sim.weather import get_weather

EPISODE_STRIDE = 100_000  # episode id = seed * EPISODE_STRIDE + index
COLLISION_POLICIES: tuple[str, ...] = ("trim", "keep", "discard")


@dataclass(frozen=True)
class CollectConfig:
    """How episodes are made and which frames are kept. Stored in the dataset's manifest (resume checks it)."""

    town: str = "town01"
    weathers: tuple[str, ...] = ("ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset")
    vehicles: tuple[int, int] = (10, 30)  # drawn uniformly per episode, inclusive
    pedestrians: tuple[int, int] = (5, 20)
    min_route_length: float = 200.0  # metres
    camera: bool = True
    # steering noise (the paper: 10% of the data)
    noise_fraction: float = 0.10  # expected fraction of frames with a perturbation
    noise_amplitude: float = 0.5  # a burst adds a constant offset drawn from U[-a, a] to the steer
    noise_duration: tuple[float, float] = (0.5, 1.0)  # seconds, uniform per burst
    # frame thinning
    blocked_speed: float = 0.1  # m/s: below this the ego is "blocked"
    blocked_after: float = 2.0  # s blocked before frames are thinned
    blocked_keep_every: int = 10  # then keep every Nth frame
    straight_keep: float = 0.5  # fraction of frames kept on long straights
    straight_window: float = 20.0  # m: "long straight" = LANEFOLLOW, no curvature within this distance around
    straight_curvature: float = 0.01  # 1/m: below this the route counts as straight
    lane_follow_turn_curvature: float = 0.02  # 1/m (radius < 50 m): a lane-follow curve
    lane_follow_turn_ahead: float = 10.0  # m ahead of the ego examined for lane_follow_turn
    # episode end
    on_collision: str = "trim"  # trim: keep frames up to trim_seconds before it; keep: all; discard: drop episode
    trim_seconds: float = 2.0
    stuck_seconds: float = 90.0  # end the episode (outcome "stuck") after this long without moving 1 m
    max_episode_frames: int = 0  # > 0: end an episode after this many steps (outcome "frame_limit"), for demos

    def __post_init__(self) -> None:
        if not self.weathers:
            raise ValueError("CollectConfig.weathers must name at least one weather")
        for w in self.weathers:
            get_weather(w)
        for name in ("vehicles", "pedestrians"):
            lo, hi = getattr(self, name)
            if not (isinstance(lo, int) and isinstance(hi, int)) or lo < 0 or hi < lo:
                raise ValueError(f"CollectConfig.{name} must be (lo, hi) integers with 0 <= lo <= hi, got {(lo, hi)!r}")
        if not 0.0 <= self.noise_fraction < 1.0:
            raise ValueError(f"CollectConfig.noise_fraction must be in [0, 1), got {self.noise_fraction!r}")
        if not 0.0 <= self.noise_amplitude <= 1.0:
            raise ValueError(f"CollectConfig.noise_amplitude must be in [0, 1], got {self.noise_amplitude!r}")
        lo, hi = self.noise_duration
        if not 0.0 < lo <= hi:
            raise ValueError(f"CollectConfig.noise_duration must be (lo, hi) seconds with 0 < lo <= hi, got {(lo, hi)!r}")
        if not 0.0 < self.straight_keep <= 1.0:
            raise ValueError(f"CollectConfig.straight_keep must be in (0, 1], got {self.straight_keep!r}")
        if self.max_episode_frames < 0:
            raise ValueError(f"CollectConfig.max_episode_frames must be >= 0 (0: no limit), got {self.max_episode_frames!r}")
        if self.blocked_keep_every < 1:
            raise ValueError(f"CollectConfig.blocked_keep_every must be >= 1, got {self.blocked_keep_every!r}")
        if self.on_collision not in COLLISION_POLICIES:
            raise ValueError(f"CollectConfig.on_collision must be one of {COLLISION_POLICIES}, got {self.on_collision!r}")
        for name in ("min_route_length", "blocked_speed", "blocked_after", "straight_window", "straight_curvature",
                     "lane_follow_turn_curvature", "lane_follow_turn_ahead", "trim_seconds", "stuck_seconds"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"CollectConfig.{name} must be a finite number >= 0, got {v!r}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


@dataclass(frozen=True)
class OnPolicy:
    """How a learner shares the wheel with the expert in a DAgger round (docs/training.md, "DAgger").

    The expert labels every frame whoever drives. It drives a segment itself with probability `beta` (one
    draw per `segment_seconds`, or per episode when 0), and takes the wheel from the learner for
    `takeover_seconds` when the learner strays `takeover_lateral` m from the route, would need more than
    `takeover_decel` m/s^2 to stop for the stop point the expert brakes for, or stands `takeover_stall` s
    while the expert would drive: these recovery frames are what behaviour cloning never shows.
    """

    round: int = 1
    beta: float = 0.0
    segment_seconds: float = 0.0
    takeover_lateral: float = 2.0
    takeover_decel: float = 4.0
    takeover_stall: float = 4.0
    takeover_seconds: float = 3.0

    def __post_init__(self) -> None:
        if isinstance(self.round, bool) or not isinstance(self.round, int) or not 1 <= self.round <= 32767:
            raise ValueError(f"OnPolicy.round must be an int in [1, 32767], got {self.round!r}")
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"OnPolicy.beta must be in [0, 1], got {self.beta!r}")
        for name in ("segment_seconds", "takeover_lateral", "takeover_decel", "takeover_stall", "takeover_seconds"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"OnPolicy.{name} must be a finite number >= 0, got {v!r}")


class Driver(Protocol):
    """The duck type of a learner: what `yawil.agent.Agent` offers."""

    def reset(self) -> None: ...

    def act(self, obs: Observation) -> Control: ...


def expert_labels(state: ExpertState) -> dict[str, Any]:
    """The schema-2 privileged labels of one frame from the expert's decision (docs/dataset.md)."""
    lead = min((h for h in state.hazards if h.reason == "vehicle"), key=lambda h: h.distance, default=None)
    light = any(h.reason in ("red_light", "yellow_light") and h.distance < LIGHT_RANGE for h in state.hazards)
    near = lead is not None and lead.distance < LEAD_RANGE
    return {
        "target_speed": max(float(state.target_speed), 0.0),
        "speed_reason": SPEED_REASONS.index(state.reason) if state.reason in SPEED_REASONS else -1,
        "lead_distance": max(float(lead.distance), 0.0) if near and lead is not None else LEAD_RANGE,
        "lead_speed": max(float(lead.speed), 0.0) if near and lead is not None else 0.0,
        "light_ahead": int(light),
    }


class _Wheel:
    """Who drives each frame of an on-policy episode: the schedule (beta) and the takeovers."""

    def __init__(self, onpolicy: OnPolicy, rng: np.random.Generator, dt: float) -> None:
        self.p, self.rng, self.dt = onpolicy, rng, dt
        self.segment = max(1, round(onpolicy.segment_seconds / dt)) if onpolicy.segment_seconds > 0 else 0
        self.expert_segment = False
        self.takeover_left = 0
        self.stall = 0
        self.takeovers = 0

    def driver(self, frame: int, state: ExpertState, speed: float) -> int:
        """DRIVERS index for this frame (one draw per segment start, whatever happens: seeded alignment)."""
        p = self.p
        if frame == 0 or (self.segment and frame % self.segment == 0):
            self.expert_segment = bool(self.rng.random() < p.beta)
        self.stall = self.stall + 1 if (speed < 0.1 and state.target_speed > 1.0) else 0
        if self.takeover_left == 0 and not self.expert_segment and self._danger(state, speed):
            self.takeover_left = max(1, round(p.takeover_seconds / self.dt))
            self.takeovers += 1
        if self.takeover_left > 0:
            self.takeover_left -= 1
            self.stall = 0
            return DRIVERS.index("takeover")
        return DRIVERS.index("expert") if self.expert_segment else DRIVERS.index("learner")

    def _danger(self, state: ExpertState, speed: float) -> bool:
        p = self.p
        if abs(state.lateral_error) > p.takeover_lateral or self.stall * self.dt > p.takeover_stall:
            return True
        h = state.hazard
        if h is None or speed <= h.speed:
            return False
        need = (speed * speed - h.speed * h.speed) / (2.0 * h.distance) if h.distance > 0.05 else math.inf
        return need > p.takeover_decel


@dataclass(frozen=True)
class EpisodePlan:
    """Everything that defines one episode, derived from (seed, index) alone."""

    episode_id: int
    index: int
    seed: int
    world_seed: int
    weather: str
    vehicles: int
    pedestrians: int


def episode_id(seed: int, index: int) -> int:
    if not 0 <= index < EPISODE_STRIDE:
        raise ValueError(f"episode index must be in [0, {EPISODE_STRIDE}), got {index}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    return seed * EPISODE_STRIDE + index


def plan_episode(cfg: CollectConfig, seed: int, index: int, min_world_seed: int = 0) -> EpisodePlan:
    """Weathers cycle over indices (balanced, as the paper's data); traffic and world seed are drawn.

    `min_world_seed` keeps the world seeds above a range (DAgger keeps clear of the benchmark's).
    """
    rng = np.random.default_rng([seed, index, 0])
    return EpisodePlan(
        episode_id=episode_id(seed, index),
        index=index,
        seed=seed,
        world_seed=int(rng.integers(min_world_seed, 2**31 - 1)),
        weather=cfg.weathers[index % len(cfg.weathers)],
        vehicles=int(rng.integers(cfg.vehicles[0], cfg.vehicles[1] + 1)),
        pedestrians=int(rng.integers(cfg.pedestrians[0], cfg.pedestrians[1] + 1)),
    )


class SteeringNoise:
    """Bursts of a constant steering offset, started at random so that `fraction` of frames are perturbed."""

    def __init__(self, fraction: float, amplitude: float, duration_s: tuple[float, float], rng: np.random.Generator,
                 dt: float = 0.1) -> None:
        self.rng = rng
        self.amplitude = amplitude
        self.frames = (max(1, round(duration_s[0] / dt)), max(1, round(duration_s[1] / dt)))
        mean = 0.5 * (self.frames[0] + self.frames[1])
        # a burst starts with probability p per quiet frame: fraction = p*mean / (1 + p*mean)
        self.p_start = fraction / (mean * (1.0 - fraction)) if fraction > 0 else 0.0
        self.left = 0
        self.offset = 0.0

    def __call__(self) -> float:
        """The offset for this frame (0.0 outside a burst). Always draws the same numbers per frame."""
        start, amp, length = self.rng.random(), self.rng.uniform(-1.0, 1.0), self.rng.integers(self.frames[0], self.frames[1] + 1)
        if self.left == 0 and start < self.p_start:
            self.left, self.offset = int(length), float(amp) * self.amplitude
        if self.left > 0:
            self.left -= 1
            return self.offset
        return 0.0


@dataclass
class EpisodeResult:
    episode_id: int
    index: int
    outcome: str  # goal | timeout | collision | stuck | discarded(collision) | skipped
    frames_kept: int = 0
    frames_run: int = 0
    noise_frames: int = 0
    seconds: float = 0.0
    collisions: list[dict[str, Any]] = field(default_factory=list)
    drivers: dict[str, int] = field(default_factory=dict)  # frames run per DRIVERS name
    takeovers: int = 0


class _Keeper:
    """Decides which frames are stored: thins blocked stretches and long straights (seeded)."""

    def __init__(self, cfg: CollectConfig, route_curv: np.ndarray, route_s: np.ndarray, options: np.ndarray,
                 rng: np.random.Generator) -> None:
        self.cfg, self.curv, self.s, self.options, self.rng = cfg, route_curv, route_s, options, rng
        self.blocked_frames = 0

    def window_max_curvature(self, s0: float, s1: float) -> float:
        lo = max(int(np.searchsorted(self.s, s0)) - 1, 0)
        hi = max(int(np.searchsorted(self.s, s1)), lo + 1)
        return float(self.curv[lo:hi].max()) if hi > lo else 0.0

    def lanefollow_between(self, s0: float, s1: float) -> bool:
        lo = max(int(np.searchsorted(self.s, s0)) - 1, 0)
        hi = max(int(np.searchsorted(self.s, s1)) + 1, lo + 1)
        return bool(np.all(self.options[lo:hi] == int(RoadOption.LANEFOLLOW)))

    def lane_follow_turn(self, s: float, command: int) -> bool:
        cfg = self.cfg
        return (command == int(RoadOption.LANEFOLLOW) and self.lanefollow_between(s, s + cfg.lane_follow_turn_ahead)
                and self.window_max_curvature(s - 2.0, s + cfg.lane_follow_turn_ahead) > cfg.lane_follow_turn_curvature)

    def keep(self, speed: float, s: float, command: int, noisy: bool, steer: float) -> bool:
        cfg = self.cfg
        u = self.rng.random()  # one draw per frame, whatever the branch: the stream stays aligned
        if speed < cfg.blocked_speed:
            self.blocked_frames += 1
            if self.blocked_frames * 0.1 > cfg.blocked_after:
                return self.blocked_frames % cfg.blocked_keep_every == 0
            return True
        self.blocked_frames = 0
        if noisy or abs(steer) > 0.05 or cfg.straight_keep >= 1.0 or command != int(RoadOption.LANEFOLLOW):
            return True
        w = cfg.straight_window
        straight = self.lanefollow_between(s - w, s + w) and self.window_max_curvature(s - w, s + w) < cfg.straight_curvature
        return (not straight) or u < cfg.straight_keep


def _route_curvature(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(arc length of each waypoint, |curvature| at each waypoint over a +-2.5 m window)."""
    geo = RouteGeometry(xy)
    return geo.s, geo.waypoint_curvature(2.5)


def run_episode(
    world: World,
    plan: EpisodePlan,
    cfg: CollectConfig,
    writer: DatasetWriter | None,
    guidance: GuidanceConfig = GuidanceConfig(),
    expert_config: ExpertConfig | None = None,
    on_frame: Callable[[int], None] | None = None,
    learner: Driver | None = None,
    onpolicy: OnPolicy | None = None,
    reject_route: Callable[[Route], bool] | None = None,
) -> EpisodeResult:
    """Drive one episode with the expert (or a `learner` sharing the wheel by `onpolicy`) and store it (when
    `writer` is given), every frame labelled with the expert's control. Interrupts discard it.

    `on_frame(n)` is told of frames kept as they are kept (for a progress bar; a trimmed collision takes
    some back, which the caller corrects from the result). `reject_route(route)` True draws the world again
    with the next seed (DAgger keeps off the benchmark's routes).
    """
    if (learner is None) != (onpolicy is None):
        raise ValueError("run_episode: give both learner and onpolicy, or neither")
    if writer is not None and not cfg.camera:
        raise ValueError("CollectConfig.camera is False but a dataset needs images: enable the camera")
    t0 = time.perf_counter()
    rng = np.random.default_rng([plan.seed, plan.index, 1])
    noise = SteeringNoise(cfg.noise_fraction, cfg.noise_amplitude, cfg.noise_duration, rng)
    keep_rng = np.random.default_rng([plan.seed, plan.index, 2])
    scenario = Scenario(town=cfg.town, weather=plan.weather, vehicles=plan.vehicles, pedestrians=plan.pedestrians,
                        camera=cfg.camera, min_route_length=cfg.min_route_length)
    world_seed = plan.world_seed
    obs = world.reset(scenario, world_seed)
    tries = 0
    while reject_route is not None and reject_route(obs.route):
        tries += 1
        if tries > 100:
            raise ValueError(f"episode {plan.episode_id}: 100 drawn routes in a row were rejected (from world seed "
                             f"{plan.world_seed}); the town has no route left to drive")
        world_seed += 1
        obs = world.reset(scenario, world_seed)
    route = obs.route
    s_route, curv = _route_curvature(np.asarray(route.xy, dtype=np.float64))
    keeper = _Keeper(cfg, curv, s_route, np.asarray(route.options), keep_rng)
    expert = Expert(expert_config)
    result = EpisodeResult(plan.episode_id, plan.index, "timeout")
    meta = {"index": plan.index, "world_seed": world_seed, "vehicles": plan.vehicles,
            "pedestrians": plan.pedestrians, "route_length": float(route.length), "min_route_length": cfg.min_route_length}
    wheel = None
    if learner is not None and onpolicy is not None:
        learner.reset()
        wheel = _Wheel(onpolicy, np.random.default_rng([plan.seed, plan.index, 3]), DT)
        meta["round"] = onpolicy.round
    round_index = onpolicy.round if onpolicy is not None else 0
    ep: EpisodeWriter | None = None
    if writer is not None:
        ep = writer.begin_episode(plan.episode_id, cfg.town, plan.weather, plan.seed, meta)
    delay: deque[FrameRecord] = deque()  # the last trim_seconds of kept frames, held back in "trim" mode
    delay_frames = int(round(cfg.trim_seconds / 0.1)) if cfg.on_collision == "trim" else 0
    hint: int | None = None
    last_pos, last_move_frame = (obs.pose.x, obs.pose.y), 0
    try:
        while True:
            control = expert.act(obs)
            offset = noise()
            applied = control
            driver = 0
            if wheel is not None and learner is not None:
                own = learner.act(obs)  # every frame, so the learner's memory (guidance hint) stays current
                driver = wheel.driver(result.frames_run, expert.state, max(float(obs.speed), 0.0))
                if driver == DRIVERS.index("learner"):
                    applied, offset = own, 0.0
            name = DRIVERS[driver]
            result.drivers[name] = result.drivers.get(name, 0) + 1
            if offset != 0.0:
                applied = replace(control, steer=float(np.clip(control.steer + offset, -1.0, 1.0)))
                result.noise_frames += 1
            g, hint = compute_guidance(route.xy, route.lane_yaw, (obs.pose.x, obs.pose.y), obs.pose.yaw, obs.bounds,
                                       guidance, hint_index=hint)
            s_here = float(s_route[min(int(obs.route_index), len(s_route) - 1)])
            command = int(RoadOption.LANEFOLLOW) if int(obs.command) == int(RoadOption.VOID) else int(obs.command)
            if keeper.keep(obs.speed, s_here, command, offset != 0.0 or driver != 0, control.steer) and obs.image is not None:
                rec = FrameRecord(
                    image=obs.image, steer=control.steer, throttle=control.throttle, brake=control.brake,
                    speed=max(float(obs.speed), 0.0), command=command, guidance_yaw=g.yaw, guidance_xy=g.xy,
                    guidance_sim_yaw=g.sim_yaw, pose=(obs.pose.x, obs.pose.y, obs.pose.yaw), frame=int(obs.frame),
                    noise=offset != 0.0, lane_follow_turn=keeper.lane_follow_turn(s_here, command),
                    driver=driver, round=round_index, **expert_labels(expert.state),
                )
                delay.append(rec)
                result.frames_kept += 1
                if on_frame is not None:
                    on_frame(1)
                while len(delay) > delay_frames:
                    first = delay.popleft()
                    if ep is not None:
                        ep.append(first)
            obs = world.step(applied)
            result.frames_run += 1
            collisions = [e for e in obs.events if e.kind is EventKind.COLLISION]
            if collisions:
                result.collisions = [{"other_type": e.other_type, "other_id": e.other_id, "time": e.time,
                                      "speed": float(obs.speed)} for e in collisions]
                result.outcome = "collision"
                break
            if obs.done:
                goal = any(e.kind is EventKind.GOAL_REACHED for e in obs.events)
                result.outcome = "goal" if goal else "timeout"
                break
            if math.hypot(obs.pose.x - last_pos[0], obs.pose.y - last_pos[1]) > 1.0:
                last_pos, last_move_frame = (obs.pose.x, obs.pose.y), result.frames_run
            elif (result.frames_run - last_move_frame) * 0.1 > cfg.stuck_seconds:
                result.outcome = "stuck"
                break
            if cfg.max_episode_frames and result.frames_run >= cfg.max_episode_frames:
                result.outcome = "frame_limit"
                break
        if result.outcome == "collision" and cfg.on_collision != "keep":
            result.frames_kept -= len(delay)  # trim: the last seconds before the collision are not stored
            delay.clear()
            if cfg.on_collision == "discard":
                result.outcome = "discarded(collision)"
        if ep is not None:
            for rec in delay:
                ep.append(rec)
            if result.outcome.startswith("discarded") or len(ep) == 0:
                ep.discard()
                result.outcome = result.outcome if result.outcome.startswith("discarded") else f"discarded({result.outcome})"
                result.frames_kept = 0
            else:
                ep.commit(result.outcome)
    except BaseException:
        if ep is not None:
            ep.discard()
        raise
    result.seconds = time.perf_counter() - t0
    result.takeovers = wheel.takeovers if wheel is not None else 0
    return result


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
