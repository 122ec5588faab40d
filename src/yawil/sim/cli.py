"""`yawil sim`: look at the embedded simulator (`view`) and its routes (`routes`, `tasks`)."""

from __future__ import annotations

import argparse

from yawil.cliargs import seed

# yawil.sim.weather.WEATHERS, named here so that `--help` needs no import of the simulator
# (tests/test_help.py checks that the two lists agree).
WEATHER_NAMES: tuple[str, ...] = (
    "ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset",  # the training weathers
    "WetCloudyNoon", "SoftRainSunset",  # the test weathers
)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser("sim", help="the embedded simulator: views, routes, turning tasks")
    sub = p.add_subparsers(dest="sim_command", metavar="SUBCOMMAND")
    v = sub.add_parser("view", help="write camera frames and a bird's-eye map of an episode",
                       description="Drive a simple route follower for --steps steps, writing --frames camera "
                       "frames and the bird's-eye map of the episode into --out.")
    v.add_argument("--town", default="town01", help="town01, town02, square or a layout .json path (default town01)")
    v.add_argument("--weather", default="ClearNoon", metavar="WEATHER",
                   help=f"one of {', '.join(WEATHER_NAMES)} (default ClearNoon)")
    v.add_argument("--seed", type=seed, default=0, help="episode seed: route, traffic and pedestrians (default 0)")
    v.add_argument("--vehicles", type=int, default=30, help="vehicles (default 30)")
    v.add_argument("--pedestrians", type=int, default=20, help="pedestrians (default 20)")
    v.add_argument("--steps", type=int, default=30,
                   help="steps to drive (a simple route follower) before the views (default 30)")
    v.add_argument("--frames", type=int, default=3, help="camera frames to write, spread over the steps (default 3)")
    v.add_argument("--render-backend", default="software", choices=("software", "opengl"),
                   help="camera renderer (default software)")
    v.add_argument("--semantic", action="store_true",
                   help="also write the semantic camera's classes, colourised, as semantic_NNNN.png beside each "
                        "camera_NNNN.png (docs/rendering.md lists the classes and colours)")
    v.add_argument("--out", default="view", help="output directory (default view)")
    v.add_argument("--force", action="store_true",
                   help="write into an --out folder that holds other files (same-named ones are replaced)")
    r = sub.add_parser("routes", help="print random routes of a town (start, goal, length, lights)")
    r.add_argument("--town", default="town01")
    r.add_argument("--seed", type=seed, default=0)
    r.add_argument("--count", type=int, default=5)
    r.add_argument("--min-length", type=float, default=0.0)
    t = sub.add_parser("tasks", help="list the turning tasks of a town (the square scene has 32)")
    t.add_argument("--town", default="square")
    return p


def run(args: argparse.Namespace) -> int:
    cmd = getattr(args, "sim_command", None)
    if cmd == "view":
        return _view(args)
    if cmd == "routes":
        return _routes(args)
    if cmd == "tasks":
        return _tasks(args)
    print("usage: yawil sim {view,routes,tasks} ...  (see yawil sim --help)")
    return 2


def follow_route(obs, target_speed: float = 5.0):  # type: ignore[no-untyped-def]
    """A plain pure-pursuit follower (no traffic rules), for views and smoke tests."""
    import math

    from yawil.sim.types import Control

    r, i, p = obs.route, obs.route_index, obs.pose
    j = min(i + max(4, int(obs.speed)), len(r) - 1)
    dx, dy = r.xy[j, 0] - p.x, r.xy[j, 1] - p.y
    alpha = math.remainder(math.atan2(dy, dx) - p.yaw, 2 * math.pi)
    delta = math.atan2(2 * 2.9 * math.sin(alpha), math.hypot(dx, dy) + 1e-6)
    steer = max(-1.0, min(1.0, -delta / math.radians(35)))
    err = target_speed - obs.speed
    return Control(steer, max(0.0, min(1.0, 0.5 * err)), max(0.0, min(1.0, -0.5 * err)))


def _view(args: argparse.Namespace) -> int:

    import matplotlib

    matplotlib.use("Agg")
    from PIL import Image

    from yawil.fileio import atomic_path, check_output_folder, claimed_output_folder
    from yawil.sim.town.render.birdseye import draw_birdseye
    from yawil.sim.town.world import EmbeddedWorld
    from yawil.sim.types import Scenario

    if args.steps < 0 or args.frames < 1:
        raise ValueError(f"--steps must be >= 0 and --frames >= 1, got {args.steps} and {args.frames}")
    from yawil.sim.town.map.layout import resolve_town
    from yawil.sim.weather import get_weather

    resolve_town(args.town)  # both named before a folder is made
    get_weather(args.weather)
    check_output_folder(args.out, "--out", "sim view", args.force)
    with claimed_output_folder(args.out, "sim view") as out:  # a refused scenario leaves no folder
        world = EmbeddedWorld(render_backend=args.render_backend)
        scenario = Scenario(town=args.town, weather=args.weather, vehicles=args.vehicles, pedestrians=args.pedestrians,
                            camera=True, semantic=bool(getattr(args, "semantic", False)))
        written = []
        try:
            obs = world.reset(scenario, args.seed)
            shots = {round(k * args.steps / max(args.frames - 1, 1)) for k in range(args.frames)} if args.frames > 1 else {args.steps}
            for step in range(args.steps + 1):
                if step in shots and obs.image is not None:
                    path = out / f"camera_{step:04d}.png"
                    with atomic_path(path) as tmp:
                        Image.fromarray(obs.image).save(tmp)
                    written.append(path)
                if step in shots and obs.semantic is not None:
                    from yawil.sim.semantic import colorize

                    path = out / f"semantic_{step:04d}.png"
                    with atomic_path(path) as tmp:
                        Image.fromarray(colorize(obs.semantic)).save(tmp)
                    written.append(path)
                if step < args.steps:
                    obs = world.step(follow_route(obs))
            assert world.town is not None
            fig = draw_birdseye(world.town.geometry, route_xy=obs.route.xy, actors=world.actor_views(radius=1e9),
                                ego=world.ego_view(), light_states=world.light_states())
            path = out / "birdseye.png"
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=120)
            written.append(path)
        finally:
            world.close()
    for p in written:
        print(p)
    return 0


def _routes(args: argparse.Namespace) -> int:
    import numpy as np

    from yawil.sim.town.map.planner import random_route, route_endpoints
    from yawil.sim.town.map.town import get_town

    if args.count < 1:
        raise ValueError(f"--count {args.count}: expected an integer >= 1")
    lanes = get_town(args.town).lanes
    rng = np.random.default_rng(args.seed)
    for k in range(args.count):
        planned = random_route(lanes, rng, args.min_length)
        s, g = route_endpoints(planned)
        print(f"{k}: start=({s.x:.1f}, {s.y:.1f}, {s.yaw:.3f}) goal=({g.x:.1f}, {g.y:.1f}, {g.yaw:.3f}) "
              f"length={planned.route.length:.0f} m lights={len(planned.route.lights)}")
    return 0


def _tasks(args: argparse.Namespace) -> int:
    from yawil.sim.town.map.planner import turn_tasks
    from yawil.sim.town.map.town import get_town

    tasks = turn_tasks(get_town(args.town).lanes)
    for t in tasks:
        print(f"{t.name}: {t.kind} {t.direction} ({t.option.name}) start=({t.start.x:.1f}, {t.start.y:.1f}, "
              f"{t.start.yaw:.3f}) goal=({t.goal.x:.1f}, {t.goal.y:.1f}, {t.goal.yaw:.3f})")
    print(f"{len(tasks)} tasks")
    return 0
