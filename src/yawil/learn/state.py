"""Where a run is (`Position`) and the global random states, saved in every checkpoint so that a stopped
run resumed gives the weights an uninterrupted run would have."""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


# ------------------------------------------------------------------------------------------------ state
@dataclass
class Position:
    """Where the run is: epoch, batch within it, optimiser steps, and the running sums of the epoch."""

    epoch: int = 0
    batch: int = 0
    step: int = 0
    loss_sum: float = 0.0
    samples: int = 0
    seconds: float = 0.0  # training time spent in the current epoch
    best_val: float = math.inf


def rng_states() -> dict[str, Any]:
    """The global generators (dropout uses torch's; numpy's and python's for third-party code)."""
    states: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),  # noqa: NPY002
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def seed_globals(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed)  # noqa: NPY002 (the legacy global state, for third-party code)
    random.seed(seed)


def set_rng_states(states: Mapping[str, Any]) -> None:
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])  # noqa: NPY002
    random.setstate(states["python"])
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])
