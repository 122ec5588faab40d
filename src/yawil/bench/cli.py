"""`yawil bench`: run a suite (default action), or generate / validate the committed route files.

    yawil bench --suite nocrash --condition new-town-weather --agent runs/yilratt/best.pt --out results/yilratt
    yawil bench routes --town town01          # regenerate src/yawil/bench/routes/town01.json
    yawil bench validate --town town02        # check a route file against the current planner
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from yawil.cliargs import given_options, seed


class ChoiceHelp(argparse.Action):
    """-h/--help that prints the help of the positional choice given before it (`yawil bench routes --help`),
    else the whole command's. The choices stay one positional argument (no sub-parsers), so that options
    may come before or after it as they always could; each choice with its own help has a parser that only
    prints it, built from the same option definitions as the command."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, *, choice_dest: str,
                 helps: dict[str, Callable[[str], argparse.ArgumentParser]], help: str | None = None) -> None:
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0, help=help)
        self.choice_dest = choice_dest
        self.helps = helps

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        build = self.helps.get(getattr(namespace, self.choice_dest, None) or "")
        (build(f"{parser.prog} ") if build else parser).print_help()
        parser.exit()


def add_choice_help(p: argparse.ArgumentParser, choice_dest: str, descriptions: dict[str, str],
                    add_options: Callable[[argparse.ArgumentParser, str], None]) -> None:
    """Give `p` (made with add_help=False) a -h/--help that knows the choice of its positional `choice_dest`:
    each choice's help is a parser with its description and the options `add_options(parser, choice)` adds."""

    def parser_of(choice: str) -> Callable[[str], argparse.ArgumentParser]:
        def build(prog: str) -> argparse.ArgumentParser:
            sub = argparse.ArgumentParser(prog=f"{prog}{choice}", description=descriptions[choice])
            add_options(sub, choice)
            return sub

        return build

    helps = {choice: parser_of(choice) for choice in descriptions}
    p.add_argument("-h", "--help", action=ChoiceHelp, choice_dest=choice_dest, helps=helps,
                   help=f"show this help message and exit; after {' or '.join(helps)}: that one's help")


_ROUTE_ACTIONS: dict[str, str] = {
    "routes": "Generate the route file of each town (src/yawil/bench/routes/<town>.json, or --routes-dir) with "
    "the current planner.",
    "validate": "Re-plan every route of each town's route file with the current planner: reachable, same length, "
    "turns and class; fails naming the first route that no longer matches.",
}


def _add_route_options(p: argparse.ArgumentParser | argparse._ArgumentGroup, action: str | None) -> None:
    """The options of `routes` (action='routes'), `validate`, or both (None, on the command itself)."""
    prefix = "" if action else "routes/validate: "
    p.add_argument("--town", default=None, help=f"{prefix}town01 | town02 | square (default: all three)")
    p.add_argument("--routes-dir", default=None, help=f"{prefix}folder of route files (default: the package's)")
    if action in (None, "routes"):
        p.add_argument("--seed", type=seed, default=None,  # None: not given (a run refuses it), 0 for routes
                       help=f"{'routes: ' if action is None else ''}seed of the route draw (default 0)")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    from yawil.policy.speed import add_engine_arguments, add_speed_control_arguments

    p = subparsers.add_parser(
        "bench",
        help="run the CoRL2017 / NoCrash / square benchmark suites; manage route files",
        description="Run benchmark episodes (one JSON line each in OUT/episodes.jsonl, resumable), or "
        "`routes` to generate the route files, `validate` to check them with the current planner.",
        add_help=False,
    )
    add_choice_help(p, "action", _ROUTE_ACTIONS, _add_route_options)
    p.add_argument("action", nargs="?", default="run", choices=("run", "routes", "validate"),
                   help="run (default): drive the episodes; routes, validate: the route files")
    p.add_argument("--suite", default=None,
                   help="corl2017 | nocrash | nocrash-original | all | square | selection (default nocrash; docs/benchmark.md)")
    p.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help="a fixed episode set: eval100 = all five tasks x 10 routes x both conditions, seed 0, each "
                        "route in one weather (100 episodes, for comparing training recipes; docs/training.md)")
    p.add_argument(
        "--condition",
        action="append",
        default=None,
        help="training | new-weather | new-town | new-town-weather (square for the square suite); repeat or "
        "comma-separate; default: all of the suite's",
    )
    p.add_argument("--agent", default="expert", help="'expert', a checkpoint path or zoo:NAME (yawil zoo list; default expert)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda", "auto"),
                   help="where a learned agent's model runs (default cpu; auto: cuda when torch sees one); each "
                        "worker process loads its own copy (docs/scale.md)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per episode (default: protocol, 5 static / 3 dynamic)")
    p.add_argument("--workers", type=int, default=1, help="processes driving episodes in parallel (default 1)")
    from yawil.executor import add_executor_arguments

    add_executor_arguments(p)
    p.add_argument("--out", default=None, help="results folder (default results/<agent name>)")
    p.add_argument("--label", default=None, help="column name in reports (default: the folder name)")
    p.add_argument("--tasks", default=None, help="comma-separated subset of the suite's tasks")
    p.add_argument("--routes", default=None, help="route ids, as a slice 0:5 or a list 1,4,7")
    p.add_argument("--weather-rule", default=None, choices=("all", "cycle"),
                   help="all (default, the protocol): every route in every weather of its condition; "
                        "cycle: route i in weather i mod n only")
    p.add_argument(
        "--camera",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="render the camera (default: on for learned agents, off for the expert, which needs no pixels)",
    )
    p.add_argument("--record", action="store_true", help="save a video per episode (camera + bird's-eye) in OUT/videos")
    p.add_argument("--yaw-noise-deg", type=float, default=0.0, help="Gaussian noise sigma on guidance yaw (degrees)")
    p.add_argument("--command-noise-p", type=float, default=0.0,
                   help="wrong-command noise level p, read as --command-noise says (bursts of 5 frames)")
    p.add_argument("--yaw-noise", default="raw", choices=("raw", "independent"),
                   help="reading of --yaw-noise-deg: raw (default) on the route headings before the reference is "
                        "subtracted; independent: on each guidance component after it")
    p.add_argument("--command-noise", default="burst-start", choices=("burst-start", "frame-share"),
                   help="reading of --command-noise-p: burst-start (default) a 5-frame burst starts with p on each "
                        "quiet frame; frame-share: a share p of all frames is wrong, in 5-frame bursts")
    add_speed_control_arguments(p)
    add_engine_arguments(p, batched=True)
    p.add_argument("--expert-arg", action="append", default=[], metavar="KEY=VALUE",
                   help="--agent expert: a setting of its ExpertConfig (docs/expert.md), e.g. comfort_decel=1.5; "
                        "repeat for more")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--backend", default="embedded", choices=("embedded", "carla"), help="simulator (default embedded)")
    from yawil.sim.carla.connection import add_connection_arguments

    add_connection_arguments(p, note="map loads get at least 60")
    from yawil.sim.carla.servers import add_servers_argument

    add_servers_argument(p)
    _add_route_options(p, None)
    return p


