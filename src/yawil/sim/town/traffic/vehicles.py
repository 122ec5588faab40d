"""Background traffic: vehicles on the lane graph, vectorised with numpy.

Each vehicle holds (lane, arc length, speed) and the next two lanes of its random route, drawn from the
episode's generator whenever it moves on. Longitudinal control is the Intelligent Driver Model against the
nearest of: the vehicle ahead on its path, the ego or a pedestrian on its path (its own lane polyline
ahead, so a turning vehicle does not stop for what lies straight ahead of its bonnet), a red/yellow stop
line, or the stop line of a junction it may not enter (a conflicting connector is occupied, or its exit
lane has no room: the yielding and "don't block the box" rules).
"""

from __future__ import annotations

import math

import numpy as np

from yawil.sim.criteria import boxes_overlap
from yawil.sim.town.map.lanes import LaneGraph
from yawil.sim.town.traffic.lights import GREEN, YELLOW
from yawil.sim.types import RoadOption

VEHICLE_COLORS = ((0.75, 0.1, 0.1), (0.1, 0.2, 0.6), (0.85, 0.85, 0.85), (0.1, 0.1, 0.1), (0.5, 0.5, 0.55),
                  (0.9, 0.7, 0.1), (0.2, 0.45, 0.25), (0.45, 0.25, 0.15))
INF = 1e9


