"""`python -m yawil.bench.carla_routes`: make (or --check) the CARLA route files from a server or an OpenDRIVE file.

With `--xodr PATH --town townNN` no server is needed: the map is built client-side from CARLA's own
OpenDRIVE file of that town (`carla.Map(name, xodr_text)`). Otherwise the maps come from the server at
--host/--port.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from yawil.cliargs import seed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m yawil.bench.carla_routes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--xodr", default=None, metavar="PATH",
                   help="CARLA's OpenDRIVE file of the town (e.g. Town01.xodr): no server; needs exactly one --town")
    from yawil.sim.carla.connection import add_connection_arguments

    add_connection_arguments(p, timeout=20.0, timeout_help="client time-out in seconds (map loading is slow)", prefix="")
    p.add_argument("--town", action="append", choices=["town01", "town02"], help="repeatable; default both")
    p.add_argument("--seed", type=seed, default=0)
    p.add_argument("--out", default=None, help="folder (default: the package's yawil/bench/carla_routes)")
    p.add_argument("--check", action="store_true", help="only validate the existing files against the map(s)")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="also draw a few routes of each task over the map (with several towns: PNG name gets the town)")
    args = p.parse_args(argv)
    from pathlib import Path

    from yawil.bench.carla_routes import CARLA_ROUTES_DIR

    folder = Path(args.out) if args.out else CARLA_ROUTES_DIR
    towns = args.town or ["town01", "town02"]
    if args.xodr is not None:
        if len(towns) != 1:
            print(f"error: --xodr {args.xodr} is one town's map: give exactly one --town (got {', '.join(towns)})",
                  file=sys.stderr)
            return 2
        return _from_xodr(Path(args.xodr), towns[0], args, folder)
    return _from_server(towns, args, folder)


def _plot(topo: Any, town: str, folder: Any, png: str | None, several: bool) -> None:
    if png is None:
        return
    from pathlib import Path

    from yawil.bench.carla_routes import load_carla_routes
    from yawil.bench.carla_routes.plot import plot_routes

    out = Path(png)
    if several:
        out = out.with_name(f"{out.stem}_{town}{out.suffix or '.png'}")
    print(f"{town}: drew {plot_routes(topo, load_carla_routes(town, folder)[0], out)}")


def _check(topo: Any, town: str, folder: Any, recorded_sha: str | None = None) -> str:
    """Validate the file in `folder` against `topo`; the message to print (ValueError when it does not fit)."""
    from yawil.bench.carla_routes import load_carla_routes, validate_routes

    lists, src = load_carla_routes(town, folder)
    validate_routes(topo, lists, str(folder / f"{town}.json"))
    note = ""
    if recorded_sha is not None and src.get("xodr_sha256") not in (None, recorded_sha):
        note = f" (note: the file was made from an OpenDRIVE file with sha256 {src['xodr_sha256'][:12]}..., not this one)"
    return f"{town}: every route snaps within 2 m and matches its length on {topo.name}{note}"


def _from_xodr(path: Any, town: str, args: argparse.Namespace, folder: Any) -> int:
    from yawil.bench.carla_routes import topology_from_xodr, write_route_file

    try:
        topo, source = topology_from_xodr(path, town)
        if args.check:
            print(_check(topo, town, folder, source["xodr_sha256"]))
        else:
            out = write_route_file(topo, town, args.seed, folder, source=source)
            print(f"{town}: wrote {out} from {path} (sha256 {source['xodr_sha256'][:12]}..., carla {source['carla_client']})")
        _plot(topo, town, folder, args.plot, False)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


def _from_server(towns: list[str], args: argparse.Namespace, folder: Any) -> int:
    from yawil.bench.carla_routes import client_version, write_route_file
    from yawil.sim.carla.connection import connection_from_args
    from yawil.sim.carla.errors import CarlaSetupError
    from yawil.sim.carla.world import CarlaWorld, carla_town

    try:
        world = CarlaWorld(**connection_from_args(args).kwargs())
    except CarlaSetupError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        for town in towns:
            topo = world.topology_of(carla_town(town))
            if args.check:
                print(_check(topo, town, folder))
            else:
                # CarlaWorld refused to connect unless server and client versions agree, so one version is recorded
                source = {"kind": "server", "map": topo.name, "address": world.address, "carla_client": client_version()}
                print(f"{town}: wrote {write_route_file(topo, town, args.seed, folder, source=source)}")
            _plot(topo, town, folder, args.plot, len(towns) > 1)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    finally:
        world.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
