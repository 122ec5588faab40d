"""Benchmark route files for CARLA's Town01 and Town02, and their generator.

Same format as yawil's own route files (`yawil-routes/1`: 25 routes per task list straight, one_turn,
navigation, start and goal as map coordinates in yawil's frame), so `yawil.bench.suites.load_routes(town,
folder=CARLA_ROUTES_DIR)` reads them. They need the real map, which comes from one of two sources:
a live server (`python -m yawil.bench.carla_routes --host HOST --port 2000 --town town01`) or, with no
server, CARLA's own OpenDRIVE file of the town (`--xodr Town01.xodr --town town01`): `carla.Map(name,
xodr_text)` builds the same map client-side that the server hands out, minus traffic-light actors (which
route files do not store). The rules are the embedded towns' (yawil.bench.routegen): routes are drawn as
walks on the topology, re-planned from their end points exactly as CarlaWorld will plan them, and
classified by `yawil.bench.routegen.classify`. A generated file is validated against the map (every start
and goal snaps to a driving lane within 2 m, every goal is reachable, lengths match) and records its
source (`source`: kind, map name, the xodr's sha256, the carla client version) so a later check can tell
which map it was made from. It lives in yawil.bench, not beside the CARLA backend, because it makes
benchmark data: it reads the CARLA map through yawil.sim.carla and writes the benchmark's route format.
`connect.py` finds, makes and checks a town's file when `yawil bench --backend carla` connects.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any

import numpy as np

from yawil.fileio import write_json_atomic
from yawil.sim.carla.topology import CarlaTopology
from yawil.sim.types import Pose, RoadOption, Route

CARLA_ROUTES_DIR = Path(__file__).parent
SNAP_TOLERANCE_M = 2.0
MAX_ATTEMPTS = 20000  # candidates per task before generate_routes gives up
TOWNS = ("town01", "town02")


def _endpoints(route: Route) -> tuple[Pose, Pose]:
    xy, yaw = route.xy, route.lane_yaw
    return Pose(float(xy[0, 0]), float(xy[0, 1]), float(yaw[0])), Pose(float(xy[-1, 0]), float(xy[-1, 1]), float(yaw[-1]))


def _walk(topo: CarlaTopology, rng: np.random.Generator, want: str) -> Route | None:
    """A candidate: a road segment followed through 0-3 junctions, straight only or with one LEFT/RIGHT."""
    roads = [i for i, s in enumerate(topo.segments) if not s.junction and s.length > 5.0]
    seq = [roads[int(rng.integers(len(roads)))]]
    for _ in range(int(rng.integers(0, 4)) * 3):
        succ = [int(d["segment"]) for _, _, d in topo.graph.out_edges(topo.segments[seq[-1]].exit, data=True)]
        if not succ:
            break
        seq.append(succ[int(rng.integers(len(succ)))])
    while len(seq) > 1 and topo.segments[seq[-1]].junction:
        seq.pop()
    turns = [o for o in topo.turn_decisions(seq) if o in (RoadOption.LEFT, RoadOption.RIGHT)]
    if (want == "straight" and turns) or (want == "one_turn" and len(turns) != 1):
        return None
    first, last = topo.segments[seq[0]], topo.segments[seq[-1]]
    ss, sg = float(rng.uniform(0.05, 0.5) * first.length), float(rng.uniform(0.5, 0.95) * last.length)
    if len(seq) == 1 and sg <= ss + 1.0:
        return None
    return topo.sample(seq, ss, sg).route


def generate_routes(topo: CarlaTopology, town: str, seed: int = 0, per_task: int | None = None,
                    max_attempts: int | None = None) -> dict[str, list[Any]]:
    """Route lists straight, one_turn, navigation for a CARLA town, drawn on its topology from the seed.

    Gives up after `max_attempts` candidates per task (default MAX_ATTEMPTS) with a ValueError saying how far
    it got and the longest candidate seen: a map too small for the town's rules is the usual cause.
    """
    from yawil.bench.routegen import accept_route
    from yawil.bench.suites import MIN_LENGTH, ROUTES_PER_TASK, RouteSpec

    if town not in TOWNS:
        raise ValueError(f"no route rules for CARLA town {town!r}; choose one of {', '.join(TOWNS)}")
    n = per_task or ROUTES_PER_TASK
    attempts = MAX_ATTEMPTS if max_attempts is None else max_attempts
    if isinstance(attempts, bool) or not isinstance(attempts, int) or attempts < 1:
        raise ValueError(f"max_attempts must be a positive integer, got {attempts!r}")
    rng = np.random.default_rng(seed)
    out: dict[str, list[Any]] = {}
    for kind in ("straight", "one_turn", "navigation"):
        minimum = MIN_LENGTH[town][kind]
        specs: list[Any] = []
        seen: set[tuple[int, int, int, int]] = set()
        longest = 0.0
        for _ in range(attempts):
            cand = topo.random_route(rng, minimum).route if kind == "navigation" else _walk(topo, rng, kind)
            if cand is None:
                continue
            start, goal = _endpoints(cand)
            route = topo.plan(start, goal).route  # what CarlaWorld will drive
            longest = max(longest, route.length)
            names = accept_route(route, start, goal, kind, minimum, seen)
            if names is None:
                continue
            specs.append(RouteSpec(len(specs), start, goal, round(route.length, 2), names))
            if len(specs) == n:
                break
        else:
            raise ValueError(f"could not draw {n} {kind} routes of >= {minimum:.0f} m on CARLA {town} (map {topo.name!r}) "
                             f"in {attempts} attempts: got {len(specs)}, the longest candidate as planned was "
                             f"{longest:.0f} m (is this {town}'s map?)")
        out[kind] = specs
    return out


def validate_routes(topo: CarlaTopology, lists: dict[str, list[Any]], where: str) -> None:
    """Every start/goal snaps to a driving lane within 2 m, every goal is reachable, every length matches within 1 %.

    The first route that does not fit is a ValueError naming `where`, the route and the figure.
    """
    for name, specs in lists.items():
        for spec in specs:
            route = f"{where}: routes.{name}[{spec.id}]"
            for end, pose in (("start", spec.start), ("goal", spec.goal)):
                try:
                    d = topo.snap(pose)[2]
                except ValueError as err:
                    raise ValueError(f"{route}.{end}: {err}") from None
                if d > SNAP_TOLERANCE_M:
                    raise ValueError(f"{route}.{end} {pose} is {d:.1f} m from the nearest driving "
                                     f"lane of map {topo.name!r} (at most {SNAP_TOLERANCE_M} m allowed)")
            try:
                length = topo.plan(spec.start, spec.goal).route.length
            except ValueError as err:
                raise ValueError(f"{route}: {err}") from None
            if not math.isclose(length, spec.length_m, rel_tol=0.01, abs_tol=1.0):
                raise ValueError(f"{route} is {length:.1f} m on this map, the file says "
                                 f"{spec.length_m:.1f} m (a different map version?)")


def client_version() -> str:
    """The installed `carla` client package's version (the wheel's metadata; the module has no __version__)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("carla")
    except PackageNotFoundError:
        raise ValueError("the `carla` client package is not installed: pip install -c constraints.txt carla==0.9.16") from None