class Vehicles:
    A_MAX = 2.0  # IDM comfortable acceleration
    B_COMF = 3.0  # IDM comfortable deceleration
    B_MAX = 8.0
    S0 = 2.5  # standstill gap, m
    T = 1.2  # time headway, s
    TURN_SPEED = 5.0
    CORRIDOR = 30.0  # how far along its path a vehicle looks for the ego
    PED_CORRIDOR = 20.0  # ... and for pedestrians on the road
    PATH_STEP = 2.0  # metres between the path samples (well under a vehicle's length: nothing slips between)
    RESERVE_S = 10.0  # waited this long for room on its exit lane, a queue head reserves the next room there
    BEHIND = 6.0  # paths do not turn back: what lies this far behind a vehicle's centre is never on its path

    def __init__(self, lanes: LaneGraph) -> None:
        self.lanes = lanes
        self.is_turn = np.array([ln.kind == "connector" and ln.option in (RoadOption.LEFT, RoadOption.RIGHT)
                                 or (ln.kind == "connector" and self.lanes.degree[ln.node] == 2)
                                 for ln in lanes.lanes])
        self.is_gate = np.array([ln.kind == "connector" and lanes.degree[ln.node] >= 3 for ln in lanes.lanes])
        self.stop_s = np.array([lanes.approaches[i].stop_s if i >= 0 else ln.length - lanes.STOP_BACK
                                for i, ln in zip(lanes.light_of_lane.tolist(), lanes.lanes, strict=True)])
        self.successors = [np.array(ln.successors, dtype=np.int64) for ln in lanes.lanes]
        self.exit_of = np.array([max(ln.exit, 0) for ln in lanes.lanes], dtype=np.int64)
        self.n = 0
        self._alloc(0)

    def _alloc(self, n: int) -> None:
        self.n = n
        self.lane = np.zeros(n, dtype=np.int64)
        self.s = np.zeros(n)
        self.v = np.zeros(n)
        self.v0 = np.zeros(n)
        self.nxt1 = np.zeros(n, dtype=np.int64)
        self.nxt2 = np.zeros(n, dtype=np.int64)
        self.length = np.zeros(n)
        self.width = np.zeros(n)
        self.height = np.zeros(n)
        self.color_index = np.zeros(n, dtype=np.int64)
        self.x = np.zeros(n)
        self.y = np.zeros(n)
        self.yaw = np.zeros(n)
        self.ids = np.arange(1, n + 1)
        self.wait = np.zeros(n)  # seconds a queue head has waited at its stop line for room after the junction
        self.ego_wait = 0.0  # the same for the ego

    def _pick(self, lane: int, rng: np.random.Generator) -> int:
        succ = self.successors[lane]
        return int(succ[int(rng.integers(len(succ)))])

    def spawn(self, n: int, rng: np.random.Generator, keep_out: list[tuple[float, float, float]]) -> None:
        """Place n vehicles on road lanes, clear of each other and of the (x, y, radius) keep-out discs."""
        self._alloc(n)
        lanes = self.lanes
        room = np.maximum(lanes.length[: lanes.n_road_lanes] - 12.0, 0.0)
        if n > room.sum() / 12.0:
            raise ValueError(f"{n} vehicles do not fit on town {lanes.layout.name!r} (about {int(room.sum() / 12.0)} "
                             f"do). Use fewer vehicles.")
        weights = room / room.sum()
        placed = 0
        tries = 0
        while placed < n:
            tries += 1
            if tries > 100 * n + 1000:
                raise ValueError(f"cannot place {n} vehicles on town {lanes.layout.name!r} without overlaps; "
                                 f"placed {placed}. Use fewer vehicles.")
            lane = int(rng.choice(lanes.n_road_lanes, p=weights))
            s = float(rng.uniform(6.0, lanes.length[lane] - 6.0))
            (x,), (y,), _ = lanes.lookup(np.array([lane]), np.array([s]))
            if any(math.hypot(x - kx, y - ky) < kr for kx, ky, kr in keep_out):
                continue
            if placed and np.min(np.hypot(self.x[:placed] - x, self.y[:placed] - y)) < 9.0:
                continue
            i = placed
            self.lane[i], self.s[i] = lane, s
            self.x[i], self.y[i] = x, y
            self.nxt1[i] = self._pick(lane, rng)
            self.nxt2[i] = self._pick(int(self.nxt1[i]), rng)
            self.v0[i] = rng.uniform(6.5, 9.0)
            self.length[i] = rng.uniform(3.8, 5.0)
            self.width[i] = rng.uniform(1.7, 2.0)
            self.height[i] = rng.uniform(1.4, 1.9)
            self.color_index[i] = rng.integers(len(VEHICLE_COLORS))
            placed += 1
        self._update_pose()

    def _update_pose(self) -> None:
        if self.n:
            self.x, self.y, self.yaw = self.lanes.lookup(self.lane, self.s)

    def _exit_room(self, ego_on_lane: tuple[int, float], ego_length: float) -> np.ndarray:
        """Free metres on each lane for one more vehicle, minus what is already queued in the junctions towards it.

        A vehicle enters a junction only if its exit lane has room for it ("don't block the box"), which keeps
        dense traffic from gridlocking. Room is the smaller of the free metres at the lane's start now and
        the lane's length minus the queue everything on it would form if it stopped (length + standstill gap
        each): a lane whose vehicles still move looks free at its start but fills up once they queue at the
        next junction, and a vehicle that entered on the first measure would then stand in the box.
        """
        L = self.lanes.length
        first = L.copy()
        np.minimum.at(first, self.lane, self.s - self.length / 2)
        used = np.bincount(self.lane, weights=self.length + self.S0, minlength=len(L))
        if ego_on_lane[0] >= 0:
            first[ego_on_lane[0]] = min(first[ego_on_lane[0]], ego_on_lane[1] - ego_length / 2)
            used[ego_on_lane[0]] += ego_length + self.S0
        conn = self.lane >= self.lanes.n_road_lanes
        queued = np.bincount(self.exit_of[self.lane[conn]], weights=self.length[conn] + self.S0, minlength=len(L))
        return np.minimum(first, L - used) - queued

    def _path_points(self, idx: np.ndarray, ahead: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw), each (len(idx), len(ahead)), of the centres of vehicles idx `ahead` metres along their path."""
        L = self.lanes.length
        lane1, lane2, lane3 = self.lane[idx, None], self.nxt1[idx, None], self.nxt2[idx, None]
        a = self.s[idx, None] + ahead[None, :]
        l1, l2 = L[lane1], L[lane2]
        on2, on3 = a > l1, a > l1 + l2
        lane = np.where(on3, lane3, np.where(on2, lane2, lane1))
        a = np.where(on3, a - l1 - l2, np.where(on2, a - l1, a))
        x, y, yaw = self.lanes.lookup(lane.ravel(), a.ravel())
        shape = (len(idx), len(ahead))
        return x.reshape(shape), y.reshape(shape), yaw.reshape(shape)

    def _hazards_on_path(self, ego: tuple[float, float, float, float], ego_size: tuple[float, float],
                         ped_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gap to the ego, the ego's speed along the path, gap to the nearest on-road pedestrian) per vehicle.

        Each vehicle's box is slid along its own lane polyline (samples PATH_STEP apart): the ego counts when
        the box, widened 0.4 m a side, would overlap it within CORRIDOR metres; a pedestrian when it lies in
        the box widened 0.9 m a side within PED_CORRIDOR. Gaps are measured in the frame of the first
        touching sample, so they are exact on straight lanes. INF where nothing is on the path. Only
        vehicles with something near and not behind them are looked at; one path lookup serves both.
        """
        n = self.n
        g_ego, v_ego, g_ped = np.full(n, INF), np.zeros(n), np.full(n, INF)
        ex, ey, eyaw, ev = ego
        c0, s0 = np.cos(self.yaw), np.sin(self.yaw)
        rx, ry = ex - self.x, ey - self.y
        want_ego = (np.hypot(rx, ry) < self.CORRIDOR + 6.0) & (rx * c0 + ry * s0 > -self.BEHIND)
        if len(ped_xy):
            px, py = ped_xy[None, :, 0] - self.x[:, None], ped_xy[None, :, 1] - self.y[:, None]
            want_ped = np.any((np.hypot(px, py) < self.PED_CORRIDOR + 4.0)
                              & (px * c0[:, None] + py * s0[:, None] > -self.BEHIND), axis=1)
        else:
            want_ped = np.zeros(n, dtype=bool)
        idx = np.flatnonzero(want_ego | want_ped)
        if not len(idx):
            return g_ego, v_ego, g_ped
        ahead = np.arange(0.0, self.CORRIDOR + self.PATH_STEP / 2, self.PATH_STEP)
        x, y, yaw = self._path_points(idx, ahead)
        c, sn = np.cos(yaw), np.sin(yaw)
        half = self.length[idx, None] / 2
        # the ego: bounding circles first, the exact box test only for samples that may touch
        reach = np.hypot(half, self.width[idx, None] / 2 + 0.4) + math.hypot(ego_size[0] / 2, ego_size[1] / 2)
        near = want_ego[idx, None] & (np.hypot(x - ex, y - ey) < reach)
        if near.any():
            rows, cols = np.nonzero(near)
            boxes = np.stack([x[rows, cols], y[rows, cols], yaw[rows, cols], 2 * half[rows, 0],
                              self.width[idx[rows]] + 0.8], 1)
            lon = (ex - x[rows, cols]) * c[rows, cols] + (ey - y[rows, cols]) * sn[rows, cols]
            hit = boxes_overlap((ex, ey, eyaw, ego_size[0], ego_size[1]), boxes) & (ahead[cols] + lon > 0.0)
            rows, cols, lon = rows[hit], cols[hit], lon[hit]
            first = np.ones(len(rows), dtype=bool)
            first[1:] = rows[1:] != rows[:-1]  # np.nonzero is row-major: the first hit of a row is its nearest
            rows, cols, lon = rows[first], cols[first], lon[first]
            rel = eyaw - yaw[rows, cols]
            ext = ego_size[0] / 2 * np.abs(np.cos(rel)) + ego_size[1] / 2 * np.abs(np.sin(rel))
            g_ego[idx[rows]] = ahead[cols] + lon - ext - half[rows, 0]
            v_ego[idx[rows]] = max(ev, 0.0) * np.maximum(np.cos(rel), 0.0)
        # pedestrians on the road, within PED_CORRIDOR along the path
        k = int(round(self.PED_CORRIDOR / self.PATH_STEP)) + 1
        rows = np.flatnonzero(want_ped[idx])
        if len(rows):
            xs, ys, cs, ss = x[rows, :k, None], y[rows, :k, None], c[rows, :k, None], sn[rows, :k, None]
            qx, qy = ped_xy[None, None, :, 0] - xs, ped_xy[None, None, :, 1] - ys
            lon, lat = qx * cs + qy * ss, -qx * ss + qy * cs
            h = half[rows, :, None]
            along = ahead[None, :k, None] + lon  # the pedestrian's arc distance along the path
            hit = (np.abs(lat) < self.width[idx[rows], None, None] / 2 + 0.9) & (np.abs(lon) <= h + 0.5) & (along > 0)
            g_ped[idx[rows]] = np.where(hit, along - h - 0.5, INF).min(axis=(1, 2))
        return g_ego, v_ego, g_ped

    def occupied(self, extra: np.ndarray) -> np.ndarray:
        """Connector occupancy (bool per lane): vehicles on connectors plus `extra` lane ids (the ego)."""
        occ = np.zeros(len(self.lanes.lanes), dtype=bool)
        occ[self.lane] = True
        occ[: self.lanes.n_road_lanes] = False
        occ[extra] = True
        return occ

    def step(self, dt: float, rng: np.random.Generator, light_codes: np.ndarray, ego: tuple[float, float, float, float],
             ego_size: tuple[float, float], ego_lanes: np.ndarray, ped_xy: np.ndarray,
             ego_on_lane: tuple[int, float] = (-1, 0.0), ego_gate: tuple[int, bool] = (-1, False)) -> None:
        """Advance dt. `ego_lanes`: junction connectors the ego occupies; `ego_on_lane`: its (road lane, s);
        `ego_gate`: (the lane it will exit the junction ahead onto, whether it stands at that junction's stop
        line as the head of its queue), so that it takes part in the exit-room reservation like a vehicle."""
        if not self.n:
            return
        lanes = self.lanes
        L = lanes.length
        lane, s, v = self.lane, self.s, self.v
        rem = L[lane] - s
        half = self.length / 2
        # 1. the vehicle ahead on the path: the next one on the same lane (in (lane, s) order), else the rearmost
        # one on the next lane, else on the one after. Sorting is O(n log n) where a pairwise table was O(n^2).
        order = np.lexsort((s, lane))
        lane_sorted = lane[order]
        gap = np.full(self.n, INF)
        j = np.zeros(self.n, dtype=np.int64)
        has = lane_sorted[1:] == lane_sorted[:-1]
        me, ahead = order[:-1][has], order[1:][has]
        gap[me] = s[ahead] - s[me] - half[me] - half[ahead]
        j[me] = ahead
        rearmost = np.full(len(L), -1, dtype=np.int64)
        starts = np.concatenate([[True], ~has])
        rearmost[lane_sorted[starts]] = order[starts]
        for next_lane, before in ((self.nxt1, rem), (self.nxt2, rem + L[self.nxt1])):
            k = rearmost[next_lane]
            ok = k >= 0
            d = np.where(ok, before + s[k] - half - half[k], INF)
            better = d < gap
            gap = np.where(better, d, gap)
            j = np.where(better, k, j)
        lead_v = v[j]
        # 2. the ego and pedestrians on the path ahead
        g_ego, v_ego, g_ped = self._hazards_on_path(ego, ego_size, ped_xy)
        closer = g_ego < gap
        gap = np.where(closer, g_ego, gap)
        lead_v = np.where(closer, v_ego, lead_v)
        closer = g_ped < gap
        gap = np.where(closer, g_ped, gap)
        lead_v = np.where(closer, 0.0, lead_v)
        # 3. stop lines: lights, and junctions whose conflicting connector is occupied
        occ = self.occupied(ego_lanes)
        light = lanes.light_of_lane[lane]
        code = np.where(light >= 0, light_codes[np.maximum(light, 0)], GREEN)
        g_stop = self.stop_s[lane] - s - half
        must_stop = (code != GREEN) & ~((code == YELLOW) & (g_stop < v * v / (2 * self.B_COMF)))
        gate = self.is_gate[self.nxt1] & (lane < lanes.n_road_lanes)
        room = self._exit_room(ego_on_lane, ego_size[0])
        need = self.length + self.S0 + 1.0
        exit_lane = self.exit_of[self.nxt1]
        # fairness: a queue head that has waited RESERVE_S at its stop line for room on its exit lane reserves
        # the next room there, else another approach (green while it is red) can refill that lane every cycle
        at_line = gate & (g_stop < 4.0)
        self.wait = np.where(at_line & ((self.wait > 0.0) | (room[exit_lane] < need)), self.wait + dt, 0.0)
        # the ego too: else the traffic that shares its green refills the lane it waits for, for ever (town02
        # seed 26: turning right from the north onto the 20 m block, which the straight traffic keeps full)
        ego_exit, ego_at_line = ego_gate
        ego_need = ego_size[0] + self.S0 + 1.0
        waited = ego_exit >= 0 and ego_at_line and (self.ego_wait > 0.0 or room[ego_exit] < ego_need)
        self.ego_wait = self.ego_wait + dt if waited else 0.0
        holder = np.full(len(L), -1, dtype=np.int64)  # -2: the ego
        waiting = np.flatnonzero(self.wait > self.RESERVE_S)
        claims = [(float(self.wait[i]), i, int(exit_lane[i])) for i in waiting.tolist()]
        if self.ego_wait > self.RESERVE_S:
            claims.append((self.ego_wait, -2, ego_exit))
        for _, i, e in sorted(claims, key=lambda c: c[0]):
            holder[e] = i  # the longest wait wins
        reserved = np.where(holder >= 0, need[np.maximum(holder, 0)], np.where(holder == -2, ego_need, 0.0))
        room_for = room[exit_lane] - np.where(holder[exit_lane] == np.arange(self.n), 0.0, reserved[exit_lane])
        blocked = gate & (room_for < need)
        at_gate = np.flatnonzero(gate & ~blocked)
        blocked[at_gate] = np.any(lanes.conflict[self.nxt1[at_gate]] & occ[None, :], axis=1)
        # past its stop line, a blocked vehicle still waits at the junction's entry (step 5 holds it there)
        g_stop = np.where(blocked & (g_stop <= -1.0), rem - half, g_stop)
        stop = (must_stop & (light >= 0) | blocked) & (g_stop > -1.0)
        closer = stop & (g_stop < gap)
        gap = np.where(closer, g_stop, gap)
        lead_v = np.where(closer, 0.0, lead_v)
        # 4. IDM
        v0 = np.where(self.is_turn[lane] | (self.is_turn[self.nxt1] & (rem < 12.0)), np.minimum(self.v0, self.TURN_SPEED),
                      self.v0)
        s_star = self.S0 + np.maximum(0.0, v * self.T + v * (v - lead_v) / (2 * math.sqrt(self.A_MAX * self.B_COMF)))
        acc = self.A_MAX * (1 - (v / v0) ** 4 - (s_star / np.maximum(gap, 0.1)) ** 2)
        acc = np.clip(acc, -self.B_MAX, self.A_MAX)
        v_new = np.maximum(v + acc * dt, 0.0)
        s_new = s + 0.5 * (v + v_new) * dt
        self.v = v_new
        self.s = s_new
        # 5. lane changes at lane ends (few per step: a plain loop)
        # Entering a junction re-checks both rules against those who got in earlier this step.
        for i in np.flatnonzero(s_new > L[lane]).tolist():
            nxt = int(self.nxt1[i])
            e = int(self.exit_of[nxt])
            free = room[e] - (reserved[e] if holder[e] not in (-1, i) else 0.0)
            if self.is_gate[nxt] and (np.any(lanes.conflict[nxt] & occ) or free < need[i]):
                self.s[i], self.v[i] = L[lane[i]], 0.0  # wait at the entry
                continue
            if nxt >= lanes.n_road_lanes:
                room[e] -= self.length[i] + self.S0
            self.s[i] -= L[lane[i]]
            self.lane[i] = nxt
            self.nxt1[i] = self.nxt2[i]
            self.nxt2[i] = self._pick(int(self.nxt1[i]), rng)
            if self.is_gate[nxt]:
                occ[nxt] = True
        self._update_pose()
