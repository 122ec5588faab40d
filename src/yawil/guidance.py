"""Route guidance for the driving models: yaw (the paper's idea), XY and simulator-yaw baselines, and noise.

The paper guides the car with the headings of the planned route just ahead of it, taken relative to the
first of them (`y = T_yaw - yaw_1`), so that a left turn looks the same wherever it is on the map. The
baselines feed map coordinates (XY-guided IL) or the lane headings the simulator reports (Carla-yaw IL).
Definitions and conventions: docs/guidance.md. Pure numpy; no simulator and no torch here.

Conventions: map frame x east, y north; yaw in radians counter-clockwise from +x, wrapped to (-pi, pi];
a left turn gives positive guidance values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from yawil.sim.route_geometry import arc_lengths
from yawil.sim.types import RoadOption, wrap_angle

DEFAULT_SPACING = 2.0  # metres between guidance points
DEFAULT_COUNT = 15  # K
GUIDANCE_KINDS: tuple[str, ...] = ("yaw", "xy", "sim_yaw")
REFERENCES: tuple[str, ...] = ("route", "ego")


# --------------------------------------------------------------------------------------------- validation
def _points(name: str, value: ArrayLike, min_n: int = 2, n: int | None = None) -> np.ndarray:
    """Check a polyline early, so a bad route fails here with its name rather than deep in the maths."""
    arr = np.asarray(value, dtype=np.float64)
    wanted = f"N >= {min_n}" if n is None else f"N == {n}"
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < min_n or (n is not None and arr.shape[0] != n):
        raise ValueError(f"{name} must have shape (N, 2) with {wanted}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(arr), axis=1))[0])
        raise ValueError(f"{name} must be finite, got {arr[bad].tolist()} at row {bad}")
    return arr


def _vector(name: str, value: ArrayLike, n: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n) or arr.shape[0] == 0:
        wanted = f"({n},)" if n is not None else "(N,) with N >= 1"
        raise ValueError(f"{name} must have shape {wanted}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise ValueError(f"{name} must be finite, got {arr[bad]} at index {bad}")
    return arr


def _finite(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _bounds(value: Any) -> tuple[float, float, float, float]:
    try:
        vals = [float(v) for v in value]
    except (TypeError, ValueError):
        raise ValueError(f"bounds must be (xmin, ymin, xmax, ymax), got {value!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"bounds must be 4 finite numbers (xmin, ymin, xmax, ymax), got {value!r}")
    xmin, ymin, xmax, ymax = vals
    if xmax <= xmin:
        raise ValueError(f"bounds need xmax > xmin, got xmin={xmin}, xmax={xmax}")
    if ymax <= ymin:
        raise ValueError(f"bounds need ymax > ymin, got ymin={ymin}, ymax={ymax}")
    return xmin, ymin, xmax, ymax


# ------------------------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class GuidanceConfig:
    """How guidance is sampled; stored in checkpoints and datasets so both sides agree."""

    spacing: float = DEFAULT_SPACING
    count: int = DEFAULT_COUNT  # K
    reference: str = "route"  # "route": subtract T_yaw[0] (the paper); "ego": subtract the ego's yaw

    def __post_init__(self) -> None:
        spacing = _finite("GuidanceConfig.spacing", self.spacing)
        if spacing <= 0.0:
            raise ValueError(f"GuidanceConfig.spacing must be > 0 metres, got {self.spacing!r}")
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "count", _positive_int("GuidanceConfig.count", self.count))
        if self.reference not in REFERENCES:
            raise ValueError(f"GuidanceConfig.reference must be one of {REFERENCES}, got {self.reference!r}")

    def dims(self) -> dict[str, int]:
        """Input width of each guidance kind, for building the models' measurement layers."""
        return {"yaw": self.count, "xy": 2 * self.count, "sim_yaw": self.count}

    def to_dict(self) -> dict[str, Any]:
        return {"spacing": self.spacing, "count": self.count, "reference": self.reference}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GuidanceConfig:
        """Rebuild from `to_dict` output; missing keys take the defaults, unknown keys are an error."""
        if not isinstance(d, Mapping):
            raise ValueError(f"GuidanceConfig.from_dict expects a mapping, got {type(d).__name__}")
        unknown = sorted(set(d) - {"spacing", "count", "reference"})
        if unknown:
            raise ValueError(f"GuidanceConfig has no field(s) {unknown}; known: spacing, count, reference")
        return cls(**dict(d))


