"""Pedestrians: random walks on the walkway graph, crossing at crosswalks and sometimes anywhere.

Jaywalking: while on a sidewalk along a road, each step a pedestrian may, with a small seeded probability,
cross straight over the road to the other sidewalk. Like real pedestrians they do not walk into cars: one
steps onto the road (a crosswalk or a jaywalk) only when no vehicle, nor the ego, stands on its crossing
or would reach it within the time the crossing takes, and on the road it stops rather than step into a
vehicle; stopped there for a few seconds (a car pulled up across its way), it turns back to the kerb it
came from. They do not watch for cars that come after they started: drivers (and the expert) must stop.
"""

from __future__ import annotations

import numpy as np

from yawil.sim.town.map.walkways import Walkways

PED_COLORS = ((0.2, 0.2, 0.5), (0.6, 0.1, 0.1), (0.1, 0.4, 0.2), (0.3, 0.3, 0.3), (0.7, 0.6, 0.2), (0.5, 0.3, 0.5))
SIZE = 0.6  # footprint, metres square
HEIGHT = 1.75
CLEARANCE = 1.0  # metres kept from a moving vehicle's box when deciding to cross
STANDING = 0.3  # m/s: slower than this, a vehicle is standing, and passing a bumper's width off it is fine
CONTACT = SIZE / 2 + 0.2  # on the road, a step that would come this close to a vehicle's box is not taken
HORIZON_EXTRA = 2.0  # seconds added to the crossing time when checking approaching vehicles
GIVE_UP_S = 4.0  # stopped on the road this long: turn back
KERB_GIVE_UP_S = 15.0  # waited at a kerb this long (a car stands on the crosswalk): walk elsewhere
LOOK_EVERY = 5  # steps between two looks from the kerb (0.5 s: a pedestrian's glance, and a tenth of the cost)


