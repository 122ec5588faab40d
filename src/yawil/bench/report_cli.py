"""`yawil report RESULTS_DIR [RESULTS_DIR ...] --out report/`: Tables III and IV, plots, Markdown and HTML."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "report",
        help="tables (as the paper's III and IV) and plots from benchmark results",
        description="Build report.md, report.html (self-contained), summary.json (the same figures as numbers) "
        "and PNG plots from results folders written by `yawil bench`; each folder is one column (one agent). "
        "Each report names the yawil version, git commit, command line and date (UTC) that made it.",
    )
    p.add_argument("results", nargs="+", help="results folders (each holds episodes.jsonl)")
    p.add_argument("--out", default="report", help="output folder (default: report)")
    p.add_argument("--force", action="store_true",
                   help="write into an --out folder that holds other files (same-named ones are replaced)")
    p.add_argument(
        "--trajectory",
        action="append",
        default=[],
        metavar="CONDITION=TASK/[WEATHER/]ROUTE/SEED",
        help="episode whose trajectories are drawn for a condition, e.g. new-town-weather=dense/3/0 or "
        "new-town-weather=dense/SoftRainSunset/3/0 (default weather: the condition's first driven; default "
        "episode: route 0, seed 0 of the hardest task run)",
    )
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.bench.report import write_report
    from yawil.bench.suites import get_condition
    from yawil.fileio import check_output_folder, claimed_output_folder

    chosen: dict[str, str] = {}
    for item in args.trajectory:
        cond, sep, spec = item.partition("=")
        if not sep:
            raise SystemExit(f"--trajectory {item!r}: expected CONDITION=TASK/ROUTE/SEED")
        get_condition(cond)
        chosen[cond] = spec
    check_output_folder(args.out, "--out", "report", args.force)  # a ValueError: one line, exit 2
    try:
        with claimed_output_folder(args.out, "report"):  # a refused report leaves no folder behind
            paths = write_report(args.results, args.out, chosen)
    except ValueError as err:
        raise SystemExit(f"yawil report: {err}") from None
    print((paths["report.md"]).read_text(encoding="utf-8"))
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0