# Fixed episode sets, each one documented command: the settings it fixes.
PRESETS: dict[str, dict[str, Any]] = {
    "eval100": {"suite": "all", "condition": ["training,new-town-weather"], "routes": "0:10", "seeds": 1,
                "weather_rule": "cycle"},
}


def apply_preset(args: argparse.Namespace) -> None:
    """Fill in a preset's settings; one also given on the command line is an error (which would win?)."""
    if args.preset is None:
        if args.suite is None:
            args.suite = "nocrash"
        return
    for key, value in PRESETS[args.preset].items():
        if getattr(args, key) is not None:
            raise ValueError(f"--preset {args.preset} fixes --{key.replace('_', '-')} ({value}); do not give it too")
        setattr(args, key, value)


def _split(values: list[str] | None) -> list[str] | None:
    if not values:
        return None
    return [v.strip() for item in values for v in item.split(",") if v.strip()]


ROUTE_OPTIONS = {"routes": {"town", "routes_dir", "seed"}, "validate": {"town", "routes_dir"}}


def check_route_action_options(args: argparse.Namespace) -> None:
    """`bench routes` and `bench validate` read only their own options: any run option given (`--agent`,
    `--workers`, `--out`, ...) is refused in one line instead of doing nothing. Given: not its default."""
    if args.action not in ROUTE_OPTIONS:
        return
    for dest, (flag, value) in given_options(args, add_parser, "bench").items():
        if dest not in ROUTE_OPTIONS[args.action]:
            raise ValueError(f"{flag} {value}: not read by bench {args.action}, which takes "
                             f"{', '.join('--' + o.replace('_', '-') for o in sorted(ROUTE_OPTIONS[args.action]))}")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    try:
        check_route_action_options(args)
        if args.action == "routes":
            from yawil.bench.routegen import check_route_target, write_route_file

            seed = 0 if args.seed is None else args.seed
            towns = [args.town] if args.town else ["town01", "town02", "square"]
            for town in towns:  # every target before any file is written
                check_route_target(town, Path(args.routes_dir) if args.routes_dir else None)
            for town in towns:
                path = write_route_file(town, seed=seed, folder=Path(args.routes_dir) if args.routes_dir else None)
                print(f"wrote {path}")
            return 0
        if args.action == "validate":
            from yawil.bench.routegen import validate_with_planner

            for town in [args.town] if args.town else ["town01", "town02", "square"]:
                n = validate_with_planner(town, folder=Path(args.routes_dir) if args.routes_dir else None)
                print(f"{town}: {n} routes valid")
            return 0
        return _run_suite(args)
    except ValueError as err:
        raise SystemExit(f"yawil bench: {err}") from None


