"""Suites, tasks, conditions, the committed route files, and the list of episodes a run is made of.

The protocol (docs/benchmark.md; its version is `yawil.bench.records.PROTOCOL`) in data form:
- tasks: Straight, One Turn, Navigation (Empty) are static (no traffic) and reported as the best of 5 seeds;
  Nav. (Regular) (30 vehicles, 10 pedestrians) and Nav. (Dense) (50, 30) are dynamic, mean +- std over 3.
  Each task carries its suite's time budget: CoRL2017's tasks 10 km/h + 10 s, NoCrash's 5 km/h + 20 s.
  NoCrash's "Empty" drives CoRL2017's Navigation routes under NoCrash's budget: a task of its own (stored
  apart), so that each suite's figures are judged by its own rule.
- `nocrash-original` and CoRL2017's Navigation Dynamic: the published traffic densities per town.
- conditions: `training` = town01 x the 4 training weathers; `new-town-weather` = town02 x the 2 test ones;
  `new-weather` and `new-town` complete NoCrash's four.
  Every route is driven in every weather of its condition (CoRL2017 and NoCrash do so: 100 episodes per
  task and seed in the training condition, 50 in the new town). The weather episodes of one route and seed
  share their world seed: weather is their only difference.
- `selection`: Nav. (Dense) in town01 at New Town02's traffic density (per lane- and walkway-metre), the set
  that chooses checkpoints and recipes for the dense test cell without driving the test town.
- `square`: the 32 turning tasks of the paper's Table I on the square map, in ClearNoon.
Route files live in `yawil/bench/routes/<town>.json`, generated once (`yawil bench routes`) and committed.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from yawil.bench.metrics import TIMEOUT_RULES, timeout_for
from yawil.sim.types import Pose, Scenario
from yawil.sim.weather import TEST_WEATHERS, TRAIN_WEATHERS, get_weather

ROUTES_DIR = Path(__file__).with_name("routes")
_CARLA_ROUTES_DIR = Path(__file__).parent / "carla_routes"  # yawil.bench.carla_routes, not imported here
ROUTE_FORMAT = "yawil-routes/1"
ROUTES_PER_TASK = 25
SQUARE_TASKS = 32
WEATHER_RULES = ("all", "cycle")  # all: every route in every weather (the protocol); cycle: route i in weather i mod n


@dataclass(frozen=True)
class Task:
    name: str
    title: str  # as the paper's tables name it
    routes: str  # which route list of the town file it drives
    vehicles: int
    pedestrians: int
    dynamic: bool  # dynamic tasks: mean +- std over seeds; static: best of seeds
    timeout: str = "nocrash"  # the time budget's rule, one of metrics.TIMEOUT_RULES (the suite's own)
    per_town: tuple[tuple[str, int, int], ...] = ()  # (town, vehicles, pedestrians) where the town differs

    @property
    def default_seeds(self) -> int:
        return 3 if self.dynamic else 5

    def traffic(self, town: str) -> tuple[int, int]:
        """Vehicles and pedestrians of this task in `town` (published suites set them per town)."""
        for name, vehicles, pedestrians in self.per_town:
            if name == town:
                return vehicles, pedestrians
        return self.vehicles, self.pedestrians


@dataclass(frozen=True)
class Condition:
    name: str
    title: str
    town: str
    weathers: tuple[str, ...]

    def weather_for(self, route_id: int) -> str:
        """The weather of route i under the `cycle` rule (i mod n): the preset eval100's one weather per route."""
        return self.weathers[route_id % len(self.weathers)]

    def weathers_for(self, route_id: int, rule: str = "all") -> tuple[str, ...]:
        """The weathers route i is driven in: all of the condition's (the protocol), or one (`cycle`)."""
        if rule not in WEATHER_RULES:
            raise ValueError(f"unknown weather rule {rule!r}; choose one of {', '.join(WEATHER_RULES)}")
        return self.weathers if rule == "all" else (self.weather_for(route_id),)


