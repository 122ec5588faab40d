"""yawil.sim.route_geometry: the one route-geometry object gives, to the last bit, what each of its users
computed before it moved there (the formulas as they were, copied here), on curved, noisy and looping routes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.sim.route_geometry import RouteGeometry, arc_lengths


def _routes() -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 1.5 * math.pi, 120)
    arc = np.column_stack((30.0 * np.cos(t), 30.0 * np.sin(t)))  # crosses the +-pi seam of the heading
    straight_turn = np.concatenate([np.column_stack((np.arange(0.0, 50.0), np.zeros(50))),
                                    np.column_stack((np.full(30, 49.0), np.arange(1.0, 31.0)))])
    noisy = np.cumsum(rng.normal(0.0, 1.0, (200, 2)) + np.array([1.0, 0.2]), axis=0)
    dup = np.repeat(straight_turn, 2, axis=0)[:-1]  # zero-length segments
    return [arc, straight_turn, noisy, dup]


def _old_collect_curvature(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # data/collect.py before
    seg = np.diff(xy, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    h = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
    h = np.concatenate([h, h[-1:]])
    lo = np.searchsorted(s, s - 2.5)
    hi = np.minimum(np.searchsorted(s, s + 2.5, side="right") - 1, len(s) - 1)
    ds = np.maximum(s[hi] - s[lo], 1e-6)
    return s, np.where(hi > lo, np.abs(h[hi] - h[lo]) / ds, 0.0)


def _old_expert_geometry(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # expert RouteCache before
    seg = np.diff(xy, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg_len)])
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    mid = 0.5 * (s[:-1] + s[1:])
    lo = np.searchsorted(mid, mid - 2.5, side="left")
    hi = np.minimum(np.searchsorted(mid, mid + 2.5, side="right") - 1, len(mid) - 1)
    unwrapped = np.unwrap(heading)
    k = np.where(hi > lo, np.abs(unwrapped[hi] - unwrapped[lo]) / np.maximum(mid[hi] - mid[lo], 1e-6), 0.0)
    return np.maximum(seg_len, 1e-9), s, heading, k


def _old_guidance_arc_lengths(route: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # guidance._arc_lengths before
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    return seg, np.concatenate(([0.0], np.cumsum(seg)))


@pytest.mark.parametrize("index", range(4))
def test_same_bits_as_the_formulas_it_replaced(index: int) -> None:
    xy = _routes()[index]
    geo = RouteGeometry(xy)
    s, curv = _old_collect_curvature(xy)
    assert np.array_equal(geo.s, s) and np.array_equal(geo.waypoint_curvature(2.5), curv)
    seg_len, s2, heading, k = _old_expert_geometry(xy)
    assert np.array_equal(geo.seg_len, seg_len) and np.array_equal(geo.s, s2)
    assert np.array_equal(geo.heading, heading) and np.array_equal(geo.segment_curvature(2.5), k)
    for a, b in zip(arc_lengths(xy), _old_guidance_arc_lengths(xy), strict=True):
        assert np.array_equal(a, b)


def test_projection_point_and_window() -> None:
    xy = _routes()[1]  # east along y = 0 for 49 m, then north along x = 49
    geo = RouteGeometry(xy)
    i, s, lat = geo.project(np.array([10.3, 0.5]), hint=8)
    assert i == 10 and s == pytest.approx(10.3) and lat == pytest.approx(0.5)  # left of the route: positive
    i, s, lat = geo.project(np.array([48.0, 20.0]), hint=60)
    assert i == 68 and s == pytest.approx(69.0) and lat == pytest.approx(1.0)
    _, s, lat = geo.project(np.array([-4.0, -1.0]), hint=0)  # before the start: extrapolated
    assert s == pytest.approx(-4.0) and lat == pytest.approx(-1.0)
    assert np.allclose(geo.point_at(10.25), [10.25, 0.0]) and np.allclose(geo.point_at(-3.0), [0.0, 0.0])
    assert np.allclose(geo.point_at(geo.s[-1] + 2.0), [49.0, 32.0])  # past the end: straight on
    lo, hi = geo.window(10.5, 12.5)
    assert (lo, hi) == (10, 14) and geo.s[lo] <= 10.5 and geo.s[hi] >= 12.5
    with pytest.raises(ValueError, match="N >= 2"):
        RouteGeometry(np.zeros((1, 2)))
