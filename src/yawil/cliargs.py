"""argparse value types that several commands share (standard library only: `yawil --help` stays fast).

Why: a value refused inside the work named no option (`--seed -1` read "expected non-negative integer", numpy's
words); refused by argparse, the line names the option and the value.
"""

from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """A seed: an integer >= 0 (numpy's generators refuse negative seeds)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value