class Pedestrians:
    def __init__(self, walk: Walkways, jaywalk_per_s: float = 0.004) -> None:
        self.walk = walk
        self.jaywalk_per_s = jaywalk_per_s
        self.is_crosswalk = np.array([k == "crosswalk" for k in walk.edge_kind])
        self.twin = np.array(walk.edge_twin, dtype=np.int64)
        self._alloc(0)

    def _alloc(self, n: int) -> None:
        self.n = n
        self.xy = np.zeros((n, 2))
        self.target = np.zeros((n, 2))
        self.dest = np.zeros(n, dtype=np.int64)  # walkway node walked to, or -1 while jaywalking
        self.prev = np.zeros(n, dtype=np.int64)
        self.edge = np.zeros(n, dtype=np.int64)  # current edge, or the twin edge while jaywalking
        self.speed = np.zeros(n)  # walking pace
        self.v = np.zeros(n)  # speed this step: the pace, or 0 while waiting (what observers are told)
        self.yaw = np.zeros(n)
        self.on_road = np.zeros(n, dtype=bool)
        self.kerb = np.zeros(n, dtype=bool)  # waiting at a kerb for a clear crosswalk
        self.back = np.zeros((n, 2))  # where a jaywalker left its sidewalk (to turn back to)
        self.stopped = np.zeros(n)  # seconds stopped on the road, or waiting at a kerb
        self.steps = 0
        self.color_index = np.zeros(n, dtype=np.int64)
        self.ids = np.arange(10001, 10001 + n)

    def spawn(self, n: int, rng: np.random.Generator, keep_out: list[tuple[float, float, float]]) -> None:
        """Place n pedestrians on sidewalk edges (not on crosswalks), outside the keep-out discs."""
        self._alloc(n)
        walk = self.walk
        side = np.flatnonzero(~self.is_crosswalk)
        lengths = np.array([walk.edge_length(int(e)) for e in side])
        p = lengths / lengths.sum()
        placed, tries = 0, 0
        while placed < n:
            tries += 1
            if tries > 100 * n + 1000:
                raise ValueError(f"cannot place {n} pedestrians; placed {placed}. Use fewer pedestrians.")
            e = int(side[int(rng.choice(len(side), p=p))])
            a, b = walk.edges[e]
            if rng.random() < 0.5:
                a, b = b, a
            f = float(rng.uniform(0.0, 1.0))
            xy = walk.xy[a] + f * (walk.xy[b] - walk.xy[a])
            if any(np.hypot(xy[0] - kx, xy[1] - ky) < kr for kx, ky, kr in keep_out):
                continue
            if placed and np.min(np.hypot(*(self.xy[:placed] - xy).T)) < 1.0:
                continue
            i = placed
            self.xy[i], self.target[i] = xy, walk.xy[b]
            self.dest[i], self.prev[i], self.edge[i] = b, a, e
            self.speed[i] = self.v[i] = rng.uniform(1.0, 1.6)
            self.color_index[i] = rng.integers(len(PED_COLORS))
            d = walk.xy[b] - walk.xy[a]
            self.yaw[i] = np.arctan2(d[1], d[0])
            placed += 1

    @staticmethod
    def _crossing_clear(p: np.ndarray, q: np.ndarray, speed: np.ndarray, actors: np.ndarray) -> np.ndarray:
        """Per crossing p[i]-q[i] (walked at speed[i]): True if no actor's box, swept along its heading over the
        crossing's duration plus HORIZON_EXTRA, comes within CLEARANCE of it.

        `actors` rows: (x, y, yaw, length, width, speed). A vehicle's path is taken as straight over these few
        seconds; that is all a pedestrian at the kerb can judge, and drivers stop for what they missed.
        """
        p, q = np.atleast_2d(p), np.atleast_2d(q)
        if not len(actors) or not len(p):
            return np.ones(len(p), dtype=bool)
        seg = q - p
        span = np.maximum(np.hypot(seg[:, 0], seg[:, 1]), 1e-6)[:, None]
        ux, uy = seg[:, 0:1] / span, seg[:, 1:2] / span
        nx, ny = -uy, ux
        x, y, yaw, length, width, speed_a = (actors[None, :, k] for k in range(6))
        rx, ry = x - p[:, 0:1], y - p[:, 1:2]
        a = rx * ux + ry * uy  # along the crossing
        b = rx * nx + ry * ny  # across it (the crossing line is b = 0)
        c, s = np.cos(yaw), np.sin(yaw)
        cu, cn = c * ux + s * uy, c * nx + s * ny  # the actor's heading on the two axes
        hu = length / 2 * np.abs(cu) + width / 2 * np.abs(cn)
        hn = length / 2 * np.abs(cn) + width / 2 * np.abs(cu)
        horizon = span / np.maximum(np.atleast_1d(speed), 0.1)[:, None] + HORIZON_EXTRA
        va, vb = speed_a * cu * horizon, speed_a * cn * horizon  # displacement over the horizon
        margin = np.where(speed_a < STANDING, CONTACT, CLEARANCE + SIZE / 2)
        meets = ((np.maximum(a, a + va) + hu + margin > 0.0) & (np.minimum(a, a + va) - hu - margin < span)
                 & (np.maximum(b, b + vb) + hn + margin > 0.0) & (np.minimum(b, b + vb) - hn - margin < 0.0))
        return ~meets.any(axis=1)

    @staticmethod
    def _box_distance(xy: np.ndarray, actors: np.ndarray) -> np.ndarray:
        """(P, M) distance from points to actor boxes (0 inside)."""
        x, y, yaw, length, width = (actors[:, k] for k in range(5))
        rx, ry = xy[:, None, 0] - x[None, :], xy[:, None, 1] - y[None, :]
        c, s = np.cos(yaw)[None, :], np.sin(yaw)[None, :]
        lon = np.maximum(np.abs(rx * c + ry * s) - length[None, :] / 2, 0.0)
        lat = np.maximum(np.abs(-rx * s + ry * c) - width[None, :] / 2, 0.0)
        return np.hypot(lon, lat)

    def _turn_back(self, i: int) -> None:
        """Return to the kerb this pedestrian left: along its crosswalk, or straight back when jaywalking."""
        walk = self.walk
        if self.dest[i] < 0:
            self.target[i] = self.back[i]
            self.edge[i] = int(self.twin[self.edge[i]])
        else:
            self.dest[i], self.prev[i] = self.prev[i], self.dest[i]
            self.target[i] = walk.xy[int(self.dest[i])]
        self.stopped[i] = 0.0

    def step(self, dt: float, rng: np.random.Generator, actors: np.ndarray | None = None) -> None:
        """Advance dt. `actors`: (M, 6) rows (x, y, yaw, length, width, speed) of the vehicles and the ego."""
        if not self.n:
            return
        walk = self.walk
        actors = np.zeros((0, 6)) if actors is None else np.asarray(actors, dtype=np.float64).reshape(-1, 6)
        # jaywalk: leave a sidewalk edge along a road for the twin on the other side, if the road is clear
        draw = rng.random(self.n)
        jay = np.flatnonzero((draw < self.jaywalk_per_s * dt) & (self.dest >= 0) & (self.twin[self.edge] >= 0)
                             & ~self.on_road)
        if len(jay):
            e = self.twin[self.edge[jay]]
            pa, pb = walk.xy[walk.edges[e, 0]], walk.xy[walk.edges[e, 1]]
            u = pb - pa
            f = np.clip(np.sum((self.xy[jay] - pa) * u, axis=1) / np.sum(u * u, axis=1), 0.0, 1.0)
            target = pa + f[:, None] * u
            go = self._crossing_clear(self.xy[jay], target, self.speed[jay], actors)
            jay, e, target = jay[go], e[go], target[go]
            self.back[jay] = self.xy[jay]
            self.target[jay] = target
            self.dest[jay], self.edge[jay] = -1, e
            self.on_road[jay] = True
        # at a kerb: step onto the crosswalk once it is clear
        self.steps += 1
        kerb = np.flatnonzero(self.kerb) if self.steps % LOOK_EVERY == 0 else np.zeros(0, dtype=np.int64)
        if len(kerb):
            clear = self._crossing_clear(self.xy[kerb], self.target[kerb], self.speed[kerb], actors)
            go = kerb[clear]
            self.kerb[go] = False
            self.on_road[go] = True
            self.stopped[go] = 0.0
            self.stopped[kerb[~clear]] += LOOK_EVERY * dt
            for i in kerb[~clear][self.stopped[kerb[~clear]] >= KERB_GIVE_UP_S].tolist():
                here = int(self.prev[i])  # the kerb's node; walk on along another edge instead
                options = [k for k in walk.neighbours[here] if k != int(self.dest[i])] or walk.neighbours[here]
                nxt = options[int(rng.integers(len(options)))]
                self.dest[i], self.edge[i] = nxt, walk.edge_of[(here, nxt)]
                self.target[i] = walk.xy[nxt]
                self.kerb[i] = bool(self.is_crosswalk[self.edge[i]])
                self.stopped[i] = 0.0
        d = self.target - self.xy
        dist = np.hypot(d[:, 0], d[:, 1])
        stride = self.speed * dt
        arrived = (dist <= stride) & ~self.kerb
        moving = ~arrived & (dist > 0) & ~self.kerb
        step = np.zeros_like(d)
        step[moving] = d[moving] * (stride[moving] / dist[moving])[:, None]
        # on the road: do not step into a vehicle (nor the ego)
        road = np.flatnonzero(self.on_road & (moving | arrived))
        if len(road) and len(actors):
            ahead_xy = self.xy[road] + np.where(arrived[road, None], d[road], step[road])
            gx, gy = actors[:, 0, None] - self.xy[None, road, 0], actors[:, 1, None] - self.xy[None, road, 1]
            close = actors[np.any(np.hypot(gx, gy) < 6.0, axis=1), :5]  # a stride from touching, at most
            now_d = self._box_distance(self.xy[road], close)
            nxt_d = self._box_distance(ahead_xy, close)
            into = np.any((nxt_d < CONTACT) & (nxt_d < now_d), axis=1)
            held = road[into]
            moving[held] = False
            arrived[held] = False
            self.stopped[held] += dt
            self.stopped[road[~into]] = 0.0
            for i in held[self.stopped[held] >= GIVE_UP_S].tolist():
                self._turn_back(i)
        self.v = np.where(moving | arrived, self.speed, 0.0)
        self.xy[moving] += step[moving]
        self.yaw[moving] = np.arctan2(d[moving, 1], d[moving, 0])
        for i in np.flatnonzero(arrived).tolist():
            self.xy[i] = self.target[i]
            self.stopped[i] = 0.0
            if self.dest[i] < 0:  # finished jaywalking: walk on along the twin edge, either way
                a, b = walk.edges[int(self.edge[i])]
                nxt, prev = (int(b), int(a)) if rng.random() < 0.5 else (int(a), int(b))
                self.dest[i], self.prev[i] = nxt, prev
                self.on_road[i] = False
            else:
                here = int(self.dest[i])
                options = [k for k in walk.neighbours[here] if k != int(self.prev[i])] or walk.neighbours[here]
                nxt = options[int(rng.integers(len(options)))]
                self.prev[i], self.dest[i] = here, nxt
                self.edge[i] = walk.edge_of[(here, nxt)]
                self.on_road[i] = False
                self.kerb[i] = bool(self.is_crosswalk[self.edge[i]])  # step onto it next step, once clear
            self.target[i] = walk.xy[int(self.dest[i])]
