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
from yawil.sim.town.lanes import LaneGraph
from yawil.sim.town.lights import GREEN, YELLOW
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
    PATH_STEP = 1.0  # metres between the path samples (shorter than any vehicle, so nothing slips between)

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

    def _ego_on_path(self, ego: tuple[float, float, float, float], ego_size: tuple[float, float]
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(gap, speed along the path) to the ego for each vehicle whose path ahead runs into it, else INF.

        The vehicle's box (widened 0.4 m a side) is slid along its own lane polyline; the first position that
        overlaps the ego gives the gap, measured in that position's frame so it is exact on straight lanes.
        """
        gap = np.full(self.n, INF)
        lead_v = np.zeros(self.n)
        ex, ey, eyaw, ev = ego
        idx = np.flatnonzero(np.hypot(self.x - ex, self.y - ey) < self.CORRIDOR + 10.0)
        if not len(idx):
            return gap, lead_v
        ahead = np.arange(0.0, self.CORRIDOR + self.PATH_STEP / 2, self.PATH_STEP)
        px, py, pyaw = self._path_points(idx, ahead)
        m, k = px.shape
        boxes = np.stack([px.ravel(), py.ravel(), pyaw.ravel(), np.repeat(self.length[idx], k),
                          np.repeat(self.width[idx] + 0.8, k)], 1)
        hit = boxes_overlap((ex, ey, eyaw, ego_size[0], ego_size[1]), boxes).reshape(m, k)
        c, sn = np.cos(pyaw), np.sin(pyaw)
        lon = (ex - px) * c + (ey - py) * sn
        rel = eyaw - pyaw
        ext = ego_size[0] / 2 * np.abs(np.cos(rel)) + ego_size[1] / 2 * np.abs(np.sin(rel))
        g = ahead[None, :] + lon - ext - self.length[idx, None] / 2
        hit &= ahead[None, :] + lon > 0.0  # the ego is ahead, not beside or behind
        first = np.argmax(hit, axis=1)
        rows = np.flatnonzero(hit[np.arange(m), first])
        sel = idx[rows]
        gap[sel] = g[rows, first[rows]]
        lead_v[sel] = max(ev, 0.0) * np.maximum(np.cos(rel[rows, first[rows]]), 0.0)
        return gap, lead_v

    def _pedestrians_on_path(self, ped_xy: np.ndarray) -> np.ndarray:
        """Gap to the nearest on-road pedestrian along each vehicle's path (INF if none within PED_CORRIDOR)."""
        gap = np.full(self.n, INF)
        if not len(ped_xy):
            return gap
        d = np.hypot(self.x[:, None] - ped_xy[None, :, 0], self.y[:, None] - ped_xy[None, :, 1])
        idx = np.flatnonzero(d.min(axis=1) < self.PED_CORRIDOR + 5.0)
        if not len(idx):
            return gap
        ahead = np.arange(0.0, self.PED_CORRIDOR + self.PATH_STEP / 2, self.PATH_STEP)
        px, py, pyaw = self._path_points(idx, ahead)
        c, sn = np.cos(pyaw)[..., None], np.sin(pyaw)[..., None]
        rx, ry = ped_xy[None, None, :, 0] - px[..., None], ped_xy[None, None, :, 1] - py[..., None]
        lon, lat = rx * c + ry * sn, -rx * sn + ry * c
        half = self.length[idx, None, None] / 2
        along = ahead[None, :, None] + lon  # the pedestrian's arc distance along the path
        hit = (np.abs(lat) < self.width[idx, None, None] / 2 + 0.9) & (np.abs(lon) <= half + 0.5) & (along > 0)
        g = np.where(hit, along - half - 0.5, INF)
        gap[idx] = g.min(axis=(1, 2))
        return gap

    def occupied(self, extra: np.ndarray) -> np.ndarray:
        """Connector occupancy (bool per lane): vehicles on connectors plus `extra` lane ids (the ego)."""
        occ = np.zeros(len(self.lanes.lanes), dtype=bool)
        occ[self.lane] = True
        occ[: self.lanes.n_road_lanes] = False
        occ[extra] = True
        return occ

    def step(self, dt: float, rng: np.random.Generator, light_codes: np.ndarray, ego: tuple[float, float, float, float],
             ego_size: tuple[float, float], ego_lanes: np.ndarray, ped_xy: np.ndarray,
             ego_on_lane: tuple[int, float] = (-1, 0.0)) -> None:
        """Advance dt. `ego_lanes`: junction connectors the ego occupies; `ego_on_lane`: its (road lane, s)."""
        if not self.n:
            return
        lanes = self.lanes
        L = lanes.length
        lane, s, v = self.lane, self.s, self.v
        rem = L[lane] - s
        half = self.length / 2
        # 1. the vehicle ahead on the path (same lane, next lane, the one after)
        same = (lane[None, :] == lane[:, None]) & (s[None, :] > s[:, None])
        d_same = np.where(same, s[None, :] - s[:, None], INF)
        d1 = np.where(lane[None, :] == self.nxt1[:, None], rem[:, None] + s[None, :], INF)
        d2 = np.where(lane[None, :] == self.nxt2[:, None], (rem + L[self.nxt1])[:, None] + s[None, :], INF)
        dist = np.minimum(np.minimum(d_same, d1), d2) - half[:, None] - half[None, :]
        j = np.argmin(dist, axis=1)
        gap = dist[np.arange(self.n), j]
        lead_v = v[j]
        # 2. the ego and pedestrians on the path ahead
        g_ego, v_ego = self._ego_on_path(ego, ego_size)
        closer = g_ego < gap
        gap = np.where(closer, g_ego, gap)
        lead_v = np.where(closer, v_ego, lead_v)
        g_ped = self._pedestrians_on_path(ped_xy)
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
        blocked = gate & (np.any(lanes.conflict[self.nxt1] & occ[None, :], axis=1)
                          | (room[self.exit_of[self.nxt1]] < self.length + self.S0 + 1.0))
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
            if self.is_gate[nxt] and (np.any(lanes.conflict[nxt] & occ)
                                      or room[self.exit_of[nxt]] < self.length[i] + self.S0 + 1.0):
                self.s[i], self.v[i] = L[lane[i]], 0.0  # wait at the entry
                continue
            if nxt >= lanes.n_road_lanes:
                room[self.exit_of[nxt]] -= self.length[i] + self.S0
            self.s[i] -= L[lane[i]]
            self.lane[i] = nxt
            self.nxt1[i] = self.nxt2[i]
            self.nxt2[i] = self._pick(int(self.nxt1[i]), rng)
            if self.is_gate[nxt]:
                occ[nxt] = True
        self._update_pose()
