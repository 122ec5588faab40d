"""Validation: mean loss and errors over the held-out split, no augmentation (the columns of metrics.csv)."""

from __future__ import annotations

import math
from typing import Any

import torch

from yawil.learn.config import TrainConfig
from yawil.learn.loss import compute_loss, lead_stop_targets
from yawil.learn.sampling import BRAKE_LABEL, BRAKE_MIN_SPEED, prepare_batch
from yawil.models.base import AUX_NAMES, LEAD_STOP_FIRES
from yawil.policy.checkpoint import Norm
from yawil.policy.runtime import Runtime

METRIC_FIELDS = (
    "epoch", "step", "train_loss", "val_loss", "val_l1_steer", "val_l1_throttle", "val_l1_brake",
    "val_l1_speed", "val_brake_recall", "val_l1_target_speed", "val_stop_recall", "val_lead_stop_recall",
    "val_lead_stop_precision", "lr", "time", "samples_per_s",
)  # fmt: skip
STOP_TARGET = 1.0  # m/s: an expert target below this while the car moves is a stop (car, light, pedestrian)


@torch.inference_mode()
def validate(
    model: torch.nn.Module, loader: Any, norm: Norm, kind: str | None, cfg: TrainConfig, runtime: Runtime
) -> dict[str, float]:
    """Mean loss and mean absolute errors (actions, speed in m/s) over the validation split, no augmentation."""
    was_training = model.training
    model.eval()
    total, n = 0.0, 0
    abs_sum = torch.zeros(4, dtype=torch.float64)
    slowing, caught = 0, 0  # frames where the expert brakes at speed, and those where the net brakes too
    ts_err, ts_n, stops, stops_seen = 0.0, 0, 0, 0  # aux head: target-speed error (m/s), stops foreseen
    close_n, close_hit, close_said = 0, 0, 0  # lead-stop output: positives, those found, frames it fires on
    uses_command = bool(getattr(model, "uses_command", False))
    for raw in loader:
        b = prepare_batch(raw, norm, kind, uses_command, runtime)
        with runtime.autocast():
            loss, pred, out = compute_loss(model, b, cfg, norm)
        size = b.image.shape[0]
        total += float(loss) * size
        n += size
        speed_pred = norm.speed_inverse(out.speed.float())
        err = torch.cat([(pred - b.action).abs(), (speed_pred - b.speed_raw).abs()], dim=1)
        abs_sum += err.sum(dim=0).double().cpu()
        want = (b.action[:, 2] > BRAKE_LABEL) & (b.speed_raw[:, 0] > BRAKE_MIN_SPEED)
        slowing += int(want.sum())
        caught += int((want & (pred[:, 2] >= BRAKE_LABEL)).sum())
        if out.aux is not None and b.privileged is not None:  # what `--speed-control` would drive by
            target = b.privileged[:, 0]
            known = target.isfinite()
            guess = norm.speed_inverse(out.aux[:, :1].float())[:, 0].clamp_min(0.0)
            ts_err += float((guess - target).abs()[known].sum())
            ts_n += int(known.sum())
            stop = known & (target < STOP_TARGET) & (b.speed_raw[:, 0] > BRAKE_MIN_SPEED)
            stops += int(stop.sum())
            stops_seen += int((stop & (guess < STOP_TARGET)).sum())
            if out.aux.shape[1] > len(AUX_NAMES):
                close, seen = lead_stop_targets(b.privileged, cfg.stop_label_reasons())
                fired = seen & (torch.sigmoid(out.aux[:, len(AUX_NAMES)].float()) > LEAD_STOP_FIRES)
                close_n += int(close.sum())
                close_hit += int((fired & (close > 0)).sum())
                close_said += int(fired.sum())
    model.train(was_training)
    if n == 0:
        raise ValueError("the validation split is empty: use more episodes or a larger val_fraction")
    l1 = (abs_sum / n).tolist()
    recall = caught / slowing if slowing else math.nan  # the agent's brake threshold is BRAKE_LABEL too
    return {"val_loss": total / n, "val_l1_steer": l1[0], "val_l1_throttle": l1[1], "val_l1_brake": l1[2],
            "val_l1_speed": l1[3], "val_brake_recall": recall,
            "val_l1_target_speed": ts_err / ts_n if ts_n else math.nan,
            "val_stop_recall": stops_seen / stops if stops else math.nan,
            "val_lead_stop_recall": close_hit / close_n if close_n else math.nan,
            "val_lead_stop_precision": close_hit / close_said if close_said else math.nan}


VAL_KEYS = ("val_loss", "val_l1_steer", "val_l1_throttle", "val_l1_brake", "val_l1_speed", "val_brake_recall",
            "val_l1_target_speed", "val_stop_recall", "val_lead_stop_recall", "val_lead_stop_precision")