TASKS: dict[str, Task] = {
    t.name: t
    for t in (
        Task("straight", "Straight", "straight", 0, 0, False, "corl2017"),
        Task("one_turn", "One Turn", "one_turn", 0, 0, False, "corl2017"),
        Task("navigation", "Navigation (Empty)", "navigation", 0, 0, False, "corl2017"),
        Task("nav_dynamic", "Nav. Dynamic (CoRL2017)", "navigation", 20, 50, True, "corl2017",
             (("town01", 20, 50), ("town02", 15, 50))),
        Task("empty", "Empty (NoCrash)", "navigation", 0, 0, False, "nocrash"),
        Task("regular", "Nav. (Regular)", "navigation", 30, 10, True, "nocrash"),
        Task("dense", "Nav. (Dense)", "navigation", 50, 30, True, "nocrash"),
        Task("nocrash_regular", "Regular (NoCrash as published)", "navigation", 20, 50, True, "nocrash",
             (("town01", 20, 50), ("town02", 15, 50))),
        Task("nocrash_dense", "Dense (NoCrash as published)", "navigation", 100, 250, True, "nocrash",
             (("town01", 100, 250), ("town02", 70, 150))),
        Task("square", "Square turning tasks", "square", 0, 0, False, "nocrash"),
        # Nav. (Dense) in town01 at New Town02's density: 50 vehicles and 30 pedestrians in town02 are 2.28x
        # town01's vehicles per lane-metre (1,880 m of road lanes against 4,280) and 2.05x its pedestrians per
        # walkway-metre (2,425 m against 4,965). The training town's selection set for the dense test cell.
        Task("dense_matched", "Nav. (Dense) at New Town02's density", "navigation", 114, 61, True, "nocrash"),
    )
}
TASK_ALIASES: dict[str, str] = {"nav": "navigation", "one-turn": "one_turn", "nav-dynamic": "nav_dynamic"}

CONDITIONS: dict[str, Condition] = {
    c.name: c
    for c in (
        Condition("training", "Training Conditions", "town01", TRAIN_WEATHERS),
        Condition("new-weather", "New Weather", "town01", TEST_WEATHERS),
        Condition("new-town", "New Town02", "town02", TRAIN_WEATHERS),
        Condition("new-town-weather", "New Town02 & Weather", "town02", TEST_WEATHERS),
        Condition("square", "Square scene", "square", ("ClearNoon",)),
    )
}

SUITES: dict[str, tuple[str, ...]] = {
    "corl2017": ("straight", "one_turn", "navigation", "nav_dynamic"),
    "nocrash": ("empty", "regular", "dense"),
    "nocrash-original": ("empty", "nocrash_regular", "nocrash_dense"),
    "all": ("straight", "one_turn", "navigation", "regular", "dense"),
    "square": ("square",),
    "selection": ("dense_matched",),  # checkpoint and recipe selection for the dense test cell, town01 only
}
SUITE_CONDITIONS: dict[str, tuple[str, ...]] = {
    "corl2017": ("training", "new-town-weather"),
    "nocrash": ("training", "new-town-weather"),
    "nocrash-original": ("training", "new-weather", "new-town", "new-town-weather"),
    "all": ("training", "new-town-weather"),
    "square": ("square",),
    "selection": ("training",),
}
TABLE_TASKS: tuple[str, ...] = SUITES["all"]  # rows of Table III, in the paper's order
assert all(t.timeout in TIMEOUT_RULES for t in TASKS.values())


def get_task(name: str) -> Task:
    key = TASK_ALIASES.get(name, name)
    if key not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {', '.join(TASKS)}")
    return TASKS[key]


def get_condition(name: str) -> Condition:
    if name not in CONDITIONS:
        raise ValueError(f"unknown condition {name!r}; choose one of {', '.join(CONDITIONS)}")
    return CONDITIONS[name]


def get_suite(name: str) -> tuple[str, ...]:
    if name not in SUITES:
        raise ValueError(f"unknown suite {name!r}; choose one of {', '.join(SUITES)}")
    return SUITES[name]


# ----- route files -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RouteSpec:
    id: int
    start: Pose
    goal: Pose
    length_m: float
    turns: tuple[str, ...]  # junction manoeuvres in order: LEFT / RIGHT / STRAIGHT
    kind: str = ""  # square tasks: corner / t_junction / crossing; empty otherwise

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "id": self.id,
            "start": {"x": round(self.start.x, 3), "y": round(self.start.y, 3), "yaw": round(self.start.yaw, 5)},
            "goal": {"x": round(self.goal.x, 3), "y": round(self.goal.y, 3), "yaw": round(self.goal.yaw, 5)},
            "length_m": round(self.length_m, 2),
            "turns": list(self.turns),
        }
        if self.kind:
            d["kind"] = self.kind
        return d


# Minimum route lengths in metres per (town, route list). Navigation's are the paper's; the others are ours.
MIN_LENGTH: dict[str, dict[str, float]] = {
    "town01": {"straight": 80.0, "one_turn": 80.0, "navigation": 1000.0},
    "town02": {"straight": 60.0, "one_turn": 60.0, "navigation": 300.0},
}
STRAIGHT_MAX_HEADING_DEG = 30.0
TURN_NAMES = ("LEFT", "RIGHT", "STRAIGHT")


