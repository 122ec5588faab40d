"""The route as the expert reads it, computed once per episode: its geometry (`yawil.sim.route_geometry`) with a
tail past the goal, curvature and junction spans (`RouteCache`), and a stretch of it to project many agents at
once (`Corridor`)."""

from __future__ import annotations

import math

import numpy as np

from yawil.sim.route_geometry import RouteGeometry
from yawil.sim.types import RoadOption, Route


class RouteCache(RouteGeometry):
    """The route's geometry (`RouteGeometry`: arc lengths, headings, projection with a hint, point at s) with a
    straight tail past the goal, plus what the expert reads from it: segment curvature and junction spans.
    Computed once per episode."""

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
        super().__init__(np.vstack([xy, tail]))  # heading: (N-1+TAIL,)
        self.length = float(self.s[-1 - len(tail)])  # the route's, without the tail
        self.curvature = self.segment_curvature(window=2.5)
        self.options = np.asarray(route.options, dtype=np.int64)
        self.junctions = self._junction_spans()

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


class Corridor:
    """The route between two arc lengths, onto which agents' (predicted) positions are projected."""

    def __init__(self, rc: RouteCache, s0: float, s1: float, stride: int = 1) -> None:
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