def topology_from_xodr(path: str | Path, town: str) -> tuple[CarlaTopology, dict[str, Any]]:
    """The real map of `town` built client-side from CARLA's OpenDRIVE file, and the route file's `source` record."""
    import carla

    from yawil.sim.carla.world import carla_town

    if town not in TOWNS:
        raise ValueError(f"no route rules for CARLA town {town!r}; choose one of {', '.join(TOWNS)}")
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as err:
        raise ValueError(f"{p}: cannot read the OpenDRIVE file ({err.strerror or err})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{p}: an OpenDRIVE file is UTF-8 XML; byte {err.start} is not UTF-8") from None
    if "<OpenDRIVE" not in text[:4096]:
        raise ValueError(f"{p}: no <OpenDRIVE> element near the start; expected CARLA's {carla_town(town)}.xodr")
    try:
        cmap = carla.Map(carla_town(town), text)
    except RuntimeError as err:
        raise ValueError(f"{p}: carla.Map cannot build a map from this OpenDRIVE file ({err})") from None
    try:
        topo = CarlaTopology.from_carla_map(cmap)
    except ValueError as err:
        raise ValueError(f"{p}: {err}") from None
    source = {"kind": "xodr", "map": topo.name, "xodr_file": p.name, "xodr_sha256": hashlib.sha256(data).hexdigest(),
              "carla_client": client_version()}
    return topo, source


