"""Tests of yawil.guidance: invariance of yaw guidance, signs, wrapping, resampling, noise, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from yawil.guidance import (
    DEFAULT_COUNT,
    DEFAULT_SPACING,
    GUIDANCE_KINDS,
    CommandNoise,
    Guidance,
    GuidanceConfig,
    compute_guidance,
    interpolate_lane_yaw,
    project_on_route,
    resample_route,
    route_headings,
    sim_yaw_guidance,
    xy_guidance,
    yaw_guidance,
)
from yawil.sim.types import RoadOption, wrap_angle

BOUNDS = (-1000.0, -1000.0, 1000.0, 1000.0)
ATOL = 2e-4  # float32 output, float64 maths


def angle_close(a: np.ndarray, b: np.ndarray, atol: float = ATOL) -> bool:
    """Angles equal up to wrapping: a value near +pi and one near -pi are the same heading."""
    return bool(np.all(np.abs(wrap_angle(np.asarray(a, np.float64) - np.asarray(b, np.float64))) < atol))


def rotate(xy: np.ndarray, theta: float, offset: np.ndarray) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return xy @ np.array([[c, s], [-s, c]]) + offset


def turn_route(sign: float = 1.0, radius: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """East-bound road, a 90 degree arc (left for sign=+1), then a straight; about 1 m between waypoints."""
    straight_in = np.column_stack((np.arange(0.0, 20.0), np.zeros(20)))
    th = np.linspace(0.0, math.pi / 2, 17)[1:]
    arc = np.column_stack((20.0 + radius * np.sin(th), radius * (1.0 - np.cos(th))))
    straight_out = np.column_stack((np.full(20, 20.0 + radius), radius + np.arange(1.0, 21.0)))
    xy = np.vstack((straight_in, arc, straight_out))
    lane = np.concatenate((np.zeros(20), th, np.full(20, math.pi / 2)))
    xy[:, 1] *= sign
    return xy, lane * sign


# ------------------------------------------------------------------------------------------ invariance
@st.composite
def random_routes(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, int, float, float]:
    """Gently curving random polyline with its lane headings, and where on it the ego stands."""
    n = draw(st.integers(min_value=8, max_value=40))
    turns = np.array(draw(st.lists(st.floats(-0.5, 0.5), min_size=n - 1, max_size=n - 1)))
    lengths = np.array(draw(st.lists(st.floats(0.5, 4.0), min_size=n - 1, max_size=n - 1)))
    heading0 = draw(st.floats(-math.pi, math.pi))
    headings = heading0 + np.cumsum(turns)
    steps = lengths[:, None] * np.column_stack((np.cos(headings), np.sin(headings)))
    xy = np.vstack(([0.0, 0.0], np.cumsum(steps, axis=0)))
    lane = wrap_angle(np.concatenate((headings[:1], headings)))
    seg = draw(st.integers(0, n - 2))
    t = draw(st.floats(0.0, 1.0))
    lateral = draw(st.floats(-0.2, 0.2))
    return xy, lane, seg, t, lateral


@settings(max_examples=100, deadline=None, derandomize=True, database=None)
@given(
    route=random_routes(),
    theta=st.floats(-math.pi, math.pi),
    dx=st.floats(-400.0, 400.0),
    dy=st.floats(-400.0, 400.0),
    reference=st.sampled_from(["route", "ego"]),
    ego_dyaw=st.floats(-0.3, 0.3),
)
def test_yaw_and_sim_yaw_invariant_under_rigid_motion(
    route: tuple[np.ndarray, np.ndarray, int, float, float],
    theta: float,
    dx: float,
    dy: float,
    reference: str,
    ego_dyaw: float,
) -> None:
    xy, lane, seg, t, lateral = route
    a, b = xy[seg], xy[seg + 1]
    direction = (b - a) / np.linalg.norm(b - a)
    ego = a + t * (b - a) + lateral * np.array([-direction[1], direction[0]])
    ego_yaw = math.atan2(direction[1], direction[0]) + ego_dyaw
    cfg = GuidanceConfig(reference=reference)
    g1, i1 = compute_guidance(xy, lane, ego, ego_yaw, BOUNDS, cfg, hint_index=seg)

    offset = np.array([dx, dy])
    xy2 = rotate(xy, theta, offset)
    ego2 = rotate(ego[None, :], theta, offset)[0]
    g2, i2 = compute_guidance(
        xy2, wrap_angle(lane + theta), ego2, float(wrap_angle(ego_yaw + theta)), BOUNDS, cfg, hint_index=seg
    )
    assert angle_close(g1.yaw, g2.yaw)
    assert angle_close(g1.sim_yaw, g2.sim_yaw)


def test_xy_guidance_changes_under_translation() -> None:
    xy, lane = turn_route()
    g1, _ = compute_guidance(xy, lane, [5.0, 0.0], 0.0, BOUNDS)
    g2, _ = compute_guidance(xy + [100.0, -50.0], lane, [105.0, -50.0], 0.0, BOUNDS)
    assert np.allclose(g1.yaw, g2.yaw, atol=ATOL)
    assert not np.allclose(g1.xy, g2.xy, atol=1e-3)
    assert np.allclose(g2.xy[0::2] - g1.xy[0::2], 0.1, atol=1e-5)  # 100 m of a 2000 m wide map
    assert np.allclose(g2.xy[1::2] - g1.xy[1::2], -0.05, atol=1e-5)


# ------------------------------------------------------------------------------------- signs and wraps
def test_left_turn_positive_right_turn_mirror() -> None:
    left_xy, left_lane = turn_route(+1.0)
    right_xy, right_lane = turn_route(-1.0)
    for ref in ("route", "ego"):
        cfg = GuidanceConfig(reference=ref)
        gl, _ = compute_guidance(left_xy, left_lane, [12.0, 0.0], 0.0, BOUNDS, cfg)
        gr, _ = compute_guidance(right_xy, right_lane, [12.0, 0.0], 0.0, BOUNDS, cfg)
        for kind in ("yaw", "sim_yaw"):
            left, right = gl.get(kind), gr.get(kind)
            assert left[-1] == pytest.approx(math.pi / 2, abs=1e-3), kind
            assert np.all(left >= -1e-6) and left.max() > 1.0, kind
            assert np.allclose(left, -right, atol=1e-5), kind


@pytest.mark.parametrize("heading", [0.0, 0.7, math.pi / 2, -2.5, math.pi, -math.pi, math.pi - 1e-9])
def test_straight_route_gives_zeros(heading: float) -> None:
    d = np.array([math.cos(heading), math.sin(heading)])
    xy = np.array([30.0, -20.0]) + np.arange(40.0)[:, None] * d
    lane = np.full(40, heading)
    for ref in ("route", "ego"):
        g, _ = compute_guidance(xy, lane, xy[3] + 0.4 * d, heading, BOUNDS, GuidanceConfig(reference=ref))
        assert angle_close(g.yaw, np.zeros(DEFAULT_COUNT), atol=1e-6)
        assert np.all(np.abs(g.yaw) < 1e-6) and np.all(np.abs(g.sim_yaw) < 1e-6)


def test_exact_west_heading_with_signed_zero() -> None:
    """atan2 gives +pi or -pi for a westward step depending on the sign of a zero dy: both mean 'straight'."""
    pts = np.array([[0.0, 0.0], [-1.0, 0.0], [-2.0, -0.0], [-3.0, 0.0]])
    pts[2, 1] = -0.0
    headings = route_headings(pts)
    assert np.all(np.abs(np.abs(headings) - math.pi) < 1e-12)
    assert np.all(yaw_guidance(pts) == 0.0)


def test_wrap_across_pi_west_with_slight_left_bend() -> None:
    bend = 0.1  # west-bound, bending left (CCW): heading goes pi -> pi + 0.1, which wraps to -pi + 0.1
    headings = np.concatenate((np.full(5, math.pi), np.full(15, math.pi + bend)))
    steps = 2.0 * np.column_stack((np.cos(headings), np.sin(headings)))
    pts = np.vstack(([0.0, 0.0], np.cumsum(steps, axis=0)))[:16]
    g = yaw_guidance(pts)
    assert np.all(np.abs(g) < 0.2)
    assert g[-1] == pytest.approx(bend, abs=1e-6)
    assert np.allclose(sim_yaw_guidance(wrap_angle(headings[:15])), g, atol=1e-6)


def test_wrap_angle_range_and_values() -> None:
    a = np.array([math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 2 * math.pi, 0.5, -0.5, 7.0, -7.0])
    w = wrap_angle(a)
    assert isinstance(w, np.ndarray) and w.dtype == np.float64
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    assert w[0] == w[1] == w[2] == w[3] == pytest.approx(math.pi)
    assert w[4] == pytest.approx(0.0)
    assert np.allclose(np.cos(w), np.cos(a)) and np.allclose(np.sin(w), np.sin(a))
    # a scalar (float, int or numpy scalar) gives a float in the same range, equal to the array's to rounding
    for x in (*a.tolist(), np.float64(7.0), np.float32(-7.0), 4):
        v = wrap_angle(x)
        assert type(v) is float and -math.pi < v <= math.pi
        assert v == pytest.approx(float(wrap_angle([float(x)])[0]), abs=1e-12)
    assert wrap_angle([-math.pi])[0] == math.pi and wrap_angle(-math.pi) == math.pi


# -------------------------------------------------------------------------------------------- resampling
def test_resample_respects_spacing_on_irregular_waypoints() -> None:
    x = np.cumsum(np.array([0.0, 0.3, 2.7, 1.0, 0.0, 5.0, 0.25, 3.75, 7.0]))  # includes a duplicate point
    xy = np.column_stack((x, 2.0 * x)) / math.sqrt(5.0)
    pts = resample_route(xy, 1.1, 2.0, 5)
    assert np.allclose(np.linalg.norm(np.diff(pts, axis=0), axis=1), 2.0)
    assert np.allclose(pts[0], xy[0] + 1.1 * np.array([1.0, 2.0]) / math.sqrt(5.0))


def test_resample_pads_along_last_segment() -> None:
    xy, _ = turn_route()  # ends going north at (30, 30)
    end_s = project_on_route(xy, xy[-1])[1]
    pts = resample_route(xy, end_s - 3.0, DEFAULT_SPACING, DEFAULT_COUNT + 1)
    assert pts[-1] == pytest.approx([30.0, 30.0 - 3.0 + DEFAULT_SPACING * DEFAULT_COUNT])
    assert np.allclose(route_headings(pts), math.pi / 2)
    g, index = compute_guidance(xy, np.zeros(len(xy)), xy[-1] + [0.0, 5.0], math.pi / 2, BOUNDS)
    assert index == len(xy) - 2
    assert np.allclose(g.yaw, 0.0)


def test_projection_with_hint_on_route_that_loops() -> None:
    """A lollipop: out along +x, left turn into a square loop driven clockwise, back over the first stretch."""
    out = np.column_stack((np.arange(0.0, 21.0), np.zeros(21)))
    loop = np.array([[20.0, 0.0], [20.0, 20.0], [40.0, 20.0], [40.0, 0.0], [20.0, 0.0]])
    dense = [np.linspace(a, b, 21)[1:] for a, b in zip(loop[:-1], loop[1:], strict=True)]
    back = np.column_stack((np.arange(19.0, -1.0, -1.0), np.zeros(20)))
    xy = np.vstack([out, *dense, back])
    ego = np.array([10.2, 0.1])
    first, s_first = project_on_route(xy, ego)
    assert first == 10 and s_first == pytest.approx(10.2)
    late = len(xy) - 11
    second, s_second = project_on_route(xy, ego, hint_index=late)
    assert abs(second - late) <= 1 and s_second == pytest.approx(20.0 + 80.0 + 9.8)
    g_out, _ = compute_guidance(xy, np.zeros(len(xy)), ego, 0.0, BOUNDS, hint_index=first)
    g_back, _ = compute_guidance(xy, np.zeros(len(xy)), ego, math.pi, BOUNDS, hint_index=late)
    assert np.allclose(g_back.yaw, 0.0) and g_out.yaw.max() > 1.0  # out leg reaches the left turn


@pytest.mark.parametrize("step", [0.1, 1.0, 7.0])
def test_compute_guidance_matches_the_building_blocks_on_the_whole_route(step: float) -> None:
    """compute_guidance works on a slice ahead of the ego; it must equal the same maths on the full route."""
    th = np.arange(0.0, 400.0, step) / 25.0
    xy = np.column_stack((25.0 * np.sin(th), 25.0 * (1.0 - np.cos(th))))  # circles, driven many times
    xy = np.vstack((xy[:40], xy[39:40], xy[40:]))  # a duplicate waypoint on the way
    lane = wrap_angle(np.concatenate((th[:40], th[39:40], th[40:])))
    cfg = GuidanceConfig(spacing=1.7, count=12)
    for hint in (5, len(xy) // 2, len(xy) - 3):
        ego = xy[hint] + [0.05, -0.05]
        g, index = compute_guidance(xy, lane, ego, 0.3, BOUNDS, cfg, hint_index=hint)
        _, s = project_on_route(xy, ego, hint_index=hint)
        pts = resample_route(xy, s, cfg.spacing, cfg.count + 1)
        lane_k = interpolate_lane_yaw(xy, lane, s + cfg.spacing * np.arange(cfg.count))
        assert abs(index - hint) <= 1
        assert angle_close(g.yaw, yaw_guidance(pts), atol=1e-5)
        assert np.allclose(g.xy, xy_guidance(pts[:-1], BOUNDS), atol=1e-6)
        assert angle_close(g.sim_yaw, sim_yaw_guidance(lane_k), atol=1e-5)


def test_compute_guidance_past_duplicated_final_waypoints() -> None:
    """Guidance starts at the ego's projection, clamped to the route end, then pads straight on."""
    xy = np.array([[0.0, 0.0], [0.0, 5.0], [0.0, 10.0], [0.0, 10.0], [0.0, 10.0]])
    g, index = compute_guidance(xy, np.full(5, math.pi / 2), [0.0, 12.0], math.pi / 2, BOUNDS, hint_index=4)
    assert index == 1 and np.all(g.yaw == 0.0)
    assert g.xy[1] == pytest.approx(0.01) and g.xy[-1] == pytest.approx((10.0 + 2.0 * 14) / 1000.0)
    # So many trailing duplicates that the hint window sees only zero-length segments.
    xy = np.vstack((xy[:3], np.repeat(xy[2:3], 80, axis=0)))
    g2, index2 = compute_guidance(xy, np.full(len(xy), 1.0), [0.0, 12.0], 0.0, BOUNDS, hint_index=len(xy) - 1)
    assert index2 > 2 and np.array_equal(g2.xy, g.xy) and np.array_equal(g2.yaw, g.yaw)


