"""`yawil collect`: expert driving data for training, resumable, in parallel processes.

Only argparse at module level (the CLI's rule); the collector, the simulator and h5py load inside `run`.
"""

from __future__ import annotations

import argparse
from typing import Any


def _range(text: str) -> tuple[int, int]:
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


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
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
    p.add_argument("--town", default="town01", help="town01, town02, square or a layout JSON file (default town01)")
    p.add_argument("--weathers", default="train",
                   help="'train', 'test', 'all' or comma-separated weather names (default train)")
    budget = p.add_argument_group("budget (the first one reached stops the run)")
    budget.add_argument("--frames", type=int, default=None,
                        help="stop once the dataset holds this many frames; episodes are stored whole, so the last one may go past it (default 200000 unless --episodes)")
    budget.add_argument("--episodes", type=int, default=None, help="episode indices 0..N-1 of this seed")
    p.add_argument("--out", required=True, help="dataset directory (created, or resumed); required")
    p.add_argument("--workers", type=int, default=1,
                   help="parallel processes, each running its own simulator (default 1)")
    p.add_argument("--seed", type=int, default=0, help="episode ids are seed*100000+index (default 0)")
    p.add_argument("--vehicles", type=_range, default=(10, 30), metavar="N|LO-HI",
                   help="vehicles per episode: N, or LO-HI drawn uniformly per episode (default 10-30)")
    p.add_argument("--pedestrians", type=_range, default=(5, 20), metavar="N|LO-HI",
                   help="pedestrians per episode: N, or LO-HI drawn uniformly per episode (default 5-20)")
    p.add_argument("--min-route-length", type=float, default=200.0, help="metres (default 200)")
    p.add_argument("--noise", type=_fraction, default=0.10,
                   help="fraction of frames with a steering perturbation (default 0.1)")
    p.add_argument("--noise-amplitude", type=_fraction, default=0.5,
                   help="perturbation drawn from U[-a, a] (default 0.5)")
    p.add_argument("--straight-keep", type=_fraction, default=0.5,
                   help="fraction of frames kept on long straights (default 0.5)")
    p.add_argument("--blocked-keep-every", type=int, default=10,
                   help="keep every Nth frame once stopped for more than 2 s (default 10)")
    p.add_argument("--on-collision", choices=("trim", "keep", "discard"), default="trim",
                   help="trim: keep the episode without its last 2 s; keep: all frames; discard: drop the episode "
                   "(default trim)")
    p.add_argument("--expert-arg", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting of the expert's ExpertConfig (docs/expert.md), e.g. comfort_decel=1.5; repeat for more "
                        "(stored in the dataset's config, so a resume must give the same)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verify", action="store_true",
                   help="on resume, decode every stored image and re-collect the episodes that fail (a resume always "
                        "re-collects missing, truncated or unreadable episode files)")
    p.add_argument("--backend", default="embedded", choices=("embedded", "carla"), help="simulator (default embedded)")
    p.add_argument("--host", default="localhost", help="--backend carla: server host (default localhost)")
    p.add_argument("--port", type=int, default=2000, help="--backend carla: server port (default 2000)")
    p.add_argument("--timeout", type=float, default=10.0,
                   help="--backend carla: seconds a client call may take (default 10; map loads get at least 60)")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.data.collect import CollectConfig, collect
    from yawil.expert import ExpertConfig

    if args.frames is None and args.episodes is None:
        args.frames = 200_000
    expert = ExpertConfig.from_items(args.expert_arg)
    cfg = CollectConfig(
        vehicles=args.vehicles, pedestrians=args.pedestrians, min_route_length=args.min_route_length,
        noise_fraction=args.noise, noise_amplitude=args.noise_amplitude, straight_keep=args.straight_keep,
        blocked_keep_every=args.blocked_keep_every, on_collision=args.on_collision,
    )
    from yawil.sim import world_factory

    if args.backend != "embedded" and args.workers != 1:
        raise SystemExit(f"yawil collect: --backend {args.backend} drives one server: use --workers 1 (got {args.workers})")
    if args.backend == "embedded":  # before any folder is made: a typo'd town must not leave a dataset behind
        from yawil.sim.town.map.layout import resolve_town

        resolve_town(args.town)
    factory = world_factory(args.backend, **({} if args.backend == "embedded" else {"host": args.host, "port": args.port, "timeout": args.timeout}))
    summary = collect(args.out, verify=args.verify, town=args.town, weathers=args.weathers, frames=args.frames, episodes=args.episodes,
                      workers=args.workers, seed=args.seed, config=cfg, progress=not args.quiet,
                      world_factory=factory, expert_config=expert)  # fmt: skip
    outcomes = ", ".join(f"{k} {v}" for k, v in sorted(summary.outcomes.items())) or "none"
    print(f"{summary.out}: wrote {summary.episodes_written} episodes, {summary.frames_written} frames in "
          f"{summary.seconds:.0f} s ({summary.frames_per_second:.1f} frames/s); skipped {summary.episodes_skipped} "
          f"already present; discarded {summary.episodes_discarded}; outcomes: {outcomes}; "
          f"dataset now {summary.dataset_frames} frames")
    return 0
