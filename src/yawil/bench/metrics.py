"""Per-episode judging and the aggregate figures of the paper's Tables I-IV.

One protocol for every agent (docs/benchmark.md): success = the goal reached by `yawil.sim.criteria.goal_reached`
(the rule the worlds also use) before the timeout with no collision of any kind; an episode ends at success,
timeout, the first collision, or `blocked` (BLOCKED_S without route progress).
Violations are counted over successful episodes only, as the paper does. Standard deviations are population
standard deviations (ddof=0): the paper's own figures (66.67 +- 0.94 over 3 runs, 31.6 +- 0.49 over 5) are
reproduced by that choice and not by ddof=1.

Nothing here imports the simulator's world or torch: a tracker reads duck-typed observations, and the
aggregates read plain episode records (dicts, as stored one per JSON line).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from yawil.sim.criteria import GoalCriterion
from yawil.sim.types import DT, EventKind, Observation

FAILURE_REASONS: tuple[str, ...] = (
    "collision_vehicle",
    "collision_pedestrian",
    "collision_static",
    "timeout",
    "blocked",
)
# An agent that makes no progress along its route for this long has stopped for good: the episode ends as
# `blocked` (the CARLA leaderboard's "agent blocked", whose 180 s this takes) instead of burning the rest of
# its timeout. The expert's longest wait (a queue at a red light over more than one cycle) must stay well
# below it: 71 s measured in town01 Regular, where 90 s would have left too little room for Dense queues;
# docs/benchmark.md gives the measured figures (`max_stall_s` of every record).
BLOCKED_S = 180.0
PROGRESS_M = 1.0  # route progress (metres along the route) that counts as moving on
TRAJECTORY_EVERY = 5  # store one (x, y) every 5 steps (0.5 s) for the report's trajectory plots
ROUTE_EVERY_M = 5  # store one route waypoint every ~5 m (route waypoints are ~1 m apart)


TIMEOUT_RULES: dict[str, str] = {
    "corl2017": "10 km/h average plus 10 s",
    "nocrash": "5 km/h average plus 20 s",
}


def timeout_for(length_m: float, rule: str = "nocrash") -> float:
    """The time budget of a route of `length_m` metres under a suite's rule (`TIMEOUT_RULES`)."""
    from yawil.sim.criteria import corl2017_timeout, nocrash_timeout  # the formulas, also the worlds' default

    if not math.isfinite(length_m) or length_m < 0:
        raise ValueError(f"route length must be a finite number >= 0 metres, got {length_m!r}")
    if rule not in TIMEOUT_RULES:
        raise ValueError(f"unknown timeout rule {rule!r}; choose one of {', '.join(TIMEOUT_RULES)}")
    return corl2017_timeout(length_m) if rule == "corl2017" else nocrash_timeout(length_m)


def collision_reason(other_type: str | None) -> str:
    """Failure reason of a collision with an actor of `other_type` (vehicle, pedestrian, anything else)."""
    if other_type == "vehicle":
        return "collision_vehicle"
    if other_type == "pedestrian":
        return "collision_pedestrian"
    return "collision_static"