def test_interpolate_lane_yaw_is_circular() -> None:
    xy = np.column_stack((np.arange(3.0), np.zeros(3)))
    lane = np.array([math.pi - 0.1, -math.pi + 0.1, -math.pi + 0.1])
    mid = interpolate_lane_yaw(xy, lane, [0.5, 10.0])
    assert abs(mid[0]) == pytest.approx(math.pi, abs=1e-9)  # not 0, the naive linear average
    assert mid[1] == pytest.approx(-math.pi + 0.1)


def test_compute_guidance_shapes_noise_and_determinism() -> None:
    xy, lane = turn_route()
    cfg = GuidanceConfig(spacing=1.5, count=7)
    g, _ = compute_guidance(xy, lane, [3.0, 0.0], 0.0, BOUNDS, cfg)
    assert {k: g.get(k).shape[0] for k in GUIDANCE_KINDS} == cfg.dims()
    assert all(g.get(k).dtype == np.float32 for k in GUIDANCE_KINDS)
    assert np.all(np.abs(g.xy) <= 1.0)
    runs = [
        compute_guidance(
            xy, lane, [3.0, 0.0], 0.0, BOUNDS, cfg, yaw_noise_deg=20.0, rng=np.random.default_rng(7)
        )[0]
        for _ in range(2)
    ]
    assert all(np.array_equal(runs[0].get(k), runs[1].get(k)) for k in GUIDANCE_KINDS)
    assert not np.allclose(runs[0].yaw, g.yaw, atol=1e-3)
    assert runs[0].yaw[0] == 0.0  # route reference: the noise on the first heading cancels
    assert np.array_equal(runs[0].xy, g.xy)  # noise is on headings only
    with pytest.raises(ValueError):
        runs[0].yaw[0] = 1.0  # read-only


