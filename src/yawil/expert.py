"""The privileged expert driver: the teacher of every learned agent and the upper bound of the benchmark.

It reads what a learned agent never may (the route, the light states, the other agents' poses and speeds)
and drives with two textbook controllers:

- lateral: pure pursuit on the route, the look-ahead growing with speed;
- longitudinal: a PID on speed towards a target speed, the least of the cruise speed (20 km/h), the
  curvature limit of the route ahead, and a comfortable braking profile to every stop point ahead:
  red and yellow lights at their stop line, vehicles and pedestrians in (or about to enter) the corridor
  the ego will sweep, crossing traffic in junctions, and the goal.

Rules and parameters: docs/expert.md. Deterministic: no randomness at all. Knows nothing of torch; it only
needs the backend-neutral types of `yawil.sim.types`, so it drives any backend.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from yawil.guidance import wrap_to_pi
from yawil.sim.types import DT, AgentState, Control, LightState, Observation, RoadOption, Route, wrap_angle


@dataclass(frozen=True)
class ExpertConfig:
    """Every tunable of the expert, with the reason for its default in docs/expert.md."""

    # vehicle (matches the embedded backend's ego; the pose is the centre of the car)
    wheelbase: float = 2.9
    max_steer_deg: float = 35.0  # wheel angle at |steer| = 1
    length: float = 4.6
    width: float = 1.9
    # lateral: pure pursuit
    lookahead_min: float = 2.5
    lookahead_gain: float = 0.4  # seconds: look-ahead = min + gain * speed, from the rear axle
    lookahead_max: float = 10.0
    # speeds
    cruise_speed: float = 20.0 / 3.6  # m/s
    max_lateral_accel: float = 1.6  # m/s^2, limits the speed in curves
    min_curve_speed: float = 2.5  # m/s, never plan slower than this for curvature alone
    comfort_decel: float = 2.5  # m/s^2, braking profile towards stop points
    max_decel: float = 8.0  # m/s^2, what full braking achieves (the embedded ego's brake)
    plan_accel: float = 1.5  # m/s^2, assumed when predicting when the ego reaches a point
    # lights
    stop_line_margin: float = 1.0  # m between the front bumper and the stop line when stopped
    yellow_decel: float = 3.0  # stop for yellow only if this deceleration suffices
    # hazards
    corridor_margin: float = 0.45  # m added to the ego's half width on each side
    pedestrian_margin: float = 0.2  # extra lateral margin for pedestrians (kerb walkers stay outside)
    stop_gap: float = 3.0  # m kept between the front bumper and a pedestrian or crossing point when stopped
    vehicle_gap: float = 2.0  # m kept behind a standing vehicle (a queue on a 20 m block must fit a car)
    time_gap: float = 1.0  # s of headway behind a moving lead vehicle
    vehicle_horizon: float = 6.0  # s of constant-velocity prediction of vehicles
    pedestrian_horizon: float = 4.0  # s for pedestrians
    prediction_step: float = 0.4  # s between predicted positions
    time_buffer_before: float = 1.0  # s: the agent reaching a point this long before the ego still conflicts
    time_buffer_after: float = 1.5  # s: and this long after the ego left it
    head_on_deg: float = 160.0  # predicted crossings at a larger angle are oncoming traffic on a curve
    traffic_yellow_decel: float = 3.0  # other vehicles stop for a yellow light if this deceleration suffices
    junction_watch: float = 4.0  # m around the junction path where a crossing vehicle blocks entry
    crosswalk_after_exit: float = 4.0  # m after a junction's exit kept clear (its crosswalk)
    crosswalk_watch: float = 2.5  # m beyond the corridor where a pedestrian at a crosswalk may step in
    pedestrian_max_speed: float = 1.6  # m/s a standing pedestrian is assumed able to walk at
    preview_min: float = 30.0  # m of route examined ahead (at least)
    restart_hold: float = 1.0  # s an agent outside the lane must stay clear before the ego starts from a stop
    restart_hold_speed: float = 0.5  # m/s below which the ego counts as standing for that rule
    # goal
    goal_overshoot: float = 0.5  # m past the route's end where the centre is planned to stop
    # PID on speed (throttle positive, brake negative)
    kp: float = 0.6
    ki: float = 0.15
    kd: float = 0.0
    integral_limit: float = 2.0
    max_throttle: float = 0.75
    brake_gain: float = 0.6  # brake per unit of negative PID output
    brake_deadband: float = 0.1
    hold_brake: float = 1.0  # brake while stopped at a stop point

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not isinstance(value, (int, float)) or not math.isfinite(float(value)):
                raise ValueError(f"ExpertConfig.{name} must be a finite number, got {value!r}")
            if value < 0:
                raise ValueError(f"ExpertConfig.{name} must be >= 0, got {value!r}")
        for name in ("wheelbase", "max_steer_deg", "cruise_speed", "comfort_decel", "max_decel", "plan_accel",
                     "prediction_step", "lookahead_min"):
            if getattr(self, name) <= 0:
                raise ValueError(f"ExpertConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if self.lookahead_max < self.lookahead_min:
            raise ValueError(f"ExpertConfig.lookahead_max ({self.lookahead_max}) must be >= lookahead_min ({self.lookahead_min})")

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_items(cls, items: Sequence[str], option: str = "--expert-arg") -> ExpertConfig:
        """`["comfort_decel=1.5", ...]` (command-line KEY=VALUE items) -> a config; the rest keep their defaults."""
        known = {f.name for f in fields(cls)}
        values: dict[str, float] = {}
        for item in items:
            key, sep, text = item.partition("=")
            if not sep or not key:
                raise ValueError(f"{option}: expected KEY=VALUE, got {item!r}")
            if key not in known:
                raise ValueError(f"{option} {item!r}: unknown expert setting {key!r}; known: {', '.join(sorted(known))}")
            try:
                values[key] = float(text)
            except ValueError:
                raise ValueError(f"{option} {item!r}: expected a number after '='") from None
        return cls(**values)

    def changes(self) -> dict[str, float]:
        """The settings that differ from the defaults (what a record or a run's settings need to say)."""
        base = ExpertConfig().to_dict()
        return {k: v for k, v in self.to_dict().items() if v != base[k]}


@dataclass(frozen=True)
class Hazard:
    """A reason to stop: the ego's centre must stop `distance` metres ahead (negative: already past it)."""

    distance: float
    reason: str  # "red_light" | "yellow_light" | "vehicle" | "pedestrian" | "junction" | "goal"
    speed: float = 0.0  # speed of the hazard along the route (a lead vehicle may be followed, not stopped for)
    agent_id: int | None = None


@dataclass
class ExpertState:
    """What the expert decided at the last step, for debugging, tests and the benchmark's diagnostics."""

    target_speed: float = 0.0
    reason: str = "cruise"
    hazard: Hazard | None = None
    lateral_error: float = 0.0
    light_decisions: dict[int, str] = field(default_factory=dict)
    hazards: tuple[Hazard, ...] = ()  # every stop point considered this step (labels of lead vehicle and lights)


class _RouteCache:
    """Arc lengths and curvature of one route, computed once per episode."""

    TAIL = 12  # metres of straight road assumed past the goal

    def __init__(self, route: Route) -> None:
        xy = np.asarray(route.xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 2 or not np.all(np.isfinite(xy)):
            raise ValueError(f"route.xy must be a finite (N, 2) array with N >= 2, got shape {xy.shape}")
        self.route = route
        # a straight tail past the goal, so that what stands just beyond it is on the corridors too (the ego's
        # front overshoots the goal: a queue standing past it was invisible, and the ego ran into its tail)
        end_yaw = float(route.lane_yaw[-1])
        tail = xy[-1] + np.arange(1.0, self.TAIL + 0.5)[:, None] * np.array([math.cos(end_yaw), math.sin(end_yaw)])
        self.xy = xy = np.vstack([xy, tail])
        seg = np.diff(xy, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        self.seg_len = np.maximum(seg_len, 1e-9)
        self.s = np.concatenate([[0.0], np.cumsum(seg_len)])
        self.heading = np.arctan2(seg[:, 1], seg[:, 0])  # (N-1+TAIL,)
        self.length = float(self.s[-1 - len(tail)])  # the route's, without the tail
        self.curvature = self._curvature(window=2.5)
        self.options = np.asarray(route.options, dtype=np.int64)
        self.junctions = self._junction_spans()

    def _curvature(self, window: float) -> np.ndarray:
        """|dheading/ds| at each segment, over +-window metres (smooths the 1 m sampling)."""
        mid = 0.5 * (self.s[:-1] + self.s[1:])
        lo = np.searchsorted(mid, mid - window, side="left")
        hi = np.minimum(np.searchsorted(mid, mid + window, side="right") - 1, len(mid) - 1)
        unwrapped = np.unwrap(self.heading)
        dh = np.abs(unwrapped[hi] - unwrapped[lo])
        ds = np.maximum(mid[hi] - mid[lo], 1e-6)
        k = np.where(hi > lo, dh / ds, 0.0)
        return np.asarray(k, dtype=np.float64)

    def _junction_spans(self) -> list[tuple[float, float]]:
        """(stop line s, exit s) of each signalised junction: the exit is where LANEFOLLOW resumes after the
        junction's option run (which starts a few metres before the junction, at or after the stop line)."""
        spans = []
        n = len(self.options)
        lf = int(RoadOption.LANEFOLLOW)
        for stop_idx, _light in self.route.lights:
            i = min(max(int(stop_idx), 0), n - 1)
            j = i
            while j < n - 1 and self.options[j] == lf and self.s[j] - self.s[i] < 10.0:
                j += 1
            while j < n - 1 and self.options[j] != lf:
                j += 1
            exit_s = float(self.s[j]) if j > i and self.options[j - 1] != lf else float(self.s[i]) + 20.0
            spans.append((float(self.s[i]), exit_s))
        return spans

    def in_junction(self, s: float, margin: float = 5.0) -> bool:
        return any(lo - margin <= s <= hi + margin for lo, hi in self.junctions)

    def project(self, p: np.ndarray, hint: int, back: int = 5, ahead: int = 40) -> tuple[int, float, float]:
        """(segment, arc length, signed lateral offset, left positive) of p near the hinted waypoint."""
        nseg = len(self.heading)
        lo = min(max(hint - back, 0), nseg - 1)
        hi = min(max(hint + ahead, lo + 1), nseg)
        a = self.xy[lo:hi]
        d = self.xy[lo + 1 : hi + 1] - a
        t = np.einsum("ij,ij->i", p - a, d) / (self.seg_len[lo:hi] ** 2)
        lower = np.zeros_like(t)
        upper = np.ones_like(t)
        if lo == 0:
            lower[0] = -np.inf  # before the route's start and past its end: extrapolate the end segments
        if hi == nseg:
            upper[-1] = np.inf
        t = np.clip(t, lower, upper)
        foot = a + t[:, None] * d
        dist = np.linalg.norm(p - foot, axis=1)
        k = int(np.argmin(dist))
        i = lo + k
        s = float(self.s[i] + t[k] * self.seg_len[i])
        cross = d[k, 0] * (p[1] - a[k, 1]) - d[k, 1] * (p[0] - a[k, 0])
        return i, s, float(math.copysign(dist[k], cross))

    def point_at(self, s: float) -> np.ndarray:
        """The route point at arc length s (the tail past the goal included); beyond the tail, extrapolated."""
        end = float(self.s[-1])
        if s >= end:
            return np.asarray(self.xy[-1] + (s - end) * np.array([math.cos(self.heading[-1]), math.sin(self.heading[-1])]))
        s = max(s, 0.0)
        i = min(int(np.searchsorted(self.s, s, side="right")) - 1, len(self.heading) - 1)
        t = (s - self.s[i]) / self.seg_len[i]
        return np.asarray(self.xy[i] + t * (self.xy[i + 1] - self.xy[i]))

    def window(self, s0: float, s1: float) -> tuple[int, int]:
        """Segment index range [lo, hi) covering arc lengths s0..s1."""
        lo = max(int(np.searchsorted(self.s, s0, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(self.s, s1, side="left")) + 1, len(self.heading))
        return lo, max(hi, lo + 1)


class _Corridor:
    """The route between two arc lengths, onto which agents' (predicted) positions are projected."""

    def __init__(self, rc: _RouteCache, s0: float, s1: float, stride: int = 1) -> None:
        lo, hi = rc.window(s0, s1)
        if stride == 1:
            self.a, self.d = rc.xy[lo:hi], rc.xy[lo + 1 : hi + 1] - rc.xy[lo:hi]
            self.seg_len, self.s, self.h = rc.seg_len[lo:hi], rc.s[lo:hi], rc.heading[lo:hi]
        else:
            idx = np.arange(lo, hi + 1, stride)  # waypoints kept (every `stride`-th, plus the last)
            if idx[-1] != hi:
                idx = np.append(idx, hi)
            pts = rc.xy[idx]
            self.a, self.d = pts[:-1], pts[1:] - pts[:-1]
            self.seg_len = np.maximum(np.hypot(self.d[:, 0], self.d[:, 1]), 1e-9)
            self.s, self.h = rc.s[idx[:-1]], np.arctan2(self.d[:, 1], self.d[:, 0])
        self.len2 = self.seg_len**2

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(arc length, distance, path heading) of the nearest route point to each of p (..., 2)."""
        rel = p[..., None, :] - self.a
        t = np.clip(np.einsum("...mj,mj->...m", rel, self.d) / self.len2, 0.0, 1.0)
        gap = rel - t[..., None] * self.d
        dist2 = np.einsum("...j,...j->...", gap, gap)
        k = np.argmin(dist2, axis=-1)
        d = np.sqrt(np.take_along_axis(dist2, k[..., None], axis=-1)[..., 0])
        tk = np.take_along_axis(t, k[..., None], axis=-1)[..., 0]
        return self.s[k] + tk * self.seg_len[k], d, self.h[k]


def _extents(rel: np.ndarray, length: np.ndarray, width: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half extents of boxes along and across a direction at angle `rel` to their heading."""
    c, s = np.abs(np.cos(rel)), np.abs(np.sin(rel))
    return 0.5 * (length * c + width * s), 0.5 * (length * s + width * c)


class Expert:
    """Privileged driver with the agent's duck type: `reset()`, `act(obs) -> Control`."""

    def __init__(self, config: ExpertConfig | None = None) -> None:
        self.config = config or ExpertConfig()
        self.state = ExpertState()
        self._cache: _RouteCache | None = None
        self._integral = 0.0
        self._prev_error: float | None = None
        self._light_decisions: dict[int, str] = {}
        self._prev_yaw: dict[int, float] = {}  # agents' headings at the previous frame, for their yaw rates
        self._prev_frame: int | None = None
        self._rates: dict[int, float] = {}
        self._hold: tuple[float, str, int | None, float] | None = None  # (stop s, reason, agent, last seen)

    def reset(self) -> None:
        """Forget the episode (route, PID memory, light decisions)."""
        self.state = ExpertState()
        self._cache = None
        self._integral = 0.0
        self._prev_error = None
        self._light_decisions = {}
        self._prev_yaw = {}
        self._prev_frame = None
        self._hold = None

    # ------------------------------------------------------------------------------------------ control
    def act(self, obs: Observation) -> Control:
        if self._cache is None or self._cache.route is not obs.route:
            self._cache = _RouteCache(obs.route)
            self._hold = None
        rc = self._cache
        pos = np.array([obs.pose.x, obs.pose.y], dtype=np.float64)
        seg, s_ego, lateral = rc.project(pos, int(obs.route_index))
        speed = max(float(obs.speed), 0.0)

        steer = self._pure_pursuit(obs, rc, s_ego, speed)

        consecutive = self._prev_frame is not None and obs.frame == self._prev_frame + 1
        self._rates = {a.id: wrap_angle(a.yaw - self._prev_yaw[a.id]) / DT for a in obs.privileged.agents
                       if consecutive and a.id in self._prev_yaw}
        self._prev_yaw = {a.id: a.yaw for a in obs.privileged.agents}
        self._prev_frame = obs.frame
        hazards = self._hazards(obs, rc, s_ego, seg, speed)
        v_target, reason, binding = self._target_speed(rc, s_ego, speed, hazards)
        throttle, brake, forced = self._longitudinal(speed, v_target, binding)
        if forced and binding is not None:
            reason = binding.reason

        self.state = ExpertState(
            target_speed=v_target,
            reason=reason,
            hazard=binding,
            lateral_error=lateral,
            light_decisions=dict(self._light_decisions),
            hazards=tuple(hazards),
        )
        return Control(steer=steer, throttle=throttle, brake=brake).validate()

    def _pure_pursuit(self, obs: Observation, rc: _RouteCache, s_ego: float, speed: float) -> float:
        cfg = self.config
        ld = min(max(cfg.lookahead_min + cfg.lookahead_gain * speed, cfg.lookahead_min), cfg.lookahead_max)
        target = rc.point_at(s_ego - 0.5 * cfg.wheelbase + ld)  # look-ahead measured from the rear axle
        c, s = math.cos(obs.pose.yaw), math.sin(obs.pose.yaw)
        rear = np.array([obs.pose.x - 0.5 * cfg.wheelbase * c, obs.pose.y - 0.5 * cfg.wheelbase * s])
        v = target - rear
        dx, dy = c * v[0] + s * v[1], -s * v[0] + c * v[1]
        dist = max(math.hypot(dx, dy), 1e-3)
        alpha = math.atan2(dy, dx)
        delta = math.atan2(2.0 * cfg.wheelbase * math.sin(alpha), dist)  # > 0: turn left
        return float(np.clip(-delta / math.radians(cfg.max_steer_deg), -1.0, 1.0))

    def _target_speed(
        self, rc: _RouteCache, s_ego: float, speed: float, hazards: list[Hazard]
    ) -> tuple[float, str, Hazard | None]:
        """The least of cruise, curvature and braking-profile speeds, with the reason that binds."""
        cfg = self.config
        best, reason, binding = cfg.cruise_speed, "cruise", None
        preview = max(cfg.preview_min, speed * speed / (2 * cfg.comfort_decel) + 10.0)
        lo, hi = rc.window(s_ego, s_ego + preview)
        k = rc.curvature[lo:hi]
        v_curve = np.maximum(np.sqrt(cfg.max_lateral_accel / np.maximum(k, 1e-6)), cfg.min_curve_speed)
        ahead = np.maximum(rc.s[lo:hi] - s_ego, 0.0)
        v_allow = np.sqrt(v_curve**2 + 2.0 * cfg.comfort_decel * ahead)
        if v_allow.size and float(v_allow.min()) < best:
            best, reason = float(v_allow.min()), "curve"
        for h in hazards:
            v = self._hazard_speed(h)
            if binding is None or v < self._hazard_speed(binding):
                binding = h
        if binding is not None and self._hazard_speed(binding) < best:
            best, reason = self._hazard_speed(binding), binding.reason
        return best, reason, binding

    def _hazard_speed(self, h: Hazard) -> float:
        """Speed allowed now so as to stop at (or, behind a moving lead, settle at) the hazard's point."""
        a = self.config.comfort_decel
        if h.speed > 0.0:  # following a moving lead: settle at its speed at the following distance
            if h.distance > 0.0:
                return min(math.sqrt(h.speed**2 + 2.0 * a * h.distance), h.speed + 0.5 * h.distance)
            return max(0.0, h.speed + 0.5 * h.distance)
        return math.sqrt(2.0 * a * h.distance) if h.distance > 0.0 else 0.0

    def _longitudinal(self, speed: float, v_target: float, binding: Hazard | None) -> tuple[float, float, bool]:
        """(throttle, brake, whether the binding hazard forced the brake beyond the PID's demand)."""
        cfg = self.config
        if v_target <= 0.05 and speed < 0.5:  # stopped at a stop point: hold still
            self._integral = 0.0
            self._prev_error = None
            return 0.0, cfg.hold_brake, False
        error = v_target - speed
        deriv = 0.0 if self._prev_error is None else (error - self._prev_error) / DT
        self._prev_error = error
        u = cfg.kp * error + cfg.ki * self._integral + cfg.kd * deriv
        if not (u >= cfg.max_throttle and error > 0):  # conditional integration: no wind-up at full throttle
            self._integral = float(np.clip(self._integral + error * DT, -cfg.integral_limit, cfg.integral_limit))
        if error < 0 and self._integral > 0:
            self._integral *= 0.9  # bleed the cruise integral while slowing: no throttle held against a stop
        throttle = float(np.clip(u, 0.0, cfg.max_throttle))
        brake = float(np.clip(-u * cfg.brake_gain, 0.0, 1.0)) if u < -cfg.brake_deadband else 0.0
        forced = False
        if binding is not None and binding.distance < 30.0 and speed > binding.speed:
            # a stop point close ahead: brake at least as hard as reaching it demands
            if binding.distance > 0.05:
                need = (speed * speed - binding.speed**2) / (2.0 * binding.distance)
            else:
                need = cfg.max_decel if binding.speed == 0.0 else cfg.comfort_decel
            if need > cfg.comfort_decel:  # above the braking profile: brake at least as it demands
                throttle = 0.0
                forced = True
                brake = max(brake, float(np.clip(need / cfg.max_decel, 0.0, 1.0)))
        if brake > 0.0:
            throttle = 0.0
        return throttle, brake, forced

    # ------------------------------------------------------------------------------------------ hazards
    def _hazards(self, obs: Observation, rc: _RouteCache, s_ego: float, seg: int, speed: float) -> list[Hazard]:
        cfg = self.config
        front = s_ego + 0.5 * cfg.length
        hazards = [Hazard(rc.length + cfg.goal_overshoot - s_ego, "goal")]
        hazards.extend(self._light_hazards(obs, rc, s_ego, front, speed))
        preview = max(cfg.preview_min, speed * speed / (2 * cfg.comfort_decel) + 15.0,
                      speed * cfg.vehicle_horizon + cfg.plan_accel * cfg.vehicle_horizon**2 / 2 + 10.0)
        preview = min(preview, cfg.cruise_speed * cfg.vehicle_horizon + 20.0)
        followed, watched = self._agent_hazards(obs, rc, s_ego, front, speed, preview)
        hazards.extend(self._keep_clear(h, rc, s_ego, front) for h in followed)
        watched = [self._keep_clear(h, rc, s_ego, front) for h in watched]
        hazards.extend(watched)
        hazards.extend(self._restart_hold(watched, float(obs.time), s_ego, speed))
        return hazards

    def _restart_hold(self, watched: list[Hazard], now: float, s_ego: float, speed: float) -> list[Hazard]:
        """Once standing for an agent outside the ego's lane, start only after it stayed clear `restart_hold` s.

        Predictions of crossing traffic and pedestrians switch on and off at their thresholds (a car turning
        across the ego's path changes its predicted curve every frame), and each gap let the ego start and
        creep a little further: it ended on the crosswalk past its stop line (town02 seed 44). A vehicle
        followed in the ego's own lane is not held for: it moves off smoothly, and a queue should follow it.
        """
        cfg = self.config
        stops = [h for h in watched if h.speed == 0.0]
        if speed >= cfg.restart_hold_speed:
            self._hold = None  # moving: the braking profiles handle what appears
            return []
        if stops:
            h = min(stops, key=lambda z: z.distance)
            self._hold = (s_ego + h.distance, h.reason, h.agent_id, now)
            return []
        if self._hold is None or not 0.0 <= now - self._hold[3] < cfg.restart_hold - 1e-9:
            self._hold = None
            return []
        s_stop, reason, agent_id, _ = self._hold
        return [Hazard(s_stop - s_ego, reason, 0.0, agent_id)]

    def _keep_clear(self, h: Hazard, rc: _RouteCache, s_ego: float, front: float) -> Hazard:
        """Never come to a stop inside a junction or on its crosswalks: wait before its stop line instead.

        Stopping there blocks crossing traffic (gridlock) and pedestrians walk into a car standing on their
        crosswalk. Applies while the ego has not yet passed the stop line; a fast lead is simply followed;
        behind a standing queue only the box is kept clear (see below).
        """
        cfg = self.config
        if h.speed > 3.0:
            return h
        c = s_ego + h.distance  # where the centre would stop
        # behind a queue only the box itself: keeping the exit crosswalk clear too would starve the ego
        # at every junction followed by a short block (town02's 20 m blocks never have that much room)
        after = 1.0 if h.reason == "vehicle" else cfg.crosswalk_after_exit
        for lo, hi in rc.junctions:
            zone_hi = hi + after
            if c + 0.5 * cfg.length > lo and c - 0.5 * cfg.length < zone_hi and front <= lo + 0.5:
                back = lo - cfg.stop_line_margin - 0.5 * cfg.length - s_ego
                return Hazard(min(back, h.distance), h.reason, 0.0, h.agent_id)
        return h

    def _light_hazards(self, obs: Observation, rc: _RouteCache, s_ego: float, front: float, speed: float) -> list[Hazard]:
        cfg = self.config
        states: dict[int, LightState] = {ls.id: ls for ls in obs.privileged.lights}
        out = []
        n = len(rc.s)
        for stop_idx, light_id in obs.route.lights:
            s_line = float(rc.s[min(max(int(stop_idx), 0), n - 1)])
            to_line = s_line - front  # front bumper to the stop line
            if to_line < -1.0 or to_line > 60.0:
                if to_line < -1.0:
                    self._light_decisions.pop(light_id, None)
                continue
            ls = states.get(light_id)
            state = ls.state if ls is not None else "green"
            if state == "green":
                self._light_decisions.pop(light_id, None)
                continue
            room = to_line - cfg.stop_line_margin
            if self._light_decisions.get(light_id) != "stop":
                # stop if it can: comfortably on yellow, with any braking on red; once decided, keep to it
                need = speed * speed / (2.0 * max(room, 0.05)) if room > 0 else math.inf
                limit = cfg.yellow_decel if state == "yellow" else cfg.max_decel
                self._light_decisions[light_id] = "stop" if (need <= limit or speed < 0.5) else "go"
            if self._light_decisions[light_id] == "stop":
                out.append(Hazard(room, f"{state}_light"))
        return out

    def _agent_hazards(
        self, obs: Observation, rc: _RouteCache, s_ego: float, front: float, speed: float, preview: float
    ) -> tuple[list[Hazard], list[Hazard]]:
        """Vehicles and pedestrians in the corridor ahead, or predicted to cross it while the ego is there:
        (vehicles in the corridor, everything else)."""
        cfg = self.config
        agents = [a for a in obs.privileged.agents if math.hypot(a.x - obs.pose.x, a.y - obs.pose.y) < preview + 10.0]
        if not agents:
            return [], []
        # from 20 m behind, so that a vehicle following the ego projects onto its lane and is recognised
        proj = _Corridor(rc, max(s_ego - 0.5 * cfg.length - 20.0, 0.0), s_ego + preview)
        pos = np.array([[a.x, a.y] for a in agents])
        yaw = np.array([a.yaw for a in agents])
        spd = np.array([max(a.speed, 0.0) for a in agents])
        length = np.array([a.length for a in agents])
        width = np.array([a.width for a in agents])
        is_ped = np.array([a.kind == "pedestrian" for a in agents])
        margin = 0.5 * cfg.width + cfg.corridor_margin + np.where(is_ped, cfg.pedestrian_margin, 0.0)
        rear = s_ego - 0.5 * cfg.length

        s0, d0, h0 = proj.project(pos)
        rel0 = wrap_to_pi(yaw - h0)
        e_lon, e_lat = _extents(rel0, length, width)
        in_corr = d0 < margin + e_lat
        behind = in_corr & (s0 - e_lon < rear)  # beside or behind the ego in its lane: not ours to stop for
        out: list[Hazard] = []
        followed: list[Hazard] = []
        for i in np.flatnonzero(in_corr & ~behind):
            if self._too_late_but_clear(float(s0[i] - e_lon[i]), float(s0[i] + e_lon[i]), float(d0[i]),
                                        float(e_lat[i]), float(spd[i] * abs(math.sin(rel0[i]))), front, rear, speed):
                continue
            v_along = 0.0 if is_ped[i] else max(float(spd[i] * math.cos(rel0[i])), 0.0)
            gap = cfg.stop_gap if is_ped[i] else cfg.vehicle_gap
            stop_at = float(s0[i] - e_lon[i]) - gap - 0.5 * cfg.length
            if v_along > 0.5:
                stop_at -= cfg.time_gap * v_along
            else:
                v_along = 0.0
            (out if is_ped[i] else followed).append(
                Hazard(stop_at - s_ego, "pedestrian" if is_ped[i] else "vehicle", v_along, agents[i].id))

        # moving agents that can reach the corridor within their horizon (the rest cannot conflict)
        horizon = np.where(is_ped, cfg.pedestrian_horizon, cfg.vehicle_horizon)
        reach = d0 - spd * horizon < margin + 0.5 * np.hypot(length, width)
        movers = np.flatnonzero(~in_corr & (spd >= 0.2) & reach)
        if movers.size:
            ahead = _Corridor(rc, max(front - 1.0, 0.0), s_ego + preview, stride=2)
            reach_m = self._room_before_lights(obs.privileged.lights, pos[movers], yaw[movers], spd[movers],
                                               length[movers], is_ped[movers])
            out.extend(self._crossing_hazards(
                [agents[i] for i in movers], pos[movers], yaw[movers], spd[movers], length[movers], width[movers],
                is_ped[movers], margin[movers], ahead, rc, s_ego, front, speed, reach_m))
        out.extend(self._junction_hazards(rc, front, s0, d0, h0, yaw, spd, e_lat, in_corr, is_ped, agents))
        peds = np.flatnonzero(is_ped & ~in_corr & (d0 < margin + e_lat + cfg.crosswalk_watch))
        if peds.size:
            out.extend(self._crosswalk_hazards(rc, proj, s_ego, front, speed, agents, peds, pos, yaw, spd, s0, d0,
                                               margin + e_lat))
        return followed, out

    def _crosswalk_hazards(
        self, rc: _RouteCache, proj: _Corridor, s_ego: float, front: float, speed: float, agents: list[AgentState],
        peds: np.ndarray, pos: np.ndarray, yaw: np.ndarray, spd: np.ndarray, s0: np.ndarray, d0: np.ndarray,
        reach: np.ndarray,
    ) -> list[Hazard]:
        """A pedestrian at the kerb of a crosswalk the ego is about to cross may step onto it at any moment
        (and turn onto it from the sidewalk without warning): unless the ego clears the crosswalk before they
        could reach its lane, wait before the crosswalk. Pedestrians walking away from the route are ignored."""
        cfg = self.config
        rear = s_ego - 0.5 * cfg.length
        out: list[Hazard] = []
        for lo, hi in rc.junctions:
            for c0, c1 in ((lo, lo + 4.0), (hi, hi + cfg.crosswalk_after_exit)):
                if c0 - front < -0.5 or c0 - front > 25.0:
                    continue  # already on it (too late to wait) or too far to matter yet
                near = peds[(s0[peds] > c0 - 1.5) & (s0[peds] < c1 + 1.5)]
                if not near.size:
                    continue
                vel = spd[near, None] * np.stack([np.cos(yaw[near]), np.sin(yaw[near])], axis=-1)
                _, d_next, _ = proj.project(pos[near] + 0.5 * vel)
                t_out = float(self._time_to_travel(speed, np.array([c1 - rear]))[0])
                for k, i in enumerate(near):
                    if d_next[k] > d0[i] + 0.2:
                        continue  # walking away from the route
                    t_enter = max(float(d0[i] - reach[i]), 0.0) / max(float(spd[i]), cfg.pedestrian_max_speed)
                    if t_enter < t_out + 0.5:
                        out.append(Hazard(c0 - cfg.stop_line_margin - front, "pedestrian", 0.0, agents[i].id))
        return out

    def _too_late_but_clear(self, near: float, far: float, dist: float, e_lat: float, v_lat: float, front: float,
                            rear: float, speed: float) -> bool:
        """An agent near the path whose body is not yet in it, too close to stop short of: braking would only
        leave the ego standing in its way, so go on if the ego is past before the agent could reach it."""
        cfg = self.config
        if speed * speed <= 2.0 * 0.9 * cfg.max_decel * max(near - front - 0.5, 0.01):
            return False  # the ego can still stop short: do that
        room = dist - (0.5 * cfg.width + e_lat + 0.1)
        if room <= 0.0:
            return False  # already touching the ego's path
        return (far - rear) / max(speed, 0.1) < room / max(v_lat, 0.1)

    def _room_before_lights(self, lights: tuple[LightState, ...], pos: np.ndarray, yaw: np.ndarray, spd: np.ndarray,
                            length: np.ndarray, is_ped: np.ndarray) -> np.ndarray:
        """Metres each vehicle can still drive before a light stops it (inf: none does).

        Traffic obeys the lights: a vehicle in the lane of a red light stops at its line, and at a yellow one
        if `traffic_yellow_decel` suffices (the simulator's vehicles and CARLA's autopilot both do). Without
        this, a car approaching its red light looked like one about to cross the ego's path, and the ego
        let the few seconds of a green go by waiting for it (town02's short greens, dense traffic).
        """
        lit = [ls for ls in lights if ls.state != "green"]
        if not lit or not len(pos):
            return np.full(len(pos), np.inf)
        # (lights, vehicles) at once, with the same elementwise operations as one light at a time (math.cos,
        # not np.cos, so the figures are the same to the last bit): this was the expert's costliest line in
        # dense traffic (docs/performance.md)
        lx, ly, lyaw = (np.array([getattr(ls, k) for ls in lit])[:, None] for k in ("x", "y", "yaw"))
        c = np.array([math.cos(ls.yaw) for ls in lit])[:, None]
        s = np.array([math.sin(ls.yaw) for ls in lit])[:, None]
        rx, ry = lx - pos[None, :, 0], ly - pos[None, :, 1]
        ahead = rx * c + ry * s - 0.5 * length  # front bumper to the stop line
        lane = (np.abs(-rx * s + ry * c) < 1.75) & (np.abs(wrap_to_pi(yaw - lyaw)) < math.radians(30.0))
        stops = ~is_ped & lane & (ahead > -0.5) & (ahead < 60.0)
        yellow = np.array([ls.state == "yellow" for ls in lit])[:, None]
        stops &= ~yellow | (ahead >= spd * spd / (2.0 * self.config.traffic_yellow_decel))
        return np.where(stops, np.maximum(ahead, 0.0), np.inf).min(axis=0)

    def _crossing_hazards(
        self, agents: list[AgentState], pos: np.ndarray, yaw: np.ndarray, spd: np.ndarray, length: np.ndarray,
        width: np.ndarray, is_ped: np.ndarray, margin: np.ndarray, proj: _Corridor, rc: _RouteCache,
        s_ego: float, front: float, speed: float, room: np.ndarray | None = None,
    ) -> list[Hazard]:
        """Predict each agent (vehicles keep their yaw rate through at most a quarter turn, as in a junction,
        and stop at a light that stops them; pedestrians walk straight); a conflict is the agent in the
        corridor while the ego passes there."""
        cfg = self.config
        dt = cfg.prediction_step
        t = np.arange(dt, max(cfg.vehicle_horizon, cfg.pedestrian_horizon) + 1e-9, dt)
        rate = np.array([0.0 if ped else float(np.clip(self._rates.get(a.id, 0.0), -1.0, 1.0))
                         for a, ped in zip(agents, is_ped, strict=True)])
        turn = np.clip(rate[:, None] * (t[None, :] - 0.5 * dt), -0.5 * math.pi, 0.5 * math.pi)  # mid-step
        theta = yaw[:, None] + turn  # (m, T)
        travel = spd[:, None] * t[None, :]
        if room is not None:
            travel = np.minimum(travel, room[:, None])
        seg = np.diff(travel, axis=1, prepend=0.0)
        step = seg[..., None] * np.stack([np.cos(theta), np.sin(theta)], axis=-1)
        p = pos[:, None, :] + np.cumsum(step, axis=1)  # (m, T, 2)
        s, d, h = proj.project(p)
        rel = wrap_to_pi(theta - h)
        e_lon, e_lat = _extents(rel, length[:, None], width[:, None])
        horizon = np.where(is_ped, cfg.pedestrian_horizon, cfg.vehicle_horizon)
        inside = (d < margin[:, None] + e_lat) & (s - e_lon > front - 0.5) & (t[None, :] <= horizon[:, None] + 1e-9)
        inside &= is_ped[:, None] | (np.abs(rel) < math.radians(cfg.head_on_deg))
        if not inside.any():
            return []
        # when the ego's front would reach, and its rear leave, each predicted point
        t_in = self._time_to_travel(speed, s - e_lon - front)
        t_out = self._time_to_travel(speed, s + e_lon - (s_ego - 0.5 * cfg.length))
        conflict = inside & (t >= t_in - cfg.time_buffer_before) & (t <= t_out + cfg.time_buffer_after)
        out = []
        rear = s_ego - 0.5 * cfg.length
        for i in np.flatnonzero(conflict.any(axis=1)):
            first = float((s[i] - e_lon[i])[conflict[i]].min())
            if speed * speed > 2.0 * 0.9 * cfg.max_decel * max(first - front - 0.5, 0.01):
                # too late to stop short of it: braking would leave the ego standing in its way, so go on
                # if, at the present speed, the ego is past before the agent arrives
                thr = 0.5 * cfg.width + e_lat[i] + 0.1  # bodies touching, not the planning margin
                touch = np.flatnonzero((d[i] < thr) & (s[i] + e_lon[i] > rear))
                if touch.size == 0:
                    continue
                k = int(touch[0])
                if k == 0:
                    t_arrive = float(t[0]) - dt
                else:  # interpolate the moment it reaches the ego's side between two predicted positions
                    d0k, d1k = float(d[i, k - 1]), float(d[i, k])
                    t_arrive = float(t[k - 1]) + dt * (d0k - float(thr[k - 1])) / max(d0k - d1k, 1e-6)
                far = float((s[i] + e_lon[i])[touch].max())
                if (far - rear) / max(speed, 0.1) < t_arrive:  # braking could only end in its way
                    continue
            stop_at = first - cfg.stop_gap - 0.5 * cfg.length
            kind = "pedestrian" if is_ped[i] else ("junction" if rc.in_junction(first) else "vehicle")
            out.append(Hazard(stop_at - s_ego, kind, 0.0, agents[i].id))
        return out

    def _junction_hazards(
        self, rc: _RouteCache, front: float, s: np.ndarray, d: np.ndarray, h: np.ndarray, yaw: np.ndarray,
        spd: np.ndarray, e_lat: np.ndarray, in_corr: np.ndarray, is_ped: np.ndarray, agents: list[AgentState],
    ) -> list[Hazard]:
        """Do not enter a junction while a vehicle crosses it near the ego's path through it."""
        cfg = self.config
        out = []
        for entry, exit_ in rc.junctions:
            to_entry = entry - front
            if to_entry < 0.0 or to_entry > 20.0:
                continue
            rel = np.abs(wrap_to_pi(yaw - h))
            crossing = (rel > math.radians(30.0)) & (rel < math.radians(150.0))
            busy = (~is_ped & ~in_corr & (spd > 0.5) & crossing & (s >= entry) & (s <= exit_)
                    & (d < cfg.junction_watch + e_lat))
            for i in np.flatnonzero(busy):
                out.append(Hazard(to_entry - cfg.stop_line_margin, "junction", 0.0, agents[i].id))
        return out

    def _time_to_travel(self, v0: float, dist: np.ndarray) -> np.ndarray:
        """Time for the ego to cover `dist` metres accelerating at plan_accel up to cruise speed."""
        cfg = self.config
        a, vmax = cfg.plan_accel, cfg.cruise_speed
        v0 = min(v0, vmax)
        dist = np.maximum(dist, 0.0)
        d_acc = (vmax * vmax - v0 * v0) / (2 * a)
        t_acc = (vmax - v0) / a
        t_ramp = (-v0 + np.sqrt(v0 * v0 + 2 * a * np.minimum(dist, d_acc))) / a
        t_flat = np.maximum(dist - d_acc, 0.0) / vmax
        return np.asarray(np.where(dist <= d_acc, t_ramp, t_acc + t_flat))


def expert_info(expert: Expert) -> dict[str, Any]:
    """The last decision as plain data (for logs and benchmark diagnostics)."""
    st = expert.state
    return {
        "target_speed": st.target_speed,
        "reason": st.reason,
        "hazard": None if st.hazard is None else asdict(st.hazard),
        "lateral_error": st.lateral_error,
    }
