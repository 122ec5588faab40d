"""`yawil collect`: expert driving data for training, resumable, in parallel processes.

Only argparse at module level (the CLI's rule); the collector, the simulator and h5py load inside `run`.
"""

from __future__ import annotations

import argparse
from typing import Any

from yawil.cliargs import seed


def int_range(text: str) -> tuple[int, int]:
    """'30' -> (30, 30); '10-30' -> (10, 30)."""
    try:
        parts = [int(p) for p in text.split("-")] if "-" in text.strip("-") else [int(text)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI (integers), got {text!r}") from None
    lo, hi = (parts[0], parts[0]) if len(parts) == 1 else (parts[0], parts[1])
    if len(parts) > 2 or lo < 0 or hi < lo:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI with 0 <= LO <= HI, got {text!r}")
    return lo, hi


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return v


def _span(r: tuple[int, int]) -> str:
    return str(r[0]) if r[0] == r[1] else f"{r[0]}-{r[1]}"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from yawil.data.collect_config import COLLISION_POLICIES, DEFAULT_FRAMES, CollectConfig

    d = CollectConfig()  # every default below is the dataclass's
    p: argparse.ArgumentParser = subparsers.add_parser(
        "collect",
        help="drive the expert on random routes and record a training dataset",
        description=(
            "Drive the privileged expert on random routes of a town and record camera frames with the expert's "
            "controls, speed, command and the three guidance vectors. Steering noise is applied on about 10% "
            "of the frames (--noise); the label stays the expert's own control. Running the same command again "
            "resumes (episodes already in the dataset are skipped). See docs/expert.md."
        ),
    )
    p.add_argument("--town", default=d.town, help=f"town01, town02, square or a layout JSON file (default {d.town})")
    p.add_argument("--weathers", default="train",
                   help="'train', 'test', 'all' or comma-separated weather names (default train)")
    budget = p.add_argument_group("budget (the first one reached stops the run)")
    budget.add_argument("--frames", type=int, default=None,
                        help=f"stop once the dataset holds this many frames; episodes are stored whole, so the last one may go past it (default {DEFAULT_FRAMES} unless --episodes)")
    budget.add_argument("--episodes", type=int, default=None, help="episode indices 0..N-1 of this seed")
    p.add_argument("--out", required=True, help="dataset directory (created, or resumed); required")
    p.add_argument("--workers", type=int, default=1,
                   help="parallel processes, each running its own simulator (default 1)")
    from yawil.executor import add_executor_arguments

    add_executor_arguments(p)
    p.add_argument("--seed", type=seed, default=0, help="episode ids are seed*100000+index (default 0)")
    p.add_argument("--vehicles", type=int_range, default=d.vehicles, metavar="N|LO-HI",
                   help=f"vehicles per episode: N, or LO-HI drawn uniformly per episode (default {_span(d.vehicles)})")
    p.add_argument("--pedestrians", type=int_range, default=d.pedestrians, metavar="N|LO-HI",
                   help=f"pedestrians per episode: N, or LO-HI drawn uniformly per episode (default {_span(d.pedestrians)})")
    p.add_argument("--min-route-length", type=float, default=d.min_route_length,
                   help=f"metres (default {d.min_route_length:g})")
    p.add_argument("--noise", type=_fraction, default=d.noise_fraction,
                   help=f"fraction of frames with a steering perturbation (default {d.noise_fraction:g})")
    p.add_argument("--noise-amplitude", type=_fraction, default=d.noise_amplitude,
                   help=f"perturbation drawn from U[-a, a] (default {d.noise_amplitude:g})")
    p.add_argument("--straight-keep", type=_fraction, default=d.straight_keep,
                   help=f"fraction of frames kept on long straights (default {d.straight_keep:g})")
    p.add_argument("--blocked-keep-every", type=int, default=d.blocked_keep_every,
                   help=f"keep every Nth frame once stopped for more than {d.blocked_after:g} s "
                        f"(default {d.blocked_keep_every})")
    p.add_argument("--on-collision", choices=COLLISION_POLICIES, default=d.on_collision,
                   help=f"trim: keep the episode without its last {d.trim_seconds:g} s; keep: all frames; discard: drop "
                        f"the episode (default {d.on_collision})")
    from yawil.guidance import REFERENCES, GuidanceConfig

    p.add_argument("--guidance-reference", choices=REFERENCES, default=GuidanceConfig.reference,
                   help="what the yaw guidance is measured against: route (the paper: the first guidance point's "
                        "heading) or ego (the car's own heading, so the vector also tells the heading error); "
                        "models trained on the data drive with the same (default route)")
    p.add_argument("--expert-arg", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting of the expert's ExpertConfig (docs/expert.md), e.g. comfort_decel=1.5; repeat for more "
                        "(stored in the dataset's config, so a resume must give the same)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verify", action="store_true",
                   help="on resume, decode every stored image and re-collect the episodes that fail (a resume always "
                        "re-collects missing, truncated or unreadable episode files)")
    p.add_argument("--backend", default="embedded", choices=("embedded", "carla"), help="simulator (default embedded)")
    from yawil.sim.carla.connection import add_connection_arguments

    add_connection_arguments(p, timeout_help="seconds a client call may take", note="map loads get at least 60")
    from yawil.sim.carla.servers import add_servers_argument

    add_servers_argument(p)
    return p


def config_from_args(args: argparse.Namespace) -> Any:
    """The CollectConfig of the command line (fields it has no flag for keep the dataclass's defaults)."""
    from yawil.data.collect_config import CollectConfig

    return CollectConfig(
        town=args.town, vehicles=args.vehicles, pedestrians=args.pedestrians, min_route_length=args.min_route_length,
        noise_fraction=args.noise, noise_amplitude=args.noise_amplitude, straight_keep=args.straight_keep,
        blocked_keep_every=args.blocked_keep_every, on_collision=args.on_collision,
    )


def _check_carla(town: str, factory: Any) -> None:
    """The CARLA map name and every server answering, before any folder is made: a missing server was a worker's
    traceback (or a C++ abort) after the dataset folder existed."""
    from yawil.sim.carla.errors import CarlaSetupError
    from yawil.sim.carla.world import carla_town

    carla_town(town)
    for make in factory if isinstance(factory, tuple) else (factory,):
        try:
            make().close()
        except CarlaSetupError as err:
            raise ValueError(str(err)) from None


def run(args: argparse.Namespace) -> int:
    from yawil.data.collect import collect
    from yawil.data.collect_config import DEFAULT_FRAMES
    from yawil.expert import ExpertConfig
    from yawil.fileio import check_not_inside_owned
    from yawil.guidance import GuidanceConfig

    check_not_inside_owned(args.out, "--out")  # a dataset inside another's episodes/ is read as part of it
    if args.frames is None and args.episodes is None:
        args.frames = DEFAULT_FRAMES
    expert = ExpertConfig.from_items(args.expert_arg)
    cfg = config_from_args(args)
    from yawil.executor import executor_from_args
    from yawil.sim import world_factory
    from yawil.sim.carla.servers import server_worlds, servers_for

    executor = executor_from_args(args)
    servers = servers_for(args.carla_servers, args.workers, args.backend)
    if args.backend != "embedded" and args.workers != 1 and servers is None:
        raise SystemExit(f"yawil collect: --backend {args.backend} with --workers {args.workers}: give one server per "
                         "worker with --carla-servers HOST:PORT,...")
    from yawil.sim.carla.connection import check_connection_arguments

    check_connection_arguments(args)
    if args.backend == "embedded":  # before any folder is made: a typo'd town must not leave a dataset behind
        from yawil.sim.town.map.layout import resolve_town

        resolve_town(args.town)
    from yawil.sim.carla.connection import connection_from_args

    factory = world_factory(args.backend, **({} if args.backend == "embedded" else connection_from_args(args).kwargs()))
    if servers is not None:
        factory = server_worlds(servers, args.timeout)  # type: ignore[assignment]
    if args.backend != "embedded":
        _check_carla(args.town, factory)
    summary = collect(args.out, verify=args.verify, town=args.town, weathers=args.weathers, frames=args.frames, episodes=args.episodes,
                      workers=args.workers, seed=args.seed, config=cfg, progress=not args.quiet,
                      world_factory=factory, expert_config=expert, executor=executor,
                      guidance=GuidanceConfig(reference=args.guidance_reference))  # fmt: skip
    outcomes = ", ".join(f"{k} {v}" for k, v in sorted(summary.outcomes.items())) or "none"
    print(f"{summary.out}: wrote {summary.episodes_written} episodes, {summary.frames_written} frames in "
          f"{summary.seconds:.0f} s ({summary.frames_per_second:.1f} frames/s); skipped {summary.episodes_skipped} "
          f"already present; discarded {summary.episodes_discarded}; outcomes: {outcomes}; "
          f"dataset now {summary.dataset_frames} frames")
    return 0
