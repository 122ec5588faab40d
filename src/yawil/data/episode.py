"""One collection episode: the expert drives (or a learner shares the wheel), every frame is labelled with the
expert's control, and the kept frames go to the dataset writer.

The paper's recipe (Sec. IV): the expert drives, a steering perturbation is applied 10% of the time so the
data shows recoveries, and the label is always the expert's own control, never the perturbed one.

Determinism: episode `index` of a run with `seed` has the id `seed * EPISODE_STRIDE + index`, and everything
about it (traffic counts, weather, world seed, noise bursts, frame thinning) derives from
`numpy.random.default_rng([seed, index])`, so an episode's frames depend only on (seed, index), never on
the number of workers or on which episodes were already done. Rules and options: docs/expert.md.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from yawil.data.collect_config import CollectConfig, OnPolicy
from yawil.data.schema import DRIVERS, LEAD_RANGE, LIGHT_RANGE, SPEED_REASONS, FrameRecord
from yawil.data.writer import DatasetWriter, EpisodeWriter
from yawil.expert import Expert, ExpertConfig, ExpertState
from yawil.guidance import GuidanceConfig, compute_guidance
from yawil.sim.route_geometry import RouteGeometry
from yawil.sim.types import DT, Control, EventKind, Observation, RoadOption, Route, Scenario, World

EPISODE_STRIDE = 100_000  # episode id = seed * EPISODE_STRIDE + index


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
