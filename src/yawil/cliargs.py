"""argparse value types that several commands share (standard library only: `yawil --help` stays fast).

Why: a value refused inside the work named no option (`--seed -1` read "expected non-negative integer", numpy's
words); refused by argparse, the line names the option and the value.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any


def seed(text: str) -> int:
    """A seed: an integer >= 0 (numpy's generators refuse negative seeds)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value


def given_options(args: argparse.Namespace, add_parser: Callable[[Any], argparse.ArgumentParser],
                  command: str) -> dict[str, tuple[str, Any]]:
    """The options of `yawil COMMAND` given a value other than their default, as dest -> (flag, value): the
    defaults read from the command module's own `add_parser`, so that a check of options that would do nothing
    (explain's modes, bench routes, export without --check) never restates them."""
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    out: dict[str, tuple[str, Any]] = {}
    for action in sub._actions:
        if action.option_strings and action.dest in vars(args) and getattr(args, action.dest) != action.default:
            out[action.dest] = (action.option_strings[-1], getattr(args, action.dest))
    return out