@dataclass
class EpisodeTracker:
    """Judges one episode from its observations; `update` returns True once the episode is over.

    The tracker, not the world, decides the end: goal distance, the protocol's timeout, collisions and the
    blocked rule are checked here so that every backend is judged by the same rules.
    """

    goal_xy: tuple[float, float]
    timeout_s: float
    trajectory_every: int = TRAJECTORY_EVERY
    blocked_s: float = BLOCKED_S
    success: bool = False
    reason: str | None = None
    finished: bool = False
    time_s: float = 0.0
    steps: int = 0
    distance_m: float = 0.0
    lane_opposite: int = 0
    lane_offroad: int = 0
    red_lights: int = 0
    lights_passed: int = 0
    collisions: list[dict[str, Any]] = field(default_factory=list)
    trajectory: list[list[float]] = field(default_factory=list)
    final_distance_m: float = math.inf
    max_stall_s: float = 0.0  # longest time without PROGRESS_M of route progress
    _goal: GoalCriterion | None = field(default=None, init=False, repr=False, compare=False)
    _best_index: int = field(default=0, init=False, repr=False, compare=False)
    _progress_time: float = field(default=0.0, init=False, repr=False, compare=False)
    _spacing: float = field(default=1.0, init=False, repr=False, compare=False)

    def start(self, obs: Observation) -> None:
        """Record the first observation (after reset) without judging it."""
        self.trajectory.append([round(obs.pose.x, 2), round(obs.pose.y, 2)])
        self.final_distance_m = self._goal_distance(obs)
        end = (float(obs.route.xy[-1][0]), float(obs.route.xy[-1][1]))
        if math.hypot(end[0] - self.goal_xy[0], end[1] - self.goal_xy[1]) > 1e-6:
            raise ValueError(
                f"EpisodeTracker.goal_xy {self.goal_xy} is not the observed route's last "
                f"waypoint {end}; the goal must be the route's end"
            )
        self._goal = GoalCriterion(obs.route.xy)  # the worlds' own rule, its route table built once
        self._best_index = int(obs.route_index)
        n = len(obs.route.xy)
        self._spacing = float(obs.route.length) / (n - 1) if n > 1 and obs.route.length > 0 else 1.0

    def _goal_distance(self, obs: Observation) -> float:
        return math.hypot(obs.pose.x - self.goal_xy[0], obs.pose.y - self.goal_xy[1])

    def update(self, obs: Observation) -> bool:
        """Account for one step's observation; True when the episode ends with it."""
        if self.finished:
            raise RuntimeError("EpisodeTracker.update called after the episode ended")
        if self._goal is None:
            raise RuntimeError("EpisodeTracker.update called before start")
        self.steps += 1
        self.time_s = self.steps * DT
        self.distance_m = float(obs.distance_driven)
        for ev in obs.events:
            if ev.kind == EventKind.COLLISION:
                self.collisions.append(
                    {
                        "type": ev.other_type or "static",
                        "id": ev.other_id,
                        "t": round(ev.time, 2),
                        "x": round(ev.x, 2),
                        "y": round(ev.y, 2),
                        "rear_end": is_rear_end(obs, ev.other_id),
                    }
                )
            elif ev.kind == EventKind.LANE_INVASION:
                if ev.detail == "opposite_lane":
                    self.lane_opposite += 1
                elif ev.detail == "off_road":
                    self.lane_offroad += 1
                else:
                    raise ValueError(
                        f"lane_invasion event with detail {ev.detail!r}; expected 'opposite_lane' or 'off_road'"
                    )
            elif ev.kind == EventKind.RED_LIGHT:
                self.red_lights += 1
            elif ev.kind == EventKind.LIGHT_PASSED:
                self.lights_passed += 1
        if self.steps % self.trajectory_every == 0:
            self.trajectory.append([round(obs.pose.x, 2), round(obs.pose.y, 2)])
        self.final_distance_m = self._goal_distance(obs)
        if (int(obs.route_index) - self._best_index) * self._spacing >= PROGRESS_M - 1e-9:
            self._best_index = int(obs.route_index)
            self._progress_time = self.time_s
        stall = self.time_s - self._progress_time
        self.max_stall_s = max(self.max_stall_s, stall)
        if self.collisions:
            self.reason = collision_reason(self.collisions[0]["type"])
        elif self._goal.update(obs.time, obs.pose.x, obs.pose.y, obs.route_index):
            self.success = True
        elif self.time_s >= self.timeout_s - 1e-9:
            self.reason = "timeout"
        elif stall >= self.blocked_s - 1e-9:
            self.reason = "blocked"
        elif obs.done:
            # The world stopped on its own timeout before ours (its goal rule is ours, judged above).
            self.reason = "timeout"
        else:
            return False
        self.finished = True
        if self.trajectory[-1] != [round(obs.pose.x, 2), round(obs.pose.y, 2)]:
            self.trajectory.append([round(obs.pose.x, 2), round(obs.pose.y, 2)])
        return True

    def result(self) -> dict[str, Any]:
        """The judged fields of an episode record."""
        if not self.finished:
            raise RuntimeError("EpisodeTracker.result called before the episode ended")
        return {
            "success": self.success,
            "reason": self.reason,
            "time_s": round(self.time_s, 2),
            "steps": self.steps,
            "km_driven": round(self.distance_m / 1000.0, 5),
            "lane_opposite": self.lane_opposite,
            "lane_offroad": self.lane_offroad,
            "red_lights": self.red_lights,
            "lights_passed": self.lights_passed,
            "collisions": self.collisions,
            "final_distance_m": round(self.final_distance_m, 3),
            "max_stall_s": round(self.max_stall_s, 2),
            "trajectory": self.trajectory,
        }


