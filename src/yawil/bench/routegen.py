"""Generating the committed route files once, and validating them against the current planner.

Routes are built on the embedded town's lane graph and then re-planned with `plan_route` from their start
and goal poses, exactly as the world will plan them: a route is kept only if the planner's route between its
end points has the task's structure. Rules (docs/benchmark.md):
- straight: no LEFT/RIGHT manoeuvre and the lane heading never more than 30 deg from the start's (so no
  lane-follow corner either);
- one_turn: exactly one LEFT/RIGHT junction manoeuvre; before it the heading stays within 30 deg of the
  start's, after it within 30 deg of the goal's (no lane-follow corner);
- navigation: any shortest route at least 1.0 km long in town01, 0.3 km in town02;
- square: the 32 turning tasks of `yawil.sim.town.map.planner.turn_tasks` (8 corners, 16 T-junction, 8 crossing).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from yawil.bench.suites import (
    MIN_LENGTH,
    ROUTE_FORMAT,
    ROUTES_PER_TASK,
    SQUARE_TASKS,
    STRAIGHT_MAX_HEADING_DEG,
    RouteSpec,
    check_task_routes,
    load_routes,
    route_file,
)
from yawil.fileio import write_json_atomic
from yawil.sim.types import Pose, RoadOption, Route, wrap_angle

LENGTH_TOLERANCE_M = 1.0  # a re-planned route may differ from the file by max(1 m, 1 %)
TURN_OPTIONS = {int(RoadOption.LEFT): "LEFT", int(RoadOption.RIGHT): "RIGHT", int(RoadOption.STRAIGHT): "STRAIGHT"}


def route_turns(route: Route) -> tuple[tuple[str, int, int], ...]:
    """Junction manoeuvres of a route in order: (name, first waypoint, last waypoint) of each run of
    consecutive LEFT/RIGHT/STRAIGHT waypoints."""
    out: list[tuple[str, int, int]] = []
    opts = np.asarray(route.options, dtype=np.int64)
    i = 0
    while i < len(opts):
        name = TURN_OPTIONS.get(int(opts[i]))
        if name is None:
            i += 1
            continue
        j = i
        while j + 1 < len(opts) and int(opts[j + 1]) == int(opts[i]):
            j += 1
        out.append((name, i, j))
        i = j + 1
    return tuple(out)


def _max_dev_deg(yaw: np.ndarray, ref: float) -> float:
    if len(yaw) == 0:
        return 0.0
    return math.degrees(max(abs(wrap_angle(float(y) - ref)) for y in yaw))


def classify(route: Route) -> tuple[str | None, tuple[str, ...]]:
    """('straight' | 'one_turn' | None, turn names) of a planned route, by the rules above."""
    turns = route_turns(route)
    names = tuple(t[0] for t in turns)
    yaw = np.asarray(route.lane_yaw, dtype=np.float64)
    lr = [t for t in turns if t[0] in ("LEFT", "RIGHT")]
    if not lr:
        if _max_dev_deg(yaw, float(yaw[0])) <= STRAIGHT_MAX_HEADING_DEG:
            return "straight", names
        return None, names
    if len(lr) == 1:
        _, a, b = lr[0]
        if (
            _max_dev_deg(yaw[:a], float(yaw[0])) <= STRAIGHT_MAX_HEADING_DEG
            and _max_dev_deg(yaw[b + 1 :], float(yaw[-1])) <= STRAIGHT_MAX_HEADING_DEG
        ):
            return "one_turn", names
    return None, names


def _lanes(town: str) -> Any:
    from yawil.sim.town.map.town import get_town

    return get_town(town).lanes


def _replan(lanes: Any, start: Pose, goal: Pose) -> Route:
    from yawil.sim.town.map.planner import plan_route

    return plan_route(lanes, start, goal).route  # type: ignore[no-any-return]


def _endpoints(route: Route) -> tuple[Pose, Pose]:
    xy, yaw = route.xy, route.lane_yaw
    return Pose(float(xy[0, 0]), float(xy[0, 1]), float(yaw[0])), Pose(float(xy[-1, 0]), float(xy[-1, 1]), float(yaw[-1]))


def _walk(lanes: Any, rng: np.random.Generator, want: str) -> Route | None:
    """A candidate lane walk: straight connectors only (straight), or one LEFT/RIGHT among them (one_turn)."""
    from yawil.sim.town.map.planner import sample_route

    ls = int(rng.integers(0, lanes.n_road_lanes))
    seq = [ls]
    turned = want == "straight"
    for _ in range(int(rng.integers(0, 4))):
        conns = [c for c in lanes.lanes[seq[-1]].successors]
        options = [
            c for c in conns
            if lanes.lanes[c].option is RoadOption.STRAIGHT
            or (not turned and lanes.lanes[c].option in (RoadOption.LEFT, RoadOption.RIGHT))
        ]
        if not options:
            break
        c = int(rng.choice(options))
        turned = turned or lanes.lanes[c].option in (RoadOption.LEFT, RoadOption.RIGHT)
        seq += [c, lanes.lanes[c].successors[0]]
    if not turned:
        return None
    ss = float(rng.uniform(0.05, 0.5) * lanes.length[seq[0]])
    sg = float(rng.uniform(0.5, 0.95) * lanes.length[seq[-1]])
    if len(seq) == 1 and sg <= ss + 1.0:
        return None
    return sample_route(lanes, seq, ss, sg).route  # type: ignore[no-any-return]


def accept_route(
    route: Route, start: Pose, goal: Pose, kind: str, minimum: float, seen: set[tuple[int, int, int, int]]
) -> tuple[str, ...] | None:
    """The turns of a drawn route if it joins the task's list, else None.

    It must be long enough, of the task's kind, and distinct: not the same start/goal cells (10 m grid)
    as a route already taken (`seen` is updated). Shared by the embedded and the CARLA route generators.
    """
    if route.length < minimum:
        return None
    got, names = classify(route)
    if kind != "navigation" and got != kind:
        return None
    cell = (round(start.x / 10), round(start.y / 10), round(goal.x / 10), round(goal.y / 10))
    if cell in seen:
        return None
    seen.add(cell)
    return names


def _draw(
    lanes: Any, rng: np.random.Generator, kind: str, town: str, make: Callable[[], Route | None]
) -> list[RouteSpec]:
    minimum = MIN_LENGTH.get(town, {}).get(kind, 0.0)
    out: list[RouteSpec] = []
    seen: set[tuple[int, int, int, int]] = set()
    for _ in range(20000):
        cand = make()
        if cand is None:
            continue
        start, goal = _endpoints(cand)
        route = _replan(lanes, start, goal)  # what the world will drive
        names = accept_route(route, start, goal, kind, minimum, seen)
        if names is None:
            continue
        out.append(RouteSpec(len(out), start, goal, round(route.length, 2), names))
        if len(out) == ROUTES_PER_TASK:
            return out
    raise ValueError(f"could not draw {ROUTES_PER_TASK} {kind} routes of >= {minimum:.0f} m on {town}; got {len(out)}")


def generate_routes(town: str, seed: int = 0) -> dict[str, list[RouteSpec]]:
    """The route lists of a town: straight, one_turn, navigation (town01/town02) or square (square)."""
    lanes = _lanes(town)
    if town == "square":
        from yawil.sim.town.map.planner import turn_tasks

        specs = []
        for i, task in enumerate(turn_tasks(lanes)):
            route = _replan(lanes, task.start, task.goal)
            start, goal = _endpoints(route)
            names = tuple(t[0] for t in route_turns(route))
            specs.append(RouteSpec(i, start, goal, round(route.length, 2), names, kind=f"{task.kind}:{task.name}"))
        if len(specs) != SQUARE_TASKS:
            raise ValueError(f"the square map has {len(specs)} turning tasks, the paper's protocol needs {SQUARE_TASKS}")
        return {"square": specs}
    if town not in MIN_LENGTH:
        raise ValueError(f"no route rules for town {town!r}; choose one of town01, town02, square")
    from yawil.sim.town.map.planner import random_route

    rng = np.random.default_rng(seed)
    nav_min = MIN_LENGTH[town]["navigation"]
    return {
        "straight": _draw(lanes, rng, "straight", town, lambda: _walk(lanes, rng, "straight")),
        "one_turn": _draw(lanes, rng, "one_turn", town, lambda: _walk(lanes, rng, "one_turn")),
        "navigation": _draw(lanes, rng, "navigation", town, lambda: random_route(lanes, rng, nav_min).route),
    }


def check_route_target(town: str, folder: Path | None = None) -> Path:
    """Where `write_route_file` would write, refused in one line when that would replace a file that is not a yawil
    route file or write inside a dataset, run or results folder (`bench routes --routes-dir` over a user's file)."""
    from yawil.fileio import owning_folder

    if folder is not None and folder.exists() and not folder.is_dir():
        raise ValueError(f"--routes-dir {folder}: is a file; expected a folder for the route files")
    path = route_file(town, folder)
    owner = owning_folder(path)
    if owner is not None:
        raise ValueError(f"--routes-dir {path.parent}: inside {owner}, which a yawil dataset, run or results owns; "
                         "give a folder of route files")
    if path.exists() or path.is_symlink():
        try:
            ours = json.loads(path.read_text(encoding="utf-8")).get("format") == ROUTE_FORMAT
        except (OSError, ValueError, AttributeError):
            ours = False
        if not ours:
            raise ValueError(f"--routes-dir: {path} exists and is not a yawil route file ({ROUTE_FORMAT}); "
                             "move it or give another folder")
    return path


def write_route_file(town: str, seed: int = 0, folder: Path | None = None) -> Path:
    """Generate and atomically write `<folder>/<town>.json` (default: the package's routes folder)."""
    check_route_target(town, folder)
    lists = generate_routes(town, seed)
    for name, specs in lists.items():
        check_task_routes(town, name, specs, f"generated {town}.{name}")
    path = route_file(town, folder)
    doc = {
        "format": ROUTE_FORMAT,
        "town": town,
        "generated_by": f"yawil bench routes --town {town} --seed {seed}",
        "rules": "docs/benchmark.md#routes",
        "routes": {name: [s.to_json() for s in specs] for name, specs in lists.items()},
    }
    write_json_atomic(path, doc)
    return path


def validate_with_planner(town: str, folder: Path | None = None) -> int:
    """Re-plan every route of a town's file: reachable, same length (max(1 m, 1 %)), same turns and class.

    Raises ValueError naming the first route that no longer matches; returns the number of routes checked.
    """
    lists = load_routes(town, folder)
    lanes = _lanes(town)
    n = 0
    for name, specs in lists.items():
        for spec in specs:
            where = f"{route_file(town, folder)}: routes.{name}[{spec.id}]"
            try:
                route = _replan(lanes, spec.start, spec.goal)
            except ValueError as err:
                raise ValueError(f"{where}: unreachable with the current planner ({err})") from None
            tol = max(LENGTH_TOLERANCE_M, 0.01 * spec.length_m)
            if abs(route.length - spec.length_m) > tol:
                raise ValueError(f"{where}: planned length {route.length:.1f} m, file says {spec.length_m:.1f} m")
            got, names = classify(route)
            if names != spec.turns:
                raise ValueError(f"{where}: planned turns {names}, file says {spec.turns}")
            if name in ("straight", "one_turn") and got != name:
                raise ValueError(f"{where}: the planned route is no longer a {name} route (turns {names})")
            n += 1
    return n