def test_yaw_noise_readings_raw_and_independent() -> None:
    """Table II's two readings: raw noise on the headings (y[0] stays 0, the rest get sqrt(2) sigma,
    correlated) against independent N(0, sigma^2) on each component after the subtraction."""
    xy = np.column_stack((np.arange(0.0, 60.0), np.zeros(60)))
    lane = np.zeros(60)
    cfg = GuidanceConfig(spacing=1.5, count=7)
    sigma = 10.0

    def draw(mode: str) -> np.ndarray:
        rng = np.random.default_rng(3)
        return np.stack([compute_guidance(xy, lane, [3.0, 0.0], 0.0, BOUNDS, cfg, yaw_noise_deg=sigma, rng=rng,
                                          yaw_noise_mode=mode)[0].yaw for _ in range(4000)])

    raw, ind = np.rad2deg(draw("raw")), np.rad2deg(draw("independent"))
    assert np.all(raw[:, 0] == 0.0) and np.std(raw[:, 1:]) == pytest.approx(sigma * math.sqrt(2), rel=0.05)
    assert np.corrcoef(raw[:, 1], raw[:, 2])[0, 1] == pytest.approx(0.5, abs=0.05)  # the shared first heading
    assert np.std(ind, axis=0) == pytest.approx(np.full(7, sigma), rel=0.06)
    assert abs(np.corrcoef(ind[:, 1], ind[:, 2])[0, 1]) < 0.05
    with pytest.raises(ValueError, match="yaw_noise_mode 'both'"):
        compute_guidance(xy, lane, [3.0, 0.0], 0.0, BOUNDS, cfg, yaw_noise_deg=sigma, rng=np.random.default_rng(0),
                         yaw_noise_mode="both")