@dataclass(frozen=True, eq=False)
class Guidance:
    """The three guidance vectors of one frame (read-only float32); a model picks one by kind."""

    yaw: np.ndarray  # (K,)
    xy: np.ndarray  # (2K,) [x0, y0, x1, y1, ...] in [-1, 1]
    sim_yaw: np.ndarray  # (K,)

    def __post_init__(self) -> None:
        for kind in GUIDANCE_KINDS:
            arr = np.array(getattr(self, kind), dtype=np.float32)
            if arr.ndim != 1:
                raise ValueError(f"Guidance.{kind} must be 1-D, got shape {arr.shape}")
            arr.setflags(write=False)
            object.__setattr__(self, kind, arr)
        k = self.yaw.shape[0]
        if self.sim_yaw.shape != (k,) or self.xy.shape != (2 * k,):
            raise ValueError(
                f"Guidance shapes disagree: yaw {self.yaw.shape}, xy {self.xy.shape} (expected ({2 * k},)), "
                f"sim_yaw {self.sim_yaw.shape} (expected ({k},))"
            )

    def get(self, kind: str) -> np.ndarray:
        if kind not in GUIDANCE_KINDS:
            raise ValueError(f"guidance kind must be one of {GUIDANCE_KINDS}, got {kind!r}")
        arr: np.ndarray = getattr(self, kind)
        return arr


