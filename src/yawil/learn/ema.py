"""An exponential moving average of the weights (`TrainConfig.ema`), the weights a run drives with.

Why: at the budgets of one 2-core machine, two checkpoints of one run 750 steps apart drove 54 and 31 of the
100 evaluation episodes with equal validation errors (docs/experiments.md, 2026-12-02): the last step's weights
are a noisy draw. An average over the last few hundred steps is the usual remedy (Polyak averaging; timm's
ModelEmaV3, which this follows: the decay ramps up as (1 + n) / (10 + n) so the first steps do not pin the
average to the initial weights). Built on torch's `AveragedModel`, buffers included (BatchNorm's running
statistics are averaged too, as in timm).
"""

from __future__ import annotations

from typing import Any

import torch
from torch.optim.swa_utils import AveragedModel

Params = tuple[torch.Tensor, ...] | list[torch.Tensor]


def warmup_decay(decay: float, updates: int) -> float:
    """The decay used for the update after `updates` earlier ones: min(decay, (1 + n) / (10 + n))."""
    return min(decay, (1.0 + updates) / (10.0 + updates))


def make_ema(model: torch.nn.Module, decay: float) -> AveragedModel:
    """The average of `model`'s parameters and buffers, updated by `ema.update_parameters(model)` per step."""

    @torch.no_grad()
    def update(averaged: Params, current: Params, n: torch.Tensor | int) -> None:
        # AveragedModel counts the first call (a copy) in n, so the k-th average uses warmup_decay(k - 1)
        d = warmup_decay(decay, int(n) - 1)
        if torch.is_floating_point(averaged[0]):
            torch._foreach_lerp_(averaged, current, 1.0 - d)
        else:  # integer buffers (BatchNorm's num_batches_tracked): follow the model
            for a, c in zip(averaged, current, strict=True):
                a.copy_(c)

    return AveragedModel(model, multi_avg_fn=update, use_buffers=True)


def ema_state(ema: AveragedModel) -> dict[str, Any]:
    """What a checkpoint keeps of the average besides its weights: how many updates it has had."""
    return {"updates": int(ema.n_averaged)}


def restore_ema(ema: AveragedModel, weights: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
    """Put a saved average back (its weights are the checkpoint's `state_dict`)."""
    ema.module.load_state_dict(weights)
    ema.n_averaged.fill_(int(state["updates"]))
