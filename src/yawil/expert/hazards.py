"""Where the expert must stop: every `Hazard` ahead (red and yellow lights at their stop line, vehicles and
pedestrians in or about to enter the corridor the ego will sweep, crossing traffic in junctions, the goal).

`HazardScan` holds the scan as methods of the `Expert` (its base class), since the scan reads and keeps the
expert's memory across steps (light decisions, agents' yaw rates, the restart hold)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from yawil.expert.config import ExpertConfig
from yawil.expert.route import Corridor, RouteCache
from yawil.sim.types import AgentState, LightState, Observation, wrap_angle


@dataclass(frozen=True)
class Hazard:
    """A reason to stop: the ego's centre must stop `distance` metres ahead (negative: already past it)."""

    distance: float
    reason: str  # "red_light" | "yellow_light" | "vehicle" | "pedestrian" | "junction" | "goal"
    speed: float = 0.0  # speed of the hazard along the route (a lead vehicle may be followed, not stopped for)
    agent_id: int | None = None


def _extents(rel: np.ndarray, length: np.ndarray, width: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half extents of boxes along and across a direction at angle `rel` to their heading."""
    c, s = np.abs(np.cos(rel)), np.abs(np.sin(rel))
    return 0.5 * (length * c + width * s), 0.5 * (length * s + width * c)



class HazardScan:
    """The hazard scan of `Expert` (see `yawil.expert.driver`): the state it reads is set by `Expert.__init__`."""

    config: ExpertConfig
    _light_decisions: dict[int, str]
    _rates: dict[int, float]
    _hold: tuple[float, str, int | None, float] | None

    # ------------------------------------------------------------------------------------------ hazards
    def _hazards(self, obs: Observation, rc: RouteCache, s_ego: float, seg: int, speed: float) -> list[Hazard]:
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

    def _keep_clear(self, h: Hazard, rc: RouteCache, s_ego: float, front: float) -> Hazard:
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

    def _light_hazards(self, obs: Observation, rc: RouteCache, s_ego: float, front: float, speed: float) -> list[Hazard]:
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
        self, obs: Observation, rc: RouteCache, s_ego: float, front: float, speed: float, preview: float
    ) -> tuple[list[Hazard], list[Hazard]]:
        """Vehicles and pedestrians in the corridor ahead, or predicted to cross it while the ego is there:
        (vehicles in the corridor, everything else)."""
        cfg = self.config
        agents = [a for a in obs.privileged.agents if math.hypot(a.x - obs.pose.x, a.y - obs.pose.y) < preview + 10.0]
        if not agents:
            return [], []
        # from 20 m behind, so that a vehicle following the ego projects onto its lane and is recognised
        proj = Corridor(rc, max(s_ego - 0.5 * cfg.length - 20.0, 0.0), s_ego + preview)
        pos = np.array([[a.x, a.y] for a in agents])
        yaw = np.array([a.yaw for a in agents])
        spd = np.array([max(a.speed, 0.0) for a in agents])
        length = np.array([a.length for a in agents])
        width = np.array([a.width for a in agents])
        is_ped = np.array([a.kind == "pedestrian" for a in agents])
        margin = 0.5 * cfg.width + cfg.corridor_margin + np.where(is_ped, cfg.pedestrian_margin, 0.0)
        rear = s_ego - 0.5 * cfg.length

        s0, d0, h0 = proj.project(pos)
        rel0 = wrap_angle(yaw - h0)
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
            ahead = Corridor(rc, max(front - 1.0, 0.0), s_ego + preview, stride=2)
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
        self, rc: RouteCache, proj: Corridor, s_ego: float, front: float, speed: float, agents: list[AgentState],
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
        lane = (np.abs(-rx * s + ry * c) < 1.75) & (np.abs(wrap_angle(yaw - lyaw)) < math.radians(30.0))
        stops = ~is_ped & lane & (ahead > -0.5) & (ahead < 60.0)
        yellow = np.array([ls.state == "yellow" for ls in lit])[:, None]
        stops &= ~yellow | (ahead >= spd * spd / (2.0 * self.config.traffic_yellow_decel))
        return np.where(stops, np.maximum(ahead, 0.0), np.inf).min(axis=0)

    def _crossing_hazards(
        self, agents: list[AgentState], pos: np.ndarray, yaw: np.ndarray, spd: np.ndarray, length: np.ndarray,
        width: np.ndarray, is_ped: np.ndarray, margin: np.ndarray, proj: Corridor, rc: RouteCache,
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
        rel = wrap_angle(theta - h)
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
        self, rc: RouteCache, front: float, s: np.ndarray, d: np.ndarray, h: np.ndarray, yaw: np.ndarray,
        spd: np.ndarray, e_lat: np.ndarray, in_corr: np.ndarray, is_ped: np.ndarray, agents: list[AgentState],
    ) -> list[Hazard]:
        """Do not enter a junction while a vehicle crosses it near the ego's path through it."""
        cfg = self.config
        out = []
        for entry, exit_ in rc.junctions:
            to_entry = entry - front
            if to_entry < 0.0 or to_entry > 20.0:
                continue
            rel = np.abs(wrap_angle(yaw - h))
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