def _run_suite(args: argparse.Namespace) -> int:
    from pathlib import Path

    # route-file options that a run would ignore: its towns follow from the conditions, its seeds are --seeds
    for name, actions, instead in (("town", "routes and validate", "the towns follow from --condition"),
                                   ("seed", "routes", "the episodes' seeds are --seeds")):
        if getattr(args, name, None) is not None:
            raise ValueError(f"--{name} {getattr(args, name)}: applies to bench {actions} only; in a run {instead}")
    if args.label is not None and not args.label.strip():
        raise ValueError(f"--label {args.label!r}: expected a column name (leave --label out for the folder's name)")
    apply_preset(args)
    from yawil.bench.runner import AgentSpec, agent_device, drive_options, run_benchmark
    from yawil.bench.suites import episodes
    from yawil.executor import executor_from_args
    from yawil.sim.carla.connection import check_connection_arguments
    from yawil.sim.carla.servers import server_worlds, servers_for

    check_connection_arguments(args)
    executor = executor_from_args(args)
    servers = servers_for(args.carla_servers, args.workers, args.backend)
    spec = AgentSpec(args.agent, args.yaw_noise_deg, args.command_noise_p, yaw_noise_mode=args.yaw_noise,
                     command_noise_mode=args.command_noise, expert_args=tuple(args.expert_arg),
                     device=agent_device(args.device), engine=args.engine, **drive_options(args)).validate(build=False)
    out = Path(args.out) if args.out else Path("results") / (
        "expert" if spec.is_expert else spec.checkpoint.resolve().parent.name
    )
    from yawil.fileio import check_not_inside_owned

    check_not_inside_owned(out, "--out")  # before a CARLA connection is made
    per_worker = args.episodes_per_worker
    if args.backend != "embedded" and per_worker not in (None, 1):
        raise ValueError(f"--episodes-per-worker {per_worker}: a CARLA server drives one episode at a time; give 1")
    factory: Any = None
    if args.backend != "embedded":
        if args.workers != 1 and servers is None:
            raise ValueError(f"--backend {args.backend} with --workers {args.workers}: give one server per worker "
                             "with --carla-servers HOST:PORT,...")
        if servers is not None:  # the route files are checked on the first server, the same CARLA as the others
            args.host, args.port = servers[0]
        eps, factory, world = _carla_episodes(args)
        if servers is not None:  # each worker connects to its own server; this connection must not hold one
            world.close()
            world, factory = None, server_worlds(servers, args.timeout)
    else:
        world = None
        eps = episodes(
            args.suite,
            conditions=_split(args.condition),
            tasks=_split([args.tasks] if args.tasks else None),
            routes=args.routes,
            seeds=args.seeds,
            routes_folder=Path(args.routes_dir) if args.routes_dir else None,
            weather_rule=args.weather_rule or "all",
        )
    try:
        summary = run_benchmark(
            eps,
            spec,
            out,
            workers=args.workers,
            camera=args.camera,
            record=args.record,
            progress=not args.no_progress,
            label=args.label,
            world_factory=factory,
            executor=executor,
            episodes_per_worker=1 if args.backend != "embedded" else per_worker,
        )
    finally:
        if world is not None:
            world.close()  # the runner closes it too when it drove episodes; closing twice is harmless
    print(
        f"{summary.total} episodes: {summary.skipped} already done, {summary.ran} run now "
        f"({summary.successes} successful) in {summary.wall_s:.1f} s; results in {out}/episodes.jsonl"
    )
    return 0


def _carla_episodes(args: argparse.Namespace) -> tuple[list[Any], Callable[[], Any], Any]:
    """Connect once, find or make each town's route file and check it against the server's map, then the episodes.

    Every town is checked before any episode runs, the first town driven last so that it stays loaded. The
    world that made the checks drives the episodes; after a simulator error the runner gets a new connection.
    """
    from pathlib import Path

    from yawil.bench.carla_routes.connect import prepare_route_file
    from yawil.bench.suites import SUITE_CONDITIONS, episodes, get_condition, get_suite
    from yawil.sim import make_world
    from yawil.sim.carla.connection import connection_from_args
    from yawil.sim.carla.errors import CarlaSetupError
    from yawil.sim.carla.world import carla_town

    get_suite(args.suite)
    conditions = _split(args.condition) or list(SUITE_CONDITIONS[args.suite])
    towns: list[str] = []
    for name in conditions:
        town = get_condition(name).town
        carla_town(town)  # 'square' is embedded-only: a clear error before connecting
        if town not in towns:
            towns.append(town)
    routes_dir = Path(args.routes_dir) if args.routes_dir else None
    try:
        world = make_world("carla", **connection_from_args(args).kwargs())
    except CarlaSetupError as err:
        raise ValueError(str(err)) from None
    try:
        folders = {town: prepare_route_file(world, town, routes_dir).parent for town in reversed(towns)}
        eps: list[Any] = []
        for name in conditions:  # episodes() takes one folder: one call per condition, in the same order
            eps += episodes(
                args.suite,
                conditions=[name],
                tasks=_split([args.tasks] if args.tasks else None),
                routes=args.routes,
                seeds=args.seeds,
                routes_folder=folders[get_condition(name).town],
                weather_rule=args.weather_rule or "all",
            )
    except CarlaSetupError as err:
        world.close()
        raise ValueError(str(err)) from None
    except BaseException:
        world.close()
        raise
    first = [world]

    def factory() -> Any:
        return first.pop() if first else make_world("carla", **connection_from_args(args).kwargs())

    return eps, factory, world