def test_config_round_trip_and_validation() -> None:
    cfg = GuidanceConfig(spacing=3, count=10, reference="ego")
    assert GuidanceConfig.from_dict(cfg.to_dict()) == cfg and isinstance(cfg.spacing, float)
    assert GuidanceConfig.from_dict({}) == GuidanceConfig()
    assert GuidanceConfig().dims() == {"yaw": 15, "xy": 30, "sim_yaw": 15}


# ---------------------------------------------------------------------------------------- command noise
def run_noise(seed: int, p: float, commands: list[int]) -> tuple[list[int], list[bool]]:
    noise = CommandNoise(p, np.random.default_rng(seed))
    out, flags = [], []
    for c in commands:
        out.append(noise(c))
        flags.append(noise.active)
    return out, flags


def test_command_noise_deterministic_and_never_true_while_active() -> None:
    rng = np.random.default_rng(0)
    values = [int(v) for v in RoadOption if v is not RoadOption.VOID]
    commands = [values[i] for i in rng.integers(0, 4, 3000)]  # the true command changes often
    a, flags = run_noise(11, 0.1, commands)
    b, _ = run_noise(11, 0.1, commands)
    assert a == b
    assert a != run_noise(12, 0.1, commands)[0]
    for true, given_, noisy in zip(commands, a, flags, strict=True):
        assert (given_ != true) == noisy
        assert given_ in values


