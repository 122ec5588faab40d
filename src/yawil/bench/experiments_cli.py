"""`yawil experiment square|noise`: the paper's Table I and Table II on the square scene, resumable."""

from __future__ import annotations

import argparse

from yawil.bench.cli import add_choice_help  # argparse only, like this module
from yawil.cliargs import seed

_DESCRIPTIONS: dict[str, str] = {
    "square": "Collect on the square map, build the 3 datasets, train 12 models, drive the 32 turning tasks, "
    "write table1.md (Table I). Every stage is skipped when its output exists.",
    "noise": "Drive the models that passed every task of `square` again with yaw noise (guided) or wrong "
    "commands (CIL), write table2.md (Table II). Every stage is skipped when its output exists.",
}


def _add_options(p: argparse.ArgumentParser, which: str | None) -> None:
    """The options of `square`, `noise`, or both (None, on the command itself)."""
    p.add_argument("--profile", default="quick", choices=("quick", "standard", "paper"),
                   help="quick: minutes-scale smoke run; standard: about an hour on 2 cores, the figures of "
                   "docs/benchmark.md; paper: the paper's budgets (default quick)")
    p.add_argument("--out", default="results/square", help="experiment folder (default results/square)")

    def tag(name: str) -> str:  # on the command itself, say which action an option is for
        return f"{name}: " if which is None else ""

    if which in (None, "square"):
        p.add_argument("--seed", type=seed, default=0,
                       help=tag("square") + "seed of collection and training (default 0)")
    if which in (None, "noise"):
        p.add_argument("--noise-seeds", type=int, default=None,
                       help=tag("noise") + "seeds per noise level instead of the profile's (the paper's 5)")
        p.add_argument("--models", default=None,
                       help=tag("noise") + "comma-separated methods to test instead of the passing ones")
        p.add_argument("--yaw-noise", default="raw", choices=("raw", "independent"),
                       help=tag("noise") + "reading of the yaw noise: raw (default) on the route headings before "
                       "the reference is subtracted; independent: on each guidance component after it")
        p.add_argument("--command-noise", default="burst-start", choices=("burst-start", "frame-share"),
                       help=tag("noise") + "reading of p: burst-start (default) a 5-frame burst starts with p on "
                       "each quiet frame; frame-share: a share p of the frames is wrong")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "experiment",
        help="square experiments: Table I (road-option methods x datasets), Table II (noise)",
        description="square: collect on the square map, build the 3 datasets, train 12 models, drive the 32 "
        "turning tasks, write table1.md. noise: drive the models that passed every task again with yaw noise "
        "(guided) or wrong commands (CIL), write table2.md. Every stage is skipped when its output exists.",
        add_help=False,
    )
    add_choice_help(p, "which", _DESCRIPTIONS, _add_options)
    p.add_argument("which", choices=("square", "noise"))
    _add_options(p, None)
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.bench.experiments import noise_experiment, square_experiment
    from yawil.fileio import check_pipeline_folder, claimed_output_folder

    try:
        # square writes the folder, noise reads square's models from it and adds Table II
        check_pipeline_folder(args.out, "--out", "experiment", signature=("profile.json",))
        if args.which == "square":
            with claimed_output_folder(args.out, "experiment"):
                square_experiment(args.out, args.profile, seed=args.seed)
        else:
            models = [m.strip() for m in args.models.split(",")] if args.models else None
            noise_experiment(args.out, args.profile, models=models, seeds=args.noise_seeds,
                             yaw_noise_mode=args.yaw_noise, command_noise_mode=args.command_noise)
    except ValueError as err:
        raise SystemExit(f"yawil experiment: {err}") from None
    return 0