REAR_END_DEG = 45.0  # the other vehicle heads within this of the ego's heading


def is_rear_end(obs: Observation, other_id: int | None) -> bool:
    """The ego ran into the back of a vehicle: the other is ahead of the ego's centre and heads its way.

    The learned agents' main failure (docs/training.md), so the failure tables count it apart.
    """
    other = next((a for a in obs.privileged.agents if a.id == other_id and a.kind == "vehicle"), None)
    if other is None:
        return False
    c, s = math.cos(obs.pose.yaw), math.sin(obs.pose.yaw)
    ahead = c * (other.x - obs.pose.x) + s * (other.y - obs.pose.y)
    diff = abs(math.remainder(other.yaw - obs.pose.yaw, math.tau))
    return ahead > 0.0 and diff < math.radians(REAR_END_DEG)


def subsample_route(xy: np.ndarray, every: int = ROUTE_EVERY_M) -> list[list[float]]:
    """Every `every`-th route waypoint plus the last one, rounded, for plots in the report."""
    pts = np.asarray(xy, dtype=np.float64)
    idx = list(range(0, len(pts), max(1, every)))
    if idx and idx[-1] != len(pts) - 1:
        idx.append(len(pts) - 1)
    return [[round(float(pts[i, 0]), 2), round(float(pts[i, 1]), 2)] for i in idx]


# ----- aggregates over records -----------------------------------------------------------------------------


def _check_record(rec: Mapping[str, Any]) -> None:
    for key in ("task", "condition", "seed", "success", "km_driven"):
        if key not in rec:
            raise ValueError(f"episode record lacks field {key!r}: {dict(rec)!r:.200}")


def group_by_seed(records: Iterable[Mapping[str, Any]]) -> dict[int, list[Mapping[str, Any]]]:
    """Records of one (task, condition) split by seed, seeds in ascending order."""
    out: dict[int, list[Mapping[str, Any]]] = {}
    for rec in records:
        _check_record(rec)
        out.setdefault(int(rec["seed"]), []).append(rec)
    return dict(sorted(out.items()))


def success_rate(records: Sequence[Mapping[str, Any]]) -> float:
    """Percentage of successful episodes (0-100)."""
    if not records:
        raise ValueError("success_rate of no episodes is undefined")
    return 100.0 * sum(bool(r["success"]) for r in records) / len(records)


def lane_violations_per_km(records: Sequence[Mapping[str, Any]]) -> float:
    """(opposite-lane + off-road entries) / km driven, pooled over the successful episodes only.

    NaN when no successful episode drove any distance (nothing to measure).
    """
    ok = [r for r in records if r["success"]]
    km = sum(float(r["km_driven"]) for r in ok)
    if km <= 0:
        return math.nan
    return sum(int(r["lane_opposite"]) + int(r["lane_offroad"]) for r in ok) / km


def light_violation_ratio(records: Sequence[Mapping[str, Any]]) -> float:
    """Red lights crossed / signalised stop lines passed, pooled over successful episodes; NaN if none passed."""
    ok = [r for r in records if r["success"]]
    passed = sum(int(r["lights_passed"]) for r in ok)
    if passed <= 0:
        return math.nan
    return sum(int(r["red_lights"]) for r in ok) / passed