# ------------------------------------------------------------------------------------------------ angles
def route_headings(points: ArrayLike) -> np.ndarray:
    """Heading of each segment from coordinates alone, as a GPS-only car would compute it (the paper)."""
    pts = _points("points", points)
    d = np.diff(pts, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


# ---------------------------------------------------------------------------------------- route geometry
def project_on_route(
    route_xy: ArrayLike, point_xy: ArrayLike, hint_index: int | None = None, window: int = 50
) -> tuple[int, float]:
    """Nearest point of the route polyline to `point_xy`: (segment index, arc length s in metres).

    With `hint_index` (last frame's index) only segments within `window` of it are searched, so a route
    that passes the same place twice is tracked on the right pass. Ties go to the lowest index.
    """
    route = _points("route_xy", route_xy)
    i, t = _project(route, _vector("point_xy", point_xy, n=2), hint_index, window)
    seg, cum = arc_lengths(route[: i + 2])
    return i, float(cum[i] + t * seg[i])


def _project(route: np.ndarray, p: np.ndarray, hint_index: int | None, window: int) -> tuple[int, float]:
    """(segment index, fraction along it) of the nearest point, searching near the hint if there is one.

    Not `RouteGeometry.project`: that one extrapolates past the route's ends (the expert's lateral error off
    the end of a route) and searches an asymmetric window; guidance clamps to the route, searches the whole
    route without a hint, and its values are part of every stored dataset, so it keeps this arithmetic."""
    n_seg = route.shape[0] - 1
    lo, hi = 0, n_seg
    if hint_index is not None:
        if isinstance(hint_index, bool) or not isinstance(hint_index, (int, np.integer)):
            raise ValueError(f"hint_index must be an int or None, got {hint_index!r}")
        if not 0 <= int(hint_index) < route.shape[0]:
            raise ValueError(f"hint_index must be in [0, {route.shape[0] - 1}], got {hint_index}")
        w = _positive_int("window", window)
        lo, hi = max(0, int(hint_index) - w), min(n_seg, int(hint_index) + w + 1)
    a, b = route[lo:hi], route[lo + 1 : hi + 1]
    ab = b - a
    len2 = np.einsum("ij,ij->i", ab, ab)
    t = np.einsum("ij,ij->i", p - a, ab) / np.where(len2 > 0.0, len2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    nearest = a + t[:, None] * ab
    dist2 = np.einsum("ij,ij->i", p - nearest, p - nearest)
    j = int(np.argmin(dist2))
    return lo + j, float(t[j])


def _ahead(route: np.ndarray, index: int, start_s: float, needed: float) -> int:
    """End (exclusive) of a route slice from `index` long enough to hold `needed` metres past `start_s`.

    Guidance only looks K * spacing ahead, so working on a short slice keeps a frame O(K), not O(route).
    """
    n = route.shape[0]
    m = 32
    while True:
        end = min(n, index + m + 1)
        length = float(np.linalg.norm(np.diff(route[index:end], axis=0), axis=1).sum())
        if end == n or length >= start_s + needed:
            return end
        m *= 2


def _clean(
    route: np.ndarray, values: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Drop zero-length segments (duplicate waypoints), which have no direction to follow."""
    seg, _ = arc_lengths(route)
    keep = np.concatenate(([True], seg > 0.0))
    if keep.sum() < 2:
        raise ValueError("route_xy has zero length: all waypoints coincide")
    r = route[keep]
    _, cum = arc_lengths(r)
    return r, cum, None if values is None else values[keep]


def resample_route(route_xy: ArrayLike, start_s: float, spacing: float, n_points: int) -> np.ndarray:
    """Points at arc lengths start_s + k * spacing; past either end, continue straight along the end segment.

    Continuing straight is the padding: near the goal the guidance keeps the last segment's heading.
    """
    route = _points("route_xy", route_xy)
    s0 = _finite("start_s", start_s)
    step = _finite("spacing", spacing)
    if step <= 0.0:
        raise ValueError(f"spacing must be > 0 metres, got {spacing!r}")
    n = _positive_int("n_points", n_points)
    r, cum, _ = _clean(route)
    s = s0 + step * np.arange(n, dtype=np.float64)
    out = np.column_stack((np.interp(s, cum, r[:, 0]), np.interp(s, cum, r[:, 1])))
    total = cum[-1]
    after, before = s > total, s < 0.0
    if after.any():
        d = (r[-1] - r[-2]) / (cum[-1] - cum[-2])
        out[after] = r[-1] + (s[after] - total)[:, None] * d
    if before.any():
        d = (r[1] - r[0]) / cum[1]
        out[before] = r[0] + s[before][:, None] * d
    return out


def interpolate_lane_yaw(route_xy: ArrayLike, route_lane_yaw: ArrayLike, s_values: ArrayLike) -> np.ndarray:
    """Lane heading at arc positions, interpolated on the unit circle (no jump at +-pi); held past the ends."""
    route = _points("route_xy", route_xy)
    lane = _vector("route_lane_yaw", route_lane_yaw, n=route.shape[0])
    s = np.atleast_1d(np.asarray(s_values, dtype=np.float64))
    if s.ndim != 1 or not np.all(np.isfinite(s)):
        raise ValueError(f"s_values must be a finite 1-D array, got shape {s.shape}")
    _, cum, lane_k = _clean(route, lane)
    assert lane_k is not None
    c = np.interp(s, cum, np.cos(lane_k))
    sn = np.interp(s, cum, np.sin(lane_k))
    return np.arctan2(sn, c)


# ------------------------------------------------------------------------------------- guidance vectors
def yaw_guidance(
    points: ArrayLike, reference_yaw: float | None = None, yaw_noise: np.ndarray | None = None
) -> np.ndarray:
    """(K+1, 2) route points -> (K,) float32 wrap(T_yaw + noise - ref); ref = T_yaw[0] (after noise) if None."""
    t_yaw = route_headings(points)
    if yaw_noise is not None:
        t_yaw = t_yaw + _vector("yaw_noise", yaw_noise, n=t_yaw.shape[0])
    ref = t_yaw[0] if reference_yaw is None else _finite("reference_yaw", reference_yaw)
    return wrap_angle(t_yaw - ref).astype(np.float32)


def xy_guidance(points: ArrayLike, bounds: Sequence[float]) -> np.ndarray:
    """(K, 2) map points -> (2K,) float32 scaled to [-1, 1] by the map bounds (clipped: padding may leave it)."""
    pts = _points("points", points, min_n=1)
    xmin, ymin, xmax, ymax = _bounds(bounds)
    lo = np.array([xmin, ymin])
    scaled = 2.0 * (pts - lo) / (np.array([xmax, ymax]) - lo) - 1.0
    return np.clip(scaled, -1.0, 1.0).reshape(-1).astype(np.float32)


def sim_yaw_guidance(lane_yaw: ArrayLike, reference_yaw: float | None = None) -> np.ndarray:
    """(K,) simulator lane headings -> (K,) float32 wrap(lane_yaw - ref); ref = lane_yaw[0] if None."""
    lane = _vector("lane_yaw", lane_yaw)
    ref = lane[0] if reference_yaw is None else _finite("reference_yaw", reference_yaw)
    return wrap_angle(lane - ref).astype(np.float32)


def compute_guidance(
    route_xy: ArrayLike,
    route_lane_yaw: ArrayLike,
    ego_xy: ArrayLike,
    ego_yaw: float,
    bounds: Sequence[float],
    config: GuidanceConfig = GuidanceConfig(),
    hint_index: int | None = None,
    yaw_noise_deg: float = 0.0,
    rng: np.random.Generator | None = None,
    yaw_noise_mode: str = "raw",
) -> tuple[Guidance, int]:
    """One frame's guidance: project the ego, resample K+1 points ahead, build the three vectors.

    Returns (guidance, index of the route segment under the ego); pass the index back as `hint_index` next
    frame. With `yaw_noise_deg` > 0 (Table II; needs `rng`) one draw of N(0, sigma^2) degrees per component,
    read one of two ways (`YAW_NOISE_MODES`): "raw" adds it to the raw headings of both `yaw` and `sim_yaw`
    before the reference is subtracted (a noisy receiver's trajectory; with the first heading as reference
    y[0] stays 0 and the others get sqrt(2) sigma, correlated); "independent" adds it to each component of
    the finished vectors (exactly sigma on each, independent).
    """
    if yaw_noise_mode not in YAW_NOISE_MODES:
        raise ValueError(f"yaw_noise_mode {yaw_noise_mode!r}: choose one of {', '.join(YAW_NOISE_MODES)}")
    if not isinstance(config, GuidanceConfig):
        raise ValueError(f"config must be a GuidanceConfig, got {type(config).__name__}")
    route = _points("route_xy", route_xy)
    lane = _vector("route_lane_yaw", route_lane_yaw, n=route.shape[0])
    ego = _vector("ego_xy", ego_xy, n=2)
    yaw0 = _finite("ego_yaw", ego_yaw)
    box = _bounds(bounds)
    sigma = _finite("yaw_noise_deg", yaw_noise_deg)
    if sigma < 0.0:
        raise ValueError(f"yaw_noise_deg must be >= 0, got {yaw_noise_deg!r}")
    if sigma > 0.0 and not isinstance(rng, np.random.Generator):
        raise ValueError(f"yaw_noise_deg={sigma} needs rng as a numpy Generator, got {rng!r}")

    k = config.count
    index, t = _project(route, ego, hint_index, window=50)
    # Work on the slice from the ego's segment on: s is measured from route[index].
    s = t * float(np.linalg.norm(route[index + 1] - route[index]))
    end = _ahead(route, index, s, config.spacing * (k + 1))
    local, local_lane = route[index:end], lane[index:end]
    if not np.any(np.diff(local, axis=0)):  # the ego is on duplicates of the final point: the route's end
        local, local_lane = route, lane
        s = float(arc_lengths(route)[1][-1])
    points = resample_route(local, s, config.spacing, k + 1)
    s_k = s + config.spacing * np.arange(k, dtype=np.float64)
    lane_k = interpolate_lane_yaw(local, local_lane, s_k)
    noise = None
    if sigma > 0.0:
        assert rng is not None
        noise = np.deg2rad(rng.normal(0.0, sigma, size=k))
    raw = noise if yaw_noise_mode == "raw" else None
    ref = yaw0 if config.reference == "ego" else None
    yaw = yaw_guidance(points, reference_yaw=ref, yaw_noise=raw)
    sim_yaw = sim_yaw_guidance(lane_k if raw is None else lane_k + raw, reference_yaw=ref)
    if noise is not None and raw is None:
        yaw = wrap_angle(yaw + noise).astype(np.float32)
        sim_yaw = wrap_angle(sim_yaw + noise).astype(np.float32)
    return Guidance(yaw=yaw, xy=xy_guidance(points[:k], box), sim_yaw=sim_yaw), index


YAW_NOISE_MODES: tuple[str, ...] = ("raw", "independent")
COMMAND_NOISE_MODES: tuple[str, ...] = ("burst-start", "frame-share")


# ----------------------------------------------------------------------------------------- command noise
_NOISY_COMMANDS: tuple[int, ...] = (
    int(RoadOption.LEFT),
    int(RoadOption.RIGHT),
    int(RoadOption.STRAIGHT),
    int(RoadOption.LANEFOLLOW),
)


class CommandNoise:
    """Table II noise for CIL: wrong commands in bursts of `length` frames, p read one of two ways.

    "burst-start" (CIL's sentence read literally): with probability p on each frame without a burst, a burst
    starts; bursts never overlap, so the long-run share of noisy frames is p*L / (p*L + 1 - p) (13 %, 21 %,
    36 % at p = 3, 5, 10 % and L = 5). "frame-share": p is that share itself; the start probability q
    solving q*L / (q*L + 1 - q) = p is used. The wrong command is drawn uniformly from the three others at
    the start of a burst and redrawn only if the true command changes into it, so the true command is never
    returned while a burst runs. VOID counts as LANEFOLLOW (as CARLA's agents do).
    """

    def __init__(self, p: float, rng: np.random.Generator, length: int = 5, mode: str = "burst-start") -> None:
        prob = _finite("p", p)
        if not 0.0 <= prob <= 1.0:
            raise ValueError(f"p must be a probability in [0, 1], got {p!r}")
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy Generator, got {rng!r}")
        if mode not in COMMAND_NOISE_MODES:
            raise ValueError(f"command noise mode {mode!r}: choose one of {', '.join(COMMAND_NOISE_MODES)}")
        self.length = _positive_int("length", length)
        n = self.length
        self.p = prob if mode == "burst-start" else prob / (n * (1.0 - prob) + prob)  # start probability
        self.share = self.p * n / (self.p * n + 1.0 - self.p)  # long-run share of noisy frames
        self._rng = rng
        self._remaining = 0
        self._wrong = 0
        self._noisy = False
        self.bursts = 0  # how many bursts have started, for reports

    @property
    def active(self) -> bool:
        """True while the last returned command was a wrong one."""
        return self._noisy

    def reset(self) -> None:
        """End any running burst (new episode); the random stream carries on."""
        self._remaining = 0
        self._noisy = False

    def _draw_wrong(self, true: int) -> int:
        others = [c for c in _NOISY_COMMANDS if c != true]
        return others[int(self._rng.integers(len(others)))]

    def __call__(self, command: int) -> int:
        try:
            opt = RoadOption(int(command))
        except (TypeError, ValueError):
            raise ValueError(
                f"command must be a RoadOption value (-1, 1, 2, 3, 4), got {command!r}"
            ) from None
        true = int(RoadOption.LANEFOLLOW if opt is RoadOption.VOID else opt)
        if self._remaining == 0:
            if self._rng.random() >= self.p:
                self._noisy = False
                return int(command)
            self._remaining = self.length
            self._wrong = self._draw_wrong(true)
            self.bursts += 1
        elif self._wrong == true:
            self._wrong = self._draw_wrong(true)
        self._remaining -= 1
        self._noisy = True
        return self._wrong