def _pose(obj: Any, where: str) -> Pose:
    if not isinstance(obj, dict) or set(obj) != {"x", "y", "yaw"}:
        raise ValueError(f"{where}: expected an object with x, y, yaw, got {obj!r}")
    vals = []
    for k in ("x", "y", "yaw"):
        v = obj[k]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(float(v)):
            raise ValueError(f"{where}.{k}: expected a finite number, got {v!r}")
        vals.append(float(v))
    return Pose(*vals)


def parse_route(obj: Any, where: str) -> RouteSpec:
    """One route entry of a route file, checked field by field."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected an object, got {type(obj).__name__}")
    for k in ("id", "start", "goal", "length_m", "turns"):
        if k not in obj:
            raise ValueError(f"{where}: missing field {k!r}")
    rid = obj["id"]
    if not isinstance(rid, int) or isinstance(rid, bool) or rid < 0:
        raise ValueError(f"{where}.id: expected an integer >= 0, got {rid!r}")
    length = obj["length_m"]
    if not isinstance(length, (int, float)) or isinstance(length, bool) or not (math.isfinite(length) and length > 0):
        raise ValueError(f"{where}.length_m: expected a positive number of metres, got {length!r}")
    turns = obj["turns"]
    if not isinstance(turns, list) or any(t not in TURN_NAMES for t in turns):
        raise ValueError(f"{where}.turns: expected a list of {'/'.join(TURN_NAMES)}, got {turns!r}")
    kind = obj.get("kind", "")
    if not isinstance(kind, str):
        raise ValueError(f"{where}.kind: expected a string, got {kind!r}")
    return RouteSpec(rid, _pose(obj["start"], f"{where}.start"), _pose(obj["goal"], f"{where}.goal"), float(length), tuple(turns), kind)


def check_task_routes(town: str, name: str, routes: Sequence[RouteSpec], where: str) -> None:
    """The protocol's rules on a route list: count, ids in order, lengths, turn structure."""
    expected = SQUARE_TASKS if name == "square" else ROUTES_PER_TASK
    if len(routes) != expected:
        raise ValueError(f"{where}: {len(routes)} routes, the protocol needs {expected}")
    for i, r in enumerate(routes):
        if r.id != i:
            raise ValueError(f"{where}[{i}]: id {r.id}, expected {i} (ids are positions)")
        minimum = MIN_LENGTH.get(town, {}).get(name, 0.0)
        if r.length_m < minimum:
            raise ValueError(f"{where}[{i}]: length {r.length_m:.1f} m < the minimum {minimum:.0f} m for {name} in {town}")
        n_lr = sum(t in ("LEFT", "RIGHT") for t in r.turns)
        if name == "straight" and n_lr:
            raise ValueError(f"{where}[{i}]: a straight route has turns {r.turns}")
        if name == "one_turn" and n_lr != 1:
            raise ValueError(f"{where}[{i}]: a one-turn route needs exactly one LEFT/RIGHT, has {r.turns}")
    starts = {(r.start, r.goal) for r in routes}
    if len(starts) != len(routes) and name != "square":
        raise ValueError(f"{where}: routes repeat (same start and goal)")


def route_file(town: str, folder: Path | None = None) -> Path:
    return (folder or ROUTES_DIR) / f"{town}.json"


def load_routes(town: str, folder: Path | None = None) -> dict[str, list[RouteSpec]]:
    """The route lists of a town's committed file, validated against the protocol (not the planner)."""
    path = route_file(town, folder)
    if not path.exists():
        if folder is not None and Path(folder).resolve() == _CARLA_ROUTES_DIR.resolve():
            raise ValueError(f"no CARLA route file for town {town!r} at {path}; `yawil bench --backend carla` makes it "
                             f"from the server's map on first connect, or make it with `python -m yawil.bench.carla_routes "
                             f"--xodr {town.capitalize()}.xodr --town {town}` (no server) or `--host HOST --town {town}`")
        raise ValueError(f"no route file for town {town!r} at {path}; generate it with `yawil bench routes --town {town}`")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(doc, dict) or doc.get("format") != ROUTE_FORMAT:
        raise ValueError(f"{path}: field 'format' must be {ROUTE_FORMAT!r}")
    if doc.get("town") != town:
        raise ValueError(f"{path}: field 'town' is {doc.get('town')!r}, expected {town!r}")
    lists = doc.get("routes")
    if not isinstance(lists, dict) or not lists:
        raise ValueError(f"{path}: field 'routes' must map route-list names to lists")
    out: dict[str, list[RouteSpec]] = {}
    for name, items in lists.items():
        if not isinstance(items, list):
            raise ValueError(f"{path}: routes.{name} must be a list")
        specs = [parse_route(o, f"{path}: routes.{name}[{i}]") for i, o in enumerate(items)]
        check_task_routes(town, name, specs, f"{path}: routes.{name}")
        out[name] = specs
    return out


