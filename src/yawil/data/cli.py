"""`yawil data check|stats|subset`: look after a dataset. See docs/dataset.md.

Only argparse at module level (the CLI's rule); h5py, numpy and matplotlib load inside `run`.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

SUBSET_CHOICES = ("road-option-turns", "lane-follow-turns", "all")  # == yawil.data.subset.SUBSETS


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "data",
        help="check, describe or subset a dataset",
        description="Verify a dataset's files, print and plot its distribution, or write a subset of it.",
    )
    sub = p.add_subparsers(dest="data_command", metavar="ACTION", required=True)
    c = sub.add_parser(
        "check",
        help="verify every episode file; exit 1 if any is bad",
        description="Read every episode file of each DIR (structure, dtypes, shapes, value ranges, NaN, manifest "
        "agreement, every image decoded) and name the bad ones. Exit status 1 if any is bad.",
    )
    c.add_argument("dirs", nargs="+", metavar="DIR", help="dataset root(s)")
    c.add_argument("--no-images", action="store_true", help="skip decoding the images (labels and structure only)")
    s = sub.add_parser(
        "stats",
        help="frames by road option and weather, steer/throttle/brake histograms (Figure 7)",
        description="Print the dataset's distribution and plot it as the paper's Figure 7.",
    )
    s.add_argument("dirs", nargs="+", metavar="DIR", help="dataset root(s), described together")
    s.add_argument("--out", default=None, metavar="PNG", help="figure to write (default: DIR/stats.png of the first DIR)")
    s.add_argument("--force", action="store_true", help="replace an existing output file (never one inside a dataset, run, results or zoo folder)")
    u = sub.add_parser(
        "subset",
        help="write a subset of the square experiment as a new dataset",
        description="road-option-turns: junction turns (LEFT/RIGHT) and straight frames, no lane-follow curves; "
        "lane-follow-turns: lane-follow curves and straight frames, no junction turns; all: every frame. "
        "The subset is a complete dataset, written atomically.",
    )
    u.add_argument("src", metavar="SRC", help="source dataset root")
    u.add_argument("--only", required=True, choices=SUBSET_CHOICES)
    u.add_argument("--out", required=True, metavar="DST", help="new dataset root (must not exist)")
    return p


def run(args: argparse.Namespace) -> int:
    try:
        if args.data_command == "check":
            return _check(args)
        if args.data_command == "stats":
            return _stats(args)
        if args.data_command == "subset":
            from yawil.data.subset import write_subset
            from yawil.fileio import check_not_inside_owned

            check_not_inside_owned(args.out, "--out")
            write_subset(args.src, args.out, args.only, quiet=False)
            return 0
    except ValueError as err:
        print(f"yawil data {args.data_command}: {err}", file=sys.stderr)
        return 2
    raise AssertionError(f"unknown data action {args.data_command!r}")


def _check(args: argparse.Namespace) -> int:
    from yawil.data.check import check_dataset

    ok = True
    for d in args.dirs:
        report = check_dataset(d, images=not args.no_images)
        print("\n".join(report.lines()))
        ok &= report.ok
    return 0 if ok else 1


def _stats(args: argparse.Namespace) -> int:
    from pathlib import Path

    from yawil.data.stats import write_stats
    from yawil.fileio import check_output_file

    out = Path(args.out) if args.out else Path(args.dirs[0]) / "stats.png"
    # a dataset's own figure (DIR/stats.png) may be written or replaced; any other file inside a dataset is refused
    check_output_file(out, "--out", args.force, own=tuple(Path(d) / "stats.png" for d in args.dirs))
    print(f"wrote {write_stats(args.dirs, out)}")
    return 0
