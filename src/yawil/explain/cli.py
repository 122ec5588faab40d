"""`yawil explain`: attention heat maps of a trained agent, on dataset frames or on a driven episode.

The command line only: the work is `yawil.explain.attention.explain_frames` and `explain_episode`.
"""

from __future__ import annotations

import argparse
from pathlib import Path


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
    p.add_argument("--checkpoint", required=True, help="a yawil checkpoint (best.pt / last.pt) or zoo:NAME")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", help="a dataset folder or one episode .h5 file to draw frames from")
    src.add_argument("--episode", action="store_true", help="drive a fresh episode and make a video")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--force", action="store_true",
                   help="write into an --out folder that holds other files (same-named ones are replaced)")
    p.add_argument("--count", type=int, default=6, help="frames to explain with --frames (default 6)")
    p.add_argument("--seed", type=int, default=0, help="seed for frame choice / the episode (default 0)")
    p.add_argument("--alpha", type=float, default=0.5, help="weight of the colour map in the blend (default 0.5)")
    p.add_argument("--town", default="town02", help="--episode: town (default town02)")
    p.add_argument("--weather", default="SoftRainSunset", help="--episode: weather (default SoftRainSunset)")
    p.add_argument("--vehicles", type=int, default=20, help="--episode: vehicles (default 20)")
    p.add_argument("--pedestrians", type=int, default=20, help="--episode: pedestrians (default 20)")
    p.add_argument("--route", help="--episode: a benchmark route as TASK:ID of --condition (default: a random route)")
    p.add_argument("--condition", default="new-town-weather", help="--episode with --route: benchmark condition")
    p.add_argument("--steps", type=int, default=300, help="--episode: at most this many steps (default 300)")
    p.add_argument("--every", type=int, default=2, help="--episode: keep every Nth step in the video (default 2)")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.agent import Agent
    from yawil.explain.attention import EpisodeVideo, explain_episode, explain_frames
    from yawil.fileio import check_output_folder, claim_output_folder

    if args.count < 1 or args.steps < 1 or args.every < 1:
        raise SystemExit("yawil explain: --count, --steps and --every must be >= 1")
    check_output_folder(args.out, "--out", "explain", args.force)
    agent = Agent.from_checkpoint(args.checkpoint)
    out = claim_output_folder(args.out, "explain")
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
