"""`yawil results MANIFEST --out docs/results.md`: the results page (and README's headline block) from records."""

from __future__ import annotations

import argparse

README_START = "<!-- yawil results: headline (made by `yawil results`; edit records/results.json) -->"
README_END = "<!-- yawil results: end -->"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "results",
        help="docs/results.md from the committed records of the headline runs",
        description="Write Tables III and IV of the runs a manifest lists (records/results.json: each a results "
        "folder with its model family, training seeds, role and command), the paper's figures beside ours and "
        "the paper's claims marked by their evidence; with --readme, also the headline block of README.md.",
    )
    p.add_argument("manifest", nargs="?", default="records/results.json",
                   help="the manifest (default records/results.json)")
    p.add_argument("--out", default="docs/results.md", help="the page to write (default docs/results.md)")
    p.add_argument("--force", action="store_true", help="replace an --out file this command did not write")
    p.add_argument("--readme", default=None, metavar="README",
                   help="also rewrite the block between the yawil results markers of this file")
    return p


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from yawil.bench.results_page import TITLE, headline_block, read_results_manifest, render
    from yawil.fileio import check_output_file, write_atomic

    out = Path(args.out)
    try:  # a page this command wrote before is regenerated; any other file needs --force
        ours = out.is_file() and out.read_text(encoding="utf-8").startswith(TITLE)
    except (OSError, UnicodeDecodeError):
        ours = False
    check_output_file(out, "--out", args.force, own=(out,) if ours else ())
    readme = None
    if args.readme:  # checked before the page is written: a bad README left a new page and exit 2
        readme = Path(args.readme)
        check_output_file(readme, "--readme", force=True)  # the user's README is rewritten in place, by design
        try:
            text = readme.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise ValueError(f"--readme {readme}: cannot be read as text ({getattr(err, 'strerror', None) or err})") from None
        if text.count(README_START) != 1 or text.count(README_END) != 1:
            raise ValueError(f"--readme {readme}: expected one line {README_START!r} and one {README_END!r} around "
                             "the headline block")
    rows, notes, attention = read_results_manifest(args.manifest)
    page = write_atomic(args.out, render(rows, notes, str(args.manifest), attention))
    print(f"wrote {page} ({len(rows)} rows)")
    if readme is not None:
        head, rest = text.split(README_START)
        _, tail = rest.split(README_END)
        write_atomic(readme, head + README_START + "\n" + headline_block(rows) + README_END + tail)
        print(f"wrote the headline block of {readme}")
    return 0
