"""The privileged expert driver (`Expert`): the teacher of every learned agent and the upper bound of the benchmark.

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
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from yawil.expert.config import ExpertConfig
from yawil.expert.hazards import Hazard, HazardScan
from yawil.expert.route import RouteCache
from yawil.sim.types import DT, Control, Observation, wrap_angle


@dataclass
class ExpertState:
    """What the expert decided at the last step, for debugging, tests and the benchmark's diagnostics."""

    target_speed: float = 0.0
    reason: str = "cruise"
    hazard: Hazard | None = None
    lateral_error: float = 0.0
    light_decisions: dict[int, str] = field(default_factory=dict)
    hazards: tuple[Hazard, ...] = ()  # every stop point considered this step (labels of lead vehicle and lights)


class Expert(HazardScan):
    """Privileged driver with the agent's duck type: `reset()`, `act(obs) -> Control`."""

    def __init__(self, config: ExpertConfig | None = None) -> None:
        self.config = config or ExpertConfig()
        self.state = ExpertState()
        self._cache: RouteCache | None = None
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
            self._cache = RouteCache(obs.route)
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

    def _pure_pursuit(self, obs: Observation, rc: RouteCache, s_ego: float, speed: float) -> float:
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
        self, rc: RouteCache, s_ego: float, speed: float, hazards: list[Hazard]
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
        return hazard_speed(h.distance, h.speed, self.config.comfort_decel)

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


def hazard_speed(distance: float, speed: float, decel: float) -> float:
    """Speed allowed now so as to stop at (or, behind a moving lead at `speed`, settle at) a point `distance`
    metres ahead, braking at `decel`. The expert's rule, also the learned agent's under `speed_control="lead"`."""
    if speed > 0.0:  # following a moving lead: settle at its speed at the following distance
        if distance > 0.0:
            return min(math.sqrt(speed**2 + 2.0 * decel * distance), speed + 0.5 * distance)
        return max(0.0, speed + 0.5 * distance)
    return math.sqrt(2.0 * decel * distance) if distance > 0.0 else 0.0


def expert_info(expert: Expert) -> dict[str, Any]:
    """The last decision as plain data (for logs and benchmark diagnostics)."""
    st = expert.state
    return {
        "target_speed": st.target_speed,
        "reason": st.reason,
        "hazard": None if st.hazard is None else asdict(st.hazard),
        "lateral_error": st.lateral_error,
    }
