"""The pedestrians' network: sidewalk centre lines, corners, and crosswalks at junction approaches.

Edges are straight segments. Sidewalk edges along a road know their twin on the other side of the road, so
a jaywalker can cross straight over and walk on.
"""

from __future__ import annotations

import math

import numpy as np

from yawil.sim.town.map.layout import Layout, setback
from yawil.sim.town.map.scenery import bisector_point, corner_curve, node_roads, offset


class Walkways:
    def __init__(self, layout: Layout, node_xy: np.ndarray, degree: np.ndarray, crosswalk_centre: float) -> None:
        self._key: dict[tuple[float, float], int] = {}
        pts: list[tuple[float, float]] = []
        self.edge_list: list[tuple[int, int]] = []
        self.edge_kind: list[str] = []  # "sidewalk" | "crosswalk" | "corner"
        self.edge_twin: list[int] = []
        self._pts = pts
        d = layout.lane_width + layout.sidewalk_width / 2
        S = layout.junction_setback
        # sidewalks along roads
        for a, b in layout.roads:
            pa, pb = node_xy[a], node_xy[b]
            u = (pb - pa) / np.linalg.norm(pb - pa)
            n = np.array([-u[1], u[0]])
            s0 = setback(layout, a) + (crosswalk_centre if degree[a] >= 3 else 0.0)
            s1 = float(np.linalg.norm(pb - pa)) - setback(layout, b) - (crosswalk_centre if degree[b] >= 3 else 0.0)
            left = self._edge(pa + u * s0 + n * d, pa + u * s1 + n * d, "sidewalk")
            right = self._edge(pa + u * s0 - n * d, pa + u * s1 - n * d, "sidewalk")
            self.edge_twin[left], self.edge_twin[right] = right, left
        for node in range(len(node_xy)):
            c = node_xy[node]
            if degree[node] == 2:
                xy, yaw, _, _ = corner_curve(layout, node, n=8)
                for side in (d, -d):
                    p = offset(xy, yaw, side)
                    for i in range(len(p) - 1):
                        self._edge(p[i], p[i + 1], "corner")
                continue
            roads = node_roads(layout, node)
            sc = S + crosswalk_centre
            for k, (_, u1) in enumerate(roads):
                u2 = roads[(k + 1) % len(roads)][1]
                n1, n2 = np.array([-u1[1], u1[0]]), np.array([-u2[1], u2[0]])
                mid = bisector_point(c, u1, u2, d)
                self._edge(c + sc * u1 + d * n1, mid, "corner")
                self._edge(mid, c + sc * u2 - d * n2, "corner")
                self._edge(c + sc * u1 + d * n1, c + sc * u1 - d * n1, "crosswalk")
        self.xy = np.array(pts, dtype=np.float64)
        self.edges = np.array(self.edge_list, dtype=np.int64)
        self.neighbours: list[list[int]] = [[] for _ in range(len(pts))]
        self.edge_of: dict[tuple[int, int], int] = {}
        for e, (i, j) in enumerate(self.edge_list):
            self.neighbours[i].append(j)
            self.neighbours[j].append(i)
            self.edge_of[(i, j)] = self.edge_of[(j, i)] = e

    def _node(self, p: np.ndarray) -> int:
        key = (round(float(p[0]), 2), round(float(p[1]), 2))
        if key not in self._key:
            self._key[key] = len(self._pts)
            self._pts.append((float(p[0]), float(p[1])))
        return self._key[key]

    def _edge(self, p: np.ndarray, q: np.ndarray, kind: str) -> int:
        i, j = self._node(p), self._node(q)
        self.edge_list.append((i, j))
        self.edge_kind.append(kind)
        self.edge_twin.append(-1)
        return len(self.edge_list) - 1

    def edge_length(self, e: int) -> float:
        i, j = self.edge_list[e]
        return float(math.dist(self._pts[i], self._pts[j]))