@pytest.mark.parametrize("p", [0.03, 0.05, 0.1])
def test_command_noise_rate_and_burst_length(p: float) -> None:
    n = 40000
    out, flags = run_noise(3, p, [int(RoadOption.LANEFOLLOW)] * n)
    rate = float(np.mean(flags))
    expected = p * 5 / (p * 5 + 1 - p)  # bursts do not overlap; about p*5 for small p
    assert rate == pytest.approx(expected, rel=0.1)
    assert rate == pytest.approx(p * 5, rel=0.35)
    # Runs of noisy frames are whole bursts: multiples of 5, each burst exactly 5 frames of one wrong command.
    padded = np.concatenate(([False], flags, [False])).astype(np.int8)
    starts, ends = np.flatnonzero(np.diff(padded) == 1), np.flatnonzero(np.diff(padded) == -1)
    if ends[-1] == n:  # a burst cut short by the end of the sequence
        starts, ends = starts[:-1], ends[:-1]
    assert len(starts) > 50 and np.all((ends - starts) % 5 == 0)
    bursts = np.concatenate([np.arange(s, e, 5) for s, e in zip(starts, ends, strict=True)])
    assert all(len(set(out[s : s + 5])) == 1 for s in bursts)


@pytest.mark.parametrize("p", [0.03, 0.05, 0.1])
def test_command_noise_frame_share_reading(p: float) -> None:
    """frame-share: p is the long-run share of wrong-command frames, still in bursts of 5."""
    noise = CommandNoise(p, np.random.default_rng(4), mode="frame-share")
    flags = []
    for _ in range(60000):
        noise(int(RoadOption.LANEFOLLOW))
        flags.append(noise.active)
    assert noise.share == pytest.approx(p) and float(np.mean(flags)) == pytest.approx(p, rel=0.1)
    assert CommandNoise(p, np.random.default_rng(0)).share == pytest.approx(p * 5 / (p * 5 + 1 - p))
    with pytest.raises(ValueError, match="command noise mode"):
        CommandNoise(p, np.random.default_rng(0), mode="share")


