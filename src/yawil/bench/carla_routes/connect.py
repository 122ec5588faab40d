"""The route file of a town, found or made on connect, and checked against the server's map before driving.

`yawil bench --backend carla` calls `prepare_route_file` once per town, after connecting: the first run on a
machine without a committed file generates it from the server's own map (seed 0, the same generator as
`python -m yawil.bench.carla_routes`) and writes it atomically to a user folder; every later run finds that
file, checks it against the server (start and goal within 2 m of a driving lane, goal reachable, length
within 1 %) and drives the same episodes. A file that does not fit the server's map stops the run before
any episode, naming the file, the route and the figure.

Where a town's file is looked for, in order: `--routes-dir` when given, else the package's committed
folder then the user folder (`$XDG_CACHE_HOME/yawil/carla_routes`, default `~/.cache/yawil/carla_routes`).
When none has it, it is written to `--routes-dir` when given, else to the user folder.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from yawil.bench.carla_routes import (
    CARLA_ROUTES_DIR,
    TOWNS,
    client_version,
    load_carla_routes,
    validate_routes,
    write_route_file,
)

SEED = 0  # the seed of a route file made on connect: every machine draws the same routes from the same map


def user_routes_dir() -> Path:
    """Where route files made on connect go when no --routes-dir is given."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "yawil" / "carla_routes"


def route_folders(routes_dir: Path | None = None) -> list[Path]:
    """The folders searched for a town's file, first match wins (see the module docstring)."""
    if routes_dir is not None:
        return [Path(routes_dir)]
    return [CARLA_ROUTES_DIR, user_routes_dir()]


def find_route_file(town: str, routes_dir: Path | None = None) -> Path | None:
    """The route file of `town` that a run would use, or None when it has to be made."""
    for folder in route_folders(routes_dir):
        path = folder / f"{town}.json"
        if path.exists():
            return path
    return None


def prepare_route_file(world: Any, town: str, routes_dir: Path | None = None,
                       log: Callable[[str], None] = print) -> Path:
    """The checked route file of `town` for the connected `world` (a CarlaWorld), made from its map if missing.

    Loads the town on the server (CarlaWorld.topology_of). ValueError when the file found does not fit the
    server's map or when generation fails; nothing is written in either case.
    """
    from yawil.sim.carla.world import carla_town

    if town not in TOWNS:
        raise ValueError(f"no CARLA route rules for town {town!r}; the CARLA benchmark drives {', '.join(TOWNS)}")
    topo = world.topology_of(carla_town(town))
    path = find_route_file(town, routes_dir)
    if path is None:
        folder = Path(routes_dir) if routes_dir is not None else user_routes_dir()
        looked = " or ".join(str(f) for f in route_folders(routes_dir))
        # CarlaWorld refused to connect unless server and client versions agree, so one version is recorded
        source = {"kind": "server", "map": topo.name, "address": world.address, "carla_client": client_version()}
        try:
            path = write_route_file(topo, town, SEED, folder, source=source)
        except ValueError as err:
            raise ValueError(f"no route file for {town} in {looked}, and making one from the map {topo.name!r} of "
                             f"the server at {world.address} failed (nothing written): {err}") from None
        log(f"{town}: no route file in {looked}; made one from the server's map {topo.name} at {world.address} "
            f"(seed {SEED}) and wrote {path}. Later runs reuse it (checked against the server each time); commit it "
            f"to {CARLA_ROUTES_DIR} or share it (--routes-dir) so that others drive the same routes.")
    lists, src = load_carla_routes(town, path.parent)
    try:
        validate_routes(topo, lists, str(path))
    except ValueError as err:
        raise ValueError(f"{err}. The route file does not fit the map {topo.name!r} of the server at {world.address} "
                         f"(file made from {_describe(src)}); to drive this server, make a file from it with "
                         f"`python -m yawil.bench.carla_routes --host HOST --port PORT --town {town} --out DIR` "
                         f"and pass --routes-dir DIR") from None
    n = sum(len(v) for v in lists.values())
    log(f"{town}: {path} fits the server's map {topo.name} ({n} routes: start and goal within 2 m of a lane, "
        f"lengths within 1 %)")
    return path


def _describe(source: dict[str, Any]) -> str:
    if source.get("kind") == "xodr":
        return f"{source.get('xodr_file')} (sha256 {str(source.get('xodr_sha256'))[:12]}...)"
    if source.get("kind") == "server":
        return f"the server at {source.get('address')} (carla {source.get('carla_client')})"
    return f"map {source.get('map')!r}"
