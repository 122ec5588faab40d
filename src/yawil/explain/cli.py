"""`yawil explain`: attention heat maps of a trained agent, on dataset frames or on a driven episode.

The command line only: the work is `yawil.explain.attention.explain_frames` and `explain_episode`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from yawil.cliargs import given_options, seed


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "explain",
        help="attention heat maps (per frame, grid, episode video)",
        description=(
            "Heat maps of what a trained network attends to (YILRatt: its attention layers 1-3; models without "
            "attention such as CILRS: the channel mean of |activation| of ResNet layers 1-3). With --frames, "
            "one figure per dataset frame plus a grid (the paper's Figure 8); with --episode, a video of a "
            "driven episode (Figure 9)."
        ),
    )
    p.add_argument("--checkpoint", help="a yawil checkpoint (best.pt / last.pt) or zoo:NAME (with --failures: "
                   "instead of the results folder's own agent)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", help="a dataset folder or one episode .h5 file to draw frames from")
    src.add_argument("--episode", action="store_true", help="drive a fresh episode and make a video")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--force", action="store_true",
                   help="write into an --out folder that holds other files (same-named ones are replaced)")
    p.add_argument("--count", type=int, default=6, help="frames to explain with --frames (default 6)")
    p.add_argument("--seed", type=seed, default=0, help="seed for frame choice / the episode (default 0)")
    p.add_argument("--alpha", type=float, default=0.5, help="weight of the colour map in the blend (default 0.5)")
    p.add_argument("--town", default="town02", help="--episode: town (default town02)")
    p.add_argument("--weather", default="SoftRainSunset", help="--episode: weather (default SoftRainSunset)")
    p.add_argument("--vehicles", type=int, default=20, help="--episode: vehicles (default 20)")
    p.add_argument("--pedestrians", type=int, default=20, help="--episode: pedestrians (default 20)")
    p.add_argument("--route", help="--episode: a benchmark route as TASK:ID of --condition (default: a random route)")
    p.add_argument("--condition", default="new-town-weather", help="--episode with --route: benchmark condition")
    p.add_argument("--steps", type=int, default=300, help="--episode: at most this many steps (default 300)")
    p.add_argument("--every", type=int, default=2, help="--episode: keep every Nth step in the video (default 2)")
    # The deletion test (yawil.explain.faithfulness; its defaults, stated here so that --help imports nothing).
    g = p.add_argument_group("faithfulness (--faithfulness; docs/explain.md)")
    g.add_argument("--faithfulness", action="store_true",
                   help="the deletion test instead of figures: with --frames on --count frames (open loop; writes "
                        "faithfulness.json/.md/.csv/.png), with --episode at its braking moments (closed loop)")
    g.add_argument("--ks", default="5,10,20,40", help="--frames: percentages of pixels masked (default 5,10,20,40)")
    g.add_argument("--fill", choices=("mean", "blur"), default="mean",
                   help="what masked pixels become: the image's mean colour (default) or the image blurred")
    g.add_argument("--random", choices=("cells", "pixels"), default="cells",
                   help="the random baseline: blobs of the maps' own grain (default) or single pixels")
    g.add_argument("--maps", choices=("auto", "attention", "activation"), default="auto",
                   help="attention maps, or the channel-mean |activation| of each stage (default: attention where "
                        "the model has it)")
    g.add_argument("--select", choices=("all", "braking"), default="all",
                   help="--frames: draw from every frame, or from those where the expert brakes (default all)")
    g.add_argument("--mask-k", type=float, default=20.0, help="--episode: percentage of pixels masked (default 20)")
    g.add_argument("--mask-layer", default="mean",
                   help="--episode: the map whose top pixels are masked, mean or N (layer N; default mean)")
    g.add_argument("--horizon", type=int, default=20, help="--episode: steps driven masked per moment (default 20)")
    g.add_argument("--moments", type=int, default=8, help="--episode: braking moments tested at most (default 8)")
    from yawil.explain.by_class import add_by_class_arguments  # numpy only: no torch or matplotlib

    add_by_class_arguments(p.add_argument_group("attention by class (--by-class; docs/explain.md)"), flag_group=src)
    from yawil.explain.failures import add_failures_arguments  # numpy only at import

    add_failures_arguments(p.add_argument_group("failures explained (--failures; docs/explain.md)"), flag_group=src)
    return p


# The options each mode reads (beside --checkpoint, --out, --force): any other given is refused, not ignored.
_EPISODE = {"town", "weather", "vehicles", "pedestrians", "route", "condition", "seed", "steps"}
READS: dict[str, set[str]] = {
    "--frames": {"count", "seed", "alpha"},
    "--episode": _EPISODE | {"every", "alpha"},
    "--faithfulness --frames": {"ks", "fill", "random", "seed", "count", "maps", "select"},
    "--faithfulness --episode": _EPISODE | {"mask_layer", "horizon", "mask_k", "moments", "fill", "random", "maps"},
    "--by-class": {"maps"} | {f"class_{k}" for k in ("task", "condition", "suite", "routes", "seeds", "every",
                                                    "max_frames", "brake", "steer")},
    "--failures": {"failure_reasons", "max_failures", "seconds", "strip", "maps", "alpha"},
}
_ALWAYS = {"checkpoint", "out", "force", "frames", "episode", "faithfulness", "by_class", "failures"}


def check_mode_options(args: argparse.Namespace) -> None:
    """Refuse, in one line, an option the chosen mode does not read (`--town` with --frames was accepted and
    did nothing). Given: different from its default."""
    mode = ("--failures" if args.failures else "--by-class" if args.by_class else
            ("--faithfulness " if args.faithfulness else "") + ("--frames" if args.frames else "--episode"))
    for dest, (flag, value) in given_options(args, add_parser, "explain").items():
        if dest in _ALWAYS or dest in READS[mode]:
            continue
        users = [m for m, reads in READS.items() if dest in reads]
        raise SystemExit(f"yawil explain: {flag} {value}: applies to {' and '.join(users) or 'no mode'}, not to {mode}")


def run(args: argparse.Namespace) -> int:
    from yawil.agent import Agent
    from yawil.explain.attention import EpisodeVideo, explain_episode, explain_frames
    from yawil.fileio import check_output_folder, claimed_output_folder

    if args.count < 1 or args.steps < 1 or args.every < 1:
        raise SystemExit("yawil explain: --count, --steps and --every must be >= 1")
    check_mode_options(args)
    check_output_folder(args.out, "--out", "explain", args.force)
    if args.failures:  # the agent is the results folder's (or --checkpoint's), built with its drive options
        from yawil.explain.failures import run_from_args as failures

        return failures(args, args.out)
    if not args.checkpoint:
        raise SystemExit("yawil explain: --checkpoint is required (except with --failures)")
    if args.frames and not (args.by_class or args.faithfulness):
        from yawil.explain.attention import check_frame_count
        from yawil.zoo import resolve_checkpoint

        if not resolve_checkpoint(args.checkpoint).exists():  # the cheaper refusal first
            raise SystemExit(f"yawil explain: --checkpoint {args.checkpoint}: does not exist")
        check_frame_count(Path(args.frames), args.count)
    agent = Agent.from_checkpoint(args.checkpoint)
    with claimed_output_folder(args.out, "explain") as out:  # a refusal from the work below leaves no folder
        if args.by_class:
            from yawil.explain.by_class import run_from_args as by_class

            return by_class(agent, args, out)
        if args.faithfulness:
            from yawil.explain.faithfulness import run_from_args

            return run_from_args(agent, args, out)
        if args.frames:
            paths = explain_frames(agent, Path(args.frames), out, args.count, args.seed, args.alpha)
            print(f"wrote {len(paths) - 1} frame figures and {paths[-1]}")
        else:
            episode = EpisodeVideo(route=args.route, condition=args.condition, town=args.town, weather=args.weather,
                                   vehicles=args.vehicles, pedestrians=args.pedestrians, seed=args.seed,
                                   steps=args.steps, every=args.every)  # fmt: skip
            video = explain_episode(agent, out, episode, alpha=args.alpha)
            print(f"wrote {video}")
    return 0