def test_command_noise_void_counts_as_lanefollow() -> None:
    out, flags = run_noise(5, 1.0, [int(RoadOption.VOID)] * 20)
    assert all(flags) and int(RoadOption.LANEFOLLOW) not in out and -1 not in out


# --------------------------------------------------------------------------------------------- bad input
GOOD = turn_route()[0]


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda: project_on_route(GOOD[:1], [0.0, 0.0]),
            r"route_xy must have shape \(N, 2\) with N >= 2, got \(1, 2\)",
        ),
        (lambda: project_on_route(np.zeros((5, 3)), [0.0, 0.0]), r"route_xy must have shape .* got \(5, 3\)"),
        (lambda: project_on_route(np.zeros(10), [0.0, 0.0]), r"route_xy must have shape"),
        (
            lambda: project_on_route(
                np.where(np.arange(2 * len(GOOD)).reshape(-1, 2) == 7, np.nan, GOOD), [0, 0]
            ),
            "route_xy must be finite",
        ),
        (lambda: project_on_route(GOOD, [0.0, np.inf]), "point_xy must be finite"),
        (lambda: project_on_route(GOOD, [0.0, 1.0, 2.0]), r"point_xy must have shape \(2,\)"),
        (lambda: project_on_route(GOOD, [0.0, 0.0], hint_index=len(GOOD)), "hint_index"),
        (lambda: project_on_route(GOOD, [0.0, 0.0], hint_index=0, window=0), "window"),
        (lambda: resample_route(GOOD, 0.0, 0.0, 5), "spacing must be > 0"),
        (lambda: resample_route(GOOD, 0.0, -1.0, 5), "spacing must be > 0"),
        (lambda: resample_route(GOOD, 0.0, 2.0, 0), "n_points must be a positive integer"),
        (lambda: resample_route(GOOD, float("nan"), 2.0, 5), "start_s must be a finite number"),
        (lambda: resample_route(np.ones((4, 2)), 0.0, 2.0, 5), "route_xy has zero length"),
        (lambda: route_headings([[0.0, 0.0]]), r"points must have shape \(N, 2\) with N >= 2"),
        (lambda: yaw_guidance(GOOD[:5], yaw_noise=np.zeros(3)), r"yaw_noise must have shape \(4,\)"),
        (lambda: yaw_guidance(GOOD[:5], reference_yaw=float("inf")), "reference_yaw must be a finite number"),
        (lambda: xy_guidance(GOOD[:5], (0.0, 0.0, 0.0, 10.0)), "xmax > xmin"),
        (lambda: xy_guidance(GOOD[:5], (0.0, 5.0, 10.0, 5.0)), "ymax > ymin"),
        (lambda: xy_guidance(GOOD[:5], (0.0, 0.0, 10.0)), "bounds must be 4 finite numbers"),
        (lambda: xy_guidance(GOOD[:5], (0.0, 0.0, np.nan, 10.0)), "bounds must be 4 finite numbers"),
        (lambda: sim_yaw_guidance([0.0, np.nan]), "lane_yaw must be finite"),
        (lambda: sim_yaw_guidance(np.zeros((2, 2))), "lane_yaw must have shape"),
        (lambda: interpolate_lane_yaw(GOOD, np.zeros(3), [0.0]), r"route_lane_yaw must have shape \(56,\)"),
        (
            lambda: compute_guidance(GOOD, np.zeros(len(GOOD)), [0.0, 0.0], np.nan, BOUNDS),
            "ego_yaw must be a finite",
        ),
        (
            lambda: compute_guidance(GOOD, np.zeros(len(GOOD)), [0.0, 0.0], 0.0, BOUNDS, yaw_noise_deg=10.0),
            "needs rng",
        ),
        (
            lambda: compute_guidance(GOOD, np.zeros(len(GOOD)), [0.0, 0.0], 0.0, BOUNDS, yaw_noise_deg=-1.0),
            "yaw_noise_deg must be >= 0",
        ),
        (
            lambda: compute_guidance(GOOD, np.zeros(len(GOOD)), [0.0, 0.0], 0.0, (5.0, 0.0, 1.0, 9.0)),
            "xmax > xmin",
        ),
        (
            lambda: compute_guidance(GOOD, np.zeros(len(GOOD)), [0.0, 0.0], 0.0, BOUNDS, config={"count": 3}),  # type: ignore[arg-type]
            "config must be a GuidanceConfig",
        ),
        (lambda: GuidanceConfig(spacing=0.0), "GuidanceConfig.spacing must be > 0"),
        (lambda: GuidanceConfig(spacing=float("inf")), "GuidanceConfig.spacing must be a finite number"),
        (lambda: GuidanceConfig(count=0), "GuidanceConfig.count must be a positive integer"),
        (lambda: GuidanceConfig(count=2.5), "GuidanceConfig.count must be a positive integer"),  # type: ignore[arg-type]
        (lambda: GuidanceConfig(reference="north"), "GuidanceConfig.reference must be one of"),
        (lambda: GuidanceConfig.from_dict({"spacing": 2.0, "K": 3}), r"no field\(s\) \['K'\]"),
        (lambda: GuidanceConfig.from_dict([1, 2]), "expects a mapping"),  # type: ignore[arg-type]
        (lambda: Guidance(np.zeros(3), np.zeros(5), np.zeros(3)), "Guidance shapes disagree"),
        (lambda: Guidance(np.zeros(3), np.zeros(6), np.zeros(3)).get("gps"), "guidance kind must be one of"),
        (lambda: CommandNoise(1.5, np.random.default_rng(0)), r"p must be a probability in \[0, 1\]"),
        (lambda: CommandNoise(0.1, 42), "rng must be a numpy Generator"),  # type: ignore[arg-type]
        (lambda: CommandNoise(0.1, np.random.default_rng(0), length=0), "length must be a positive integer"),
        (lambda: CommandNoise(0.1, np.random.default_rng(0))(7), "command must be a RoadOption value"),
    ],
)
def test_bad_input_raises_value_error_naming_it(call: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()  # type: ignore[operator]


def test_defaults() -> None:
    assert (DEFAULT_SPACING, DEFAULT_COUNT) == (2.0, 15)
    assert GuidanceConfig() == GuidanceConfig(DEFAULT_SPACING, DEFAULT_COUNT, "route")