# ----- episodes ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Episode:
    """One episode of a run: what to drive, where, in which weather, with which seed."""

    suite: str
    task: str
    condition: str
    route: RouteSpec
    seed: int  # the run's seed index (0..n-1)
    town: str
    weather: str
    vehicles: int
    pedestrians: int

    @property
    def route_id(self) -> int:
        return self.route.id

    @property
    def key(self) -> str:
        """task/condition/weather/route/seed: `yawil.bench.records.episode_key` of its record."""
        return f"{self.task}/{self.condition}/{self.weather}/{self.route.id}/{self.seed}"

    @property
    def world_seed(self) -> int:
        """Seed of the world and agent: 1000 * seed + route id (stable, readable). The weathers of one route
        and seed share it, so traffic and agent noise are the same and weather is the only difference."""
        return 1000 * self.seed + self.route.id

    @property
    def timeout_s(self) -> float:
        return timeout_for(self.route.length_m, TASKS[self.task].timeout)

    def scenario(self, camera: bool) -> Scenario:
        return Scenario(
            town=self.town,
            start=self.route.start,
            goal=self.route.goal,
            weather=self.weather,
            vehicles=self.vehicles,
            pedestrians=self.pedestrians,
            timeout_s=self.timeout_s,
            camera=camera,
        )


def parse_range(spec: str | None, n: int) -> list[int]:
    """Route ids selected by 'a:b' (Python slice), 'a,b,c', or None (all)."""
    if spec is None or spec == "":
        return list(range(n))
    try:
        if ":" in spec:
            parts = [int(p) if p.strip() else None for p in spec.split(":")]
            if len(parts) > 3:
                raise ValueError
            chosen = list(range(n))[slice(*parts)]
            if not chosen:  # '5:2' or '30:' selected nothing: a benchmark of 0 episodes is a typo, not a result
                raise ValueError(f"--routes {spec!r} selects no route of 0..{n - 1}")
            return chosen
        ids = [int(p) for p in spec.split(",")]
    except ValueError as err:
        if "selects no route" in str(err):
            raise
        raise ValueError(f"--routes {spec!r}: expected a slice like 0:5 or a list like 1,4,7") from None
    bad = [i for i in ids if not 0 <= i < n]
    if bad:
        raise ValueError(f"--routes {spec!r}: ids {bad} outside 0..{n - 1}")
    return ids


def episodes(
    suite: str,
    conditions: Sequence[str] | None = None,
    tasks: Sequence[str] | None = None,
    routes: str | None = None,
    seeds: int | None = None,
    routes_folder: Path | None = None,
    weather_rule: str = "all",
) -> list[Episode]:
    """Every episode of a run, in a fixed order (condition, task, seed, route, weather); no key repeats.

    `seeds` None gives the protocol's count per task (5 static, 3 dynamic); a number overrides it for all.
    `weather_rule` "all" drives every route in every weather of its condition (the protocol); "cycle" route i
    in weather i mod n only (a quarter of the episodes: the preset eval100's comparisons of recipes).
    """
    if weather_rule not in WEATHER_RULES:
        raise ValueError(f"unknown weather rule {weather_rule!r}; choose one of {', '.join(WEATHER_RULES)}")
    suite_tasks = get_suite(suite)
    conds = list(conditions) if conditions else list(SUITE_CONDITIONS[suite])
    names = [get_task(t).name for t in tasks] if tasks else list(suite_tasks)
    for t in names:
        if t not in suite_tasks:
            raise ValueError(f"task {t!r} is not in suite {suite!r} ({', '.join(suite_tasks)})")
    if seeds is not None and seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {seeds}")
    out: list[Episode] = []
    seen: set[str] = set()
    for cname in conds:
        cond = get_condition(cname)
        if cname not in SUITE_CONDITIONS[suite]:
            raise ValueError(f"condition {cname!r} is not one of suite {suite!r} ({', '.join(SUITE_CONDITIONS[suite])})")
        for w in cond.weathers:
            get_weather(w)
        lists = load_routes(cond.town, routes_folder)
        for tname in names:
            task = TASKS[tname]
            if task.routes not in lists:
                raise ValueError(f"route file of {cond.town} has no {task.routes!r} list")
            specs = lists[task.routes]
            ids = parse_range(routes, len(specs))
            vehicles, pedestrians = task.traffic(cond.town)
            for seed in range(seeds if seeds is not None else task.default_seeds):
                for rid in ids:
                    for weather in cond.weathers_for(rid, weather_rule):
                        ep = Episode(suite, tname, cname, specs[rid], seed, cond.town, weather, vehicles, pedestrians)
                        if ep.key not in seen:
                            seen.add(ep.key)
                            out.append(ep)
    return out
