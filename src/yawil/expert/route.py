"""The route as the expert reads it, computed once per episode: arc lengths, curvature, junction spans,
projection with a hint (`RouteCache`), and a stretch of it to project many agents at once (`Corridor`)."""

from __future__ import annotations

import math

import numpy as np

from yawil.sim.types import RoadOption, Route


class RouteCache:
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
