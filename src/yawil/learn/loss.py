"""The training loss: actions (L1 / MSE / smooth L1, or BCE on the brake), speed, and the auxiliary head."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from yawil.data.schema import SPEED_REASONS
from yawil.learn.config import TrainConfig
from yawil.learn.sampling import Batch
from yawil.models.base import AUX_NAMES, LEAD_STOP_DISTANCE, LEAD_STOP_SPEED
from yawil.policy.checkpoint import Norm


# ------------------------------------------------------------------------------------------------- loss
def _criterion(name: str) -> Callable[..., Tensor]:
    return {
        "l1": torch.nn.functional.l1_loss,
        "mse": torch.nn.functional.mse_loss,
        "smooth_l1": torch.nn.functional.smooth_l1_loss,
    }[name]


def predicted_actions(model: torch.nn.Module, out: Any, command: Tensor | None) -> Tensor:
    """The actions the loss sees: for branched models the branch of each sample's command."""
    if getattr(model, "uses_command", False) and out.branches is not None:
        if command is None:
            raise ValueError(f"model {getattr(model, 'name', '?')} is branched and needs the command")
        return out.branches[torch.arange(command.shape[0], device=command.device), command]
    return out.actions


def compute_loss(
    model: torch.nn.Module, batch: Batch, cfg: TrainConfig, norm: Norm | None = None
) -> tuple[Tensor, Tensor, Any]:
    """alpha * L(actions) + beta * L(speed) (+ aux_weight * the aux loss), in float32 whatever the autocast."""
    out = model(batch.image, batch.speed, guidance=batch.guidance, command=batch.command)
    pred = predicted_actions(model, out, batch.command).float()
    crit = _criterion(cfg.loss)
    if cfg.brake_loss == "bce":
        act = (2.0 * crit(pred[:, :2], batch.action[:, :2]) + bce_of_probabilities(pred[:, 2], batch.action[:, 2])) / 3.0
    else:
        act = crit(pred, batch.action)
    loss = cfg.alpha * act + cfg.beta * crit(out.speed.float(), batch.speed)
    if cfg.aux_weight > 0.0:
        if out.aux is None:
            raise ValueError(f"aux_weight={cfg.aux_weight} but model {cfg.model} has no aux head (--model-arg aux=true)")
        if batch.privileged is None or norm is None:
            raise ValueError("aux_weight > 0 needs the privileged labels of the samples (schema-2 data) and the norm")
        aux_criterion = cfg.loss if cfg.aux_loss == "same" else cfg.aux_loss
        loss = loss + cfg.aux_weight * aux_loss(out.aux.float(), batch.privileged, norm, aux_criterion,
                                                cfg.stop_label_reasons())
    return loss, pred, out


def bce_of_probabilities(p: Tensor, target: Tensor, eps: float = 1e-6) -> Tensor:
    """Mean binary cross-entropy of probabilities (soft targets allowed), written out so that it runs under
    autocast (torch refuses `binary_cross_entropy` there); float32 and clamped."""
    p = p.float().clamp(eps, 1.0 - eps)
    t = target.float()
    return -(t * p.log() + (1.0 - t) * (1.0 - p).log()).mean()


def aux_targets(privileged: Tensor, norm: Norm) -> tuple[Tensor, Tensor]:
    """(targets in the aux head's scale, mask of known ones), both [B, 4]; see models.base.AUX_NAMES."""
    from yawil.data.schema import LEAD_RANGE

    ts, ld, ls, light = privileged[:, :4].unbind(dim=1)  # the fifth column, the expert's reason, is no target
    target = torch.stack([norm.speed(ts[:, None])[:, 0], ld / LEAD_RANGE, norm.speed(ls[:, None])[:, 0], light], dim=1)
    known = torch.stack([ts.isfinite(), ld.isfinite(), ls.isfinite(), light >= 0], dim=1)
    return torch.where(known, target, torch.zeros_like(target)), known


# Weight of the positive frames in the lead-stop cross-entropy: about 3 % of town01's frames are positive, so
# unweighted the head's cheapest answer is "never"; 10 makes a missed standing car cost what ten false alarms do.
LEAD_STOP_POS_WEIGHT = 10.0


# The expert's target under which a frame of one of `stop_reasons` is a stop (validation's STOP_TARGET).
REASON_STOP_TARGET = 1.0  # m/s


def lead_stop_targets(privileged: Tensor, reasons: Sequence[str] = ()) -> tuple[Tensor, Tensor]:
    """(1 where a vehicle under LEAD_STOP_SPEED is within LEAD_STOP_DISTANCE ahead, mask of known), both [B];
    also 1 where the expert stops (a target under REASON_STOP_TARGET) for one of `reasons` (its reason:
    privileged's fifth column; the training config's `stop_label_reasons()`)."""
    ld, ls = privileged[:, 1], privileged[:, 2]
    known = ld.isfinite() & ls.isfinite()
    close = known & (ld < LEAD_STOP_DISTANCE) & (ls < LEAD_STOP_SPEED)
    if reasons:
        if privileged.shape[1] < 5:
            raise ValueError(f"stop_reasons {', '.join(reasons)} need the expert's reason of each sample "
                             "(privileged's fifth column)")
        ids = torch.tensor([float(SPEED_REASONS.index(r)) for r in reasons], device=privileged.device)
        stop = torch.isin(privileged[:, 4], ids) & (privileged[:, 0] < REASON_STOP_TARGET)
        close, known = close | stop, known | stop
    return close.float(), known


def aux_loss(aux: Tensor, privileged: Tensor, norm: Norm, loss: str = "l1", reasons: Sequence[str] = ()) -> Tensor:
    """Mean over the known labels: regression terms with the action loss's criterion, BCE for the light and,
    for heads with the lead-stop output (models.base.aux_outputs), weighted BCE for it (`lead_stop_targets`)."""
    target, known = aux_targets(privileged, norm)
    crit = _criterion(loss)
    w = known.float()
    reg = crit(aux[:, :3], target[:, :3], reduction="none") * w[:, :3]
    bce = torch.nn.functional.binary_cross_entropy_with_logits(aux[:, 3], target[:, 3], reduction="none") * w[:, 3]
    total, count = reg.sum() + bce.sum(), w.sum()
    if aux.shape[1] > len(AUX_NAMES):
        close, seen = lead_stop_targets(privileged, reasons)
        stop = torch.nn.functional.binary_cross_entropy_with_logits(
            aux[:, len(AUX_NAMES)], close, reduction="none",
            pos_weight=torch.tensor(LEAD_STOP_POS_WEIGHT, device=aux.device))  # fmt: skip
        total, count = total + (stop * seen.float()).sum(), count + seen.float().sum()
    return total / count.clamp_min(1.0)
