"""Route geometry: one object for what every reader of a route polyline computes from it, computed once.

`RouteGeometry(xy)` holds a route's segments, their lengths, the arc length of each waypoint, the heading of
each segment, and answers curvature, projection with a hint, the point at an arc length and the segment window
of an arc-length range. The expert (`yawil.expert.route.RouteCache`, a RouteGeometry of the route plus a
straight tail past the goal), the collector's frame keeper (`waypoint_curvature`), guidance and the gym
wrapper's route drawing (`arc_lengths`) use it.

The arithmetic is each user's own as it was written before it moved here (the order of operations is kept, so
collected data and benchmark records stay bit-identical): two curvatures, of segments (the expert's) and of
waypoints (the collector's), since they answer different questions on different grids.
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np


def arc_lengths(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(length of each segment, arc length at each waypoint from 0) of an (N, 2) polyline."""
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    return seg, np.concatenate(([0.0], np.cumsum(seg)))


class RouteGeometry:
    """Arc lengths, headings, curvature, projection and points of one route polyline (N >= 2 points).

    Attributes: `xy` (N, 2) float64, `seg_len` (N-1,) segment lengths floored at 1e-9 (to divide by),
    `s` (N,) arc length of each waypoint, `heading` (N-1,) of each segment.
    """

    def __init__(self, xy: np.ndarray) -> None:
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 2 or not np.all(np.isfinite(xy)):
            raise ValueError(f"route.xy must be a finite (N, 2) array with N >= 2, got shape {xy.shape}")
        self.xy = xy
        seg = np.diff(xy, axis=0)
        raw_len, self.s = arc_lengths(xy)
        self.seg_len = np.maximum(raw_len, 1e-9)
        self.heading = np.arctan2(seg[:, 1], seg[:, 0])

    @cached_property
    def unwrapped_heading(self) -> np.ndarray:
        """Segment headings without jumps of 2 pi (differences along the route are turns)."""
        return np.asarray(np.unwrap(self.heading), dtype=np.float64)

    def segment_curvature(self, window: float) -> np.ndarray:
        """|dheading/ds| at each segment, over +-window metres of segment midpoints (smooths the 1 m sampling)."""
        mid = 0.5 * (self.s[:-1] + self.s[1:])
        lo = np.searchsorted(mid, mid - window, side="left")
        hi = np.minimum(np.searchsorted(mid, mid + window, side="right") - 1, len(mid) - 1)
        unwrapped = self.unwrapped_heading
        dh = np.abs(unwrapped[hi] - unwrapped[lo])
        ds = np.maximum(mid[hi] - mid[lo], 1e-6)
        k = np.where(hi > lo, dh / ds, 0.0)
        return np.asarray(k, dtype=np.float64)

    def waypoint_curvature(self, window: float) -> np.ndarray:
        """|dheading/ds| at each waypoint, over +-window metres of waypoints (the last waypoint takes the last
        segment's heading)."""
        s = self.s
        h = np.concatenate([self.unwrapped_heading, self.unwrapped_heading[-1:]])
        lo = np.searchsorted(s, s - window)
        hi = np.minimum(np.searchsorted(s, s + window, side="right") - 1, len(s) - 1)
        ds = np.maximum(s[hi] - s[lo], 1e-6)
        return np.asarray(np.where(hi > lo, np.abs(h[hi] - h[lo]) / ds, 0.0), dtype=np.float64)

    def project(self, p: np.ndarray, hint: int, back: int = 5, ahead: int = 40) -> tuple[int, float, float]:
        """(segment, arc length, signed lateral offset, left positive) of point p, searching the segments from
        `back` before to `ahead` after the hinted one; before the start and past the end, the end segments are
        extrapolated."""
        nseg = len(self.heading)
        lo = min(max(hint - back, 0), nseg - 1)
        hi = min(max(hint + ahead, lo + 1), nseg)
        a = self.xy[lo:hi]
        d = self.xy[lo + 1 : hi + 1] - a
        t = np.einsum("ij,ij->i", p - a, d) / (self.seg_len[lo:hi] ** 2)
        lower = np.zeros_like(t)
        upper = np.ones_like(t)
        if lo == 0:
            lower[0] = -np.inf
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
        """The route point at arc length s; before the start, the start; past the end, extrapolated straight."""
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