def write_route_file(topo: CarlaTopology, town: str, seed: int = 0, folder: Path | None = None,
                     per_task: int | None = None, source: dict[str, Any] | None = None,
                     max_attempts: int | None = None) -> Path:
    """Generate, check and atomically write `<folder>/<town>.json` (default: this package's folder).

    `source` says which map made the file (`topology_from_xodr`'s record, or a server's); it is stored as is.
    """
    from yawil.bench.suites import ROUTE_FORMAT, check_task_routes

    lists = generate_routes(topo, town, seed, per_task, max_attempts)
    if per_task is None:
        for name, specs in lists.items():
            check_task_routes(town, name, specs, f"generated CARLA {town}.{name}")
    validate_routes(topo, lists, f"generated CARLA {town}")
    src = dict(source) if source is not None else {"kind": "map", "map": topo.name}
    if src.get("kind") == "xodr":
        how = f"--xodr {src.get('xodr_file', 'PATH')}"
    elif src.get("kind") == "server":
        how = "--host HOST --port PORT"
    else:
        how = "(a carla.Map given in Python)"
    path = (folder or CARLA_ROUTES_DIR) / f"{town}.json"
    write_json_atomic(path, {
        "format": ROUTE_FORMAT, "town": town, "map": topo.name, "source": src,
        "generated_by": f"python -m yawil.bench.carla_routes {how} --town {town} --seed {seed}",
        "rules": "docs/benchmark.md#routes",
        "routes": {name: [s.to_json() for s in specs] for name, specs in lists.items()},
    })
    return path


def load_carla_routes(town: str, folder: Path | None = None) -> tuple[dict[str, list[Any]], dict[str, Any]]:
    """A CARLA route file's lists (checked against the protocol) and its `source` record, without any map.

    Checks what needs no map: the protocol's counts, lengths and turn structure (`load_routes`), the
    `source` record (its kind and map name fit the town), and that no route starts where it ends.
    """
    import json

    from yawil.bench.suites import load_routes, route_file
    from yawil.sim.carla.world import carla_town

    if town not in TOWNS:
        raise ValueError(f"no CARLA route file for town {town!r}; choose one of {', '.join(TOWNS)}")
    path = route_file(town, folder or CARLA_ROUTES_DIR)
    if not path.exists():
        raise ValueError(f"no CARLA route file for {town} at {path}; make it with `python -m yawil.bench.carla_routes "
                         f"--xodr {carla_town(town)}.xodr --town {town}` (no server needed) or `--host HOST --town {town}`")
    lists = load_routes(town, path.parent)
    src = json.loads(path.read_text(encoding="utf-8")).get("source")
    if not isinstance(src, dict) or src.get("kind") not in ("xodr", "server", "map"):
        raise ValueError(f"{path}: field 'source' must be an object with kind 'xodr', 'server' or 'map', got {src!r}")
    if str(src.get("map", "")).rsplit("/", 1)[-1] != carla_town(town):
        raise ValueError(f"{path}: source.map is {src.get('map')!r}, expected {carla_town(town)!r} for {town}")
    if src["kind"] == "xodr":
        sha = src.get("xodr_sha256")
        if not (isinstance(sha, str) and len(sha) == 64 and all(c in "0123456789abcdef" for c in sha)):
            raise ValueError(f"{path}: source.xodr_sha256 must be 64 lowercase hex digits, got {sha!r}")
    for name, specs in lists.items():
        for spec in specs:
            if math.hypot(spec.goal.x - spec.start.x, spec.goal.y - spec.start.y) < 1.0:
                raise ValueError(f"{path}: routes.{name}[{spec.id}] starts where it ends ({spec.start})")
    return lists, src
