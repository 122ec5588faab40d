"""Pedestrians: random walks on the walkway graph, crossing at crosswalks and sometimes anywhere.

They stop for nothing (the expert must stop for them). Jaywalking: while on a sidewalk along a road, each
step a pedestrian may, with a small seeded probability, cross straight over the road to the other sidewalk.
"""

from __future__ import annotations

import numpy as np

from yawil.sim.town.walkways import Walkways

PED_COLORS = ((0.2, 0.2, 0.5), (0.6, 0.1, 0.1), (0.1, 0.4, 0.2), (0.3, 0.3, 0.3), (0.7, 0.6, 0.2), (0.5, 0.3, 0.5))
SIZE = 0.6  # footprint, metres square
HEIGHT = 1.75


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
        self.speed = np.zeros(n)
        self.yaw = np.zeros(n)
        self.on_road = np.zeros(n, dtype=bool)
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
            self.speed[i] = rng.uniform(1.0, 1.6)
            self.color_index[i] = rng.integers(len(PED_COLORS))
            d = walk.xy[b] - walk.xy[a]
            self.yaw[i] = np.arctan2(d[1], d[0])
            placed += 1

    def step(self, dt: float, rng: np.random.Generator) -> None:
        if not self.n:
            return
        walk = self.walk
        # jaywalk: leave a sidewalk edge along a road for the twin on the other side
        draw = rng.random(self.n)
        jay = (draw < self.jaywalk_per_s * dt) & (self.dest >= 0) & (self.twin[self.edge] >= 0)
        for i in np.flatnonzero(jay).tolist():
            e = int(self.twin[self.edge[i]])
            a, b = walk.edges[e]
            pa, pb = walk.xy[a], walk.xy[b]
            u = pb - pa
            f = float(np.clip(np.dot(self.xy[i] - pa, u) / np.dot(u, u), 0.0, 1.0))
            self.target[i] = pa + f * u
            self.dest[i], self.edge[i] = -1, e
            self.on_road[i] = True
        d = self.target - self.xy
        dist = np.hypot(d[:, 0], d[:, 1])
        stride = self.speed * dt
        arrived = dist <= stride
        moving = ~arrived & (dist > 0)
        self.xy[moving] += d[moving] * (stride[moving] / dist[moving])[:, None]
        self.yaw[moving] = np.arctan2(d[moving, 1], d[moving, 0])
        for i in np.flatnonzero(arrived).tolist():
            self.xy[i] = self.target[i]
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
                self.on_road[i] = bool(self.is_crosswalk[self.edge[i]])
            self.target[i] = walk.xy[int(self.dest[i])]
