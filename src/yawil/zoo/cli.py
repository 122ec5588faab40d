"""`yawil zoo`: the model zoo shipped in the repository (yawil.zoo).

    yawil zoo list                                   # = yawil models --zoo
    yawil zoo check [NAME ...]                       # each model's outputs on its probe frames vs its card
    yawil zoo pack CKPT --name NAME --data DATA --card CARD.json [--out FOLDER] [--force]

`pack` writes FOLDER/NAME (default FOLDER: ./zoo; to ship a model with yawil, --out src/yawil/zoo); a model of
that name is replaced only with --force, and only once the new one is complete. It checks the card's fields and
`drive`, and the dataset as `yawil data check --no-images` does, before any work. It stores the checkpoint compactly (bf16, without weights no output uses), draws probe frames from DATA
and writes the card: CARD.json's fields (commands, commit, data, wall time, machine, results, `drive`) plus
what pack measures (probe outputs, stored parameters).
"""

from __future__ import annotations

import argparse
from typing import Any


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from yawil.zoo import PROBE_FRAMES

    p: argparse.ArgumentParser = subparsers.add_parser(
        "zoo", help="the trained models shipped with yawil: list, check, pack", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("action", choices=("list", "check", "pack"))
    p.add_argument("names", nargs="*", help="check: zoo model names (default all); pack: the checkpoint")
    p.add_argument("--name", help="pack: the zoo model's name")
    p.add_argument("--data", help="pack: the dataset the probe frames are drawn from")
    p.add_argument("--card", help="pack: a JSON file of the card's fields")
    p.add_argument("--frames", type=int, default=None, help=f"pack: probe frames (default {PROBE_FRAMES})")
    p.add_argument("--out", default=None, help="pack: the zoo folder to write NAME into (default ./zoo; the "
                   "shipped zoo is src/yawil/zoo)")
    p.add_argument("--force", action="store_true", help="pack: replace a model of the same name")
    return p


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from yawil import zoo
    from yawil.zoo import pack

    if args.action != "pack":  # check and list read the shipped zoo: a pack option given to them did nothing
        given = [f"--{k}" for k in ("name", "data", "card", "frames", "out") if getattr(args, k) is not None]
        given += ["--force"] * args.force
        if given:
            raise ValueError(f"zoo {args.action}: {', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to "
                             f"zoo pack only ({args.action} reads the shipped zoo, {zoo.ZOO_DIR})")
    if args.action == "list":
        print(zoo.table())
        return 0
    if args.action == "check":
        for n in args.names or zoo.zoo_names():
            print(f"zoo:{n}: probe outputs within {pack.check_zoo_model(n):.1e} of the card")
        return 0
    if len(args.names) != 1 or not (args.name and args.data and args.card):
        raise ValueError("zoo pack: give one checkpoint and --name, --data and --card")
    try:
        card = json.loads(Path(args.card).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"--card {args.card}: not a readable JSON file ({err})") from None
    frames = zoo.PROBE_FRAMES if args.frames is None else args.frames
    if frames < 1:
        raise ValueError(f"--frames {frames}: expected >= 1")
    folder = pack.pack(args.names[0], args.name, Path(args.data), pack.check_card(card, f"--card {args.card}"),
                       root=Path(args.out or "zoo"), count=frames, force=args.force)
    print(f"zoo:{args.name} -> {folder} ({sum(f.stat().st_size for f in folder.iterdir()) / 2**20:.1f} MiB)")
    return 0
