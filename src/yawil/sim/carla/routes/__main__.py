"""`python -m yawil.sim.carla.routes`: make (or --check) the CARLA route files from a live server."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m yawil.sim.carla.routes", description=__doc__)
    p.add_argument("--host", default="localhost")
    p.add_argument("--port", type=int, default=2000)
    p.add_argument("--timeout", type=float, default=20.0, help="client time-out in seconds (map loading is slow)")
    p.add_argument("--town", action="append", choices=["town01", "town02"], help="repeatable; default both")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="folder (default: the package's yawil/sim/carla/routes)")
    p.add_argument("--check", action="store_true", help="only validate the existing files against the server's maps")
    args = p.parse_args(argv)
    from pathlib import Path

    from yawil.sim.carla.errors import CarlaSetupError
    from yawil.sim.carla.routes import CARLA_ROUTES_DIR, validate_routes, write_route_file
    from yawil.sim.carla.world import CarlaWorld, carla_town

    folder = Path(args.out) if args.out else CARLA_ROUTES_DIR
    try:
        world = CarlaWorld(host=args.host, port=args.port, timeout=args.timeout)
    except CarlaSetupError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        for town in args.town or ["town01", "town02"]:
            topo = world.topology_of(carla_town(town))
            if args.check:
                from yawil.bench.suites import load_routes

                validate_routes(topo, load_routes(town, folder), str(folder / f"{town}.json"))
                print(f"{town}: every route snaps within 2 m and matches its length on {topo.name}")
            else:
                print(f"{town}: wrote {write_route_file(topo, town, args.seed, folder)}")
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    finally:
        world.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