@dataclass(frozen=True)
class Stat:
    """A figure over seeds: `value` is the mean (or the best), `std` the population std (None for best-of)."""

    value: float
    std: float | None
    n_seeds: int
    per_seed: tuple[float, ...]

    def format(self, digits: int = 2) -> str:
        if math.isnan(self.value):
            return "n/a"
        if self.std is None or self.n_seeds == 1:  # one seed has no spread to show ("± 0.00" said nothing)
            return f"{self.value:.{digits}f}".rstrip("0").rstrip(".") if digits else f"{self.value:.0f}"
        return f"{self.value:.{digits}f} ± {self.std:.{digits}f}"


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval (95 % by default) of a success rate, in %: how far the rate of `n` episodes can
    be from the agent's true rate. Why Wilson: unlike the normal approximation it stays inside [0, 100] and is
    honest at 0 or n successes, the usual cells of a benchmark table. Five lines of closed form: not worth a
    scipy or statsmodels dependency (docs/decisions.md)."""
    if n <= 0:
        return (math.nan, math.nan)
    if not 0 <= successes <= n:
        raise ValueError(f"wilson_interval: {successes} successes of {n} episodes")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    lo = 0.0 if successes == 0 else 100 * max(0.0, centre - half)  # exact at the ends, whatever the rounding
    hi = 100.0 if successes == n else 100 * min(1.0, centre + half)
    return (min(lo, 100 * p), max(hi, 100 * p))


def difference_interval(a: tuple[int, int], b: tuple[int, int], z: float = 1.959964) -> tuple[float, float, float]:
    """(difference, lo, hi) in percentage points of two success rates, a - b, each given as (successes,
    episodes): Newcombe's hybrid score interval (his method 10), built from the two Wilson intervals. Why:
    "A beats B" is a claim about the difference, and two overlapping Wilson intervals do not say it is zero."""
    (sa, na), (sb, nb) = a, b
    if na <= 0 or nb <= 0:
        return (math.nan, math.nan, math.nan)
    pa, pb = 100.0 * sa / na, 100.0 * sb / nb
    la, ua = wilson_interval(sa, na, z)
    lb, ub = wilson_interval(sb, nb, z)
    d = pa - pb
    lo = d - math.sqrt((pa - la) ** 2 + (ub - pb) ** 2)
    hi = d + math.sqrt((ua - pa) ** 2 + (pb - lb) ** 2)
    return (d, max(-100.0, lo), min(100.0, hi))


def mean_std(values: Sequence[float]) -> Stat:
    """Mean and population std over seeds, ignoring undefined (NaN) seeds; NaN if every seed is undefined."""
    vals = tuple(float(v) for v in values)
    finite = [v for v in vals if not math.isnan(v)]
    if not finite:
        return Stat(math.nan, math.nan, len(vals), vals)
    return Stat(float(np.mean(finite)), float(np.std(finite)), len(vals), vals)


def best_of(values: Sequence[float]) -> Stat:
    """The best seed, as the paper reports its static tasks."""
    vals = tuple(float(v) for v in values)
    if not vals:
        raise ValueError("best_of of no seeds is undefined")
    return Stat(max(vals), None, len(vals), vals)


def task_success(records: Iterable[Mapping[str, Any]], dynamic: bool) -> Stat:
    """Table III cell: best of the seeds for a static task, mean +- std over the seeds for a dynamic one."""
    by_seed = group_by_seed(records)
    if not by_seed:
        raise ValueError("no episodes for this task and condition")
    rates = [success_rate(recs) for recs in by_seed.values()]
    return mean_std(rates) if dynamic else best_of(rates)


def task_violations(records: Iterable[Mapping[str, Any]]) -> tuple[Stat, Stat]:
    """Table IV cells: (lane violations per km, traffic-light violation ratio), mean +- std over seeds."""
    by_seed = group_by_seed(records)
    if not by_seed:
        raise ValueError("no episodes for this task and condition")
    lanes = [lane_violations_per_km(recs) for recs in by_seed.values()]
    lights = [light_violation_ratio(recs) for recs in by_seed.values()]
    return mean_std(lanes), mean_std(lights)


def failure_counts(records: Iterable[Mapping[str, Any]]) -> dict[str, int]:
    """How many episodes ended by each reason, plus 'success'."""
    out = {"success": 0, **{r: 0 for r in FAILURE_REASONS}, "rear_end": 0}
    for rec in records:
        key = "success" if rec["success"] else str(rec.get("reason"))
        out[key] = out.get(key, 0) + 1
        cols = rec.get("collisions") or []
        if not rec["success"] and cols and cols[0].get("rear_end"):
            out["rear_end"] += 1  # also counted under its reason (vehicle)
    return out
