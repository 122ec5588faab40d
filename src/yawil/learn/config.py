"""Every setting of a training run (`TrainConfig`, the paper's values as defaults), read from YAML or a
mapping with unknown keys refused, and what may change when a run is resumed."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from yawil.learn.augment import AugmentConfig
from yawil.policy.runtime import DEVICES, PRECISIONS, SWITCHES

LOSSES = ("l1", "mse", "smooth_l1")
BRAKE_LOSSES = ("same", "bce")
STOP_LABEL_REASONS = ("vehicle", "pedestrian", "junction")  # expert reasons `stop_reasons` may name (schema's)
# What may change when a run is resumed: budgets and where/how it runs, never what it learns from.
RESUMABLE_CHANGES = frozenset(
    {"epochs", "max_steps", "max_minutes", "device", "precision", "channels_last", "workers", "threads", "progress",
     "keep_steps", "data_on_device"}
)


# ------------------------------------------------------------------------------------------------- config
@dataclass
class TrainConfig:
    """Every setting of a run. Defaults are the paper's (Sec. IV-A): Adam, batch 512, lr 1e-3 halved
    every 10 epochs, 100 epochs, loss = 1.0 * L1(actions) + 0.1 * L1(speed)."""

    model: str = "yilratt"
    data: list[str] = field(default_factory=list)
    out: str = "runs/train"
    model_args: dict[str, Any] = field(default_factory=dict)
    pretrained: str | None = None
    epochs: int = 100
    batch_size: int = 512
    lr: float = 1e-3
    lr_step_epochs: int = 10
    lr_gamma: float = 0.5
    weight_decay: float = 0.0
    alpha: float = 1.0
    beta: float = 0.1
    loss: str = "l1"
    val_fraction: float = 0.1
    seed: int = 0
    workers: int = 0
    threads: int = 0  # torch intra-op threads; 0: the cores left after the loader workers (auto_threads)
    device: str = "auto"
    precision: str = "auto"  # auto: bf16 on a CPU with native bf16, fp16 + GradScaler on CUDA, else fp32
    channels_last: str = "auto"  # auto: on for the CPU and CUDA (measured faster, docs/performance.md)
    # Both splits read once into tensors on the device, batches drawn there (yawil.learn.resident): on a GPU no
    # batch is read or copied from the host. The same batches and weights as the DataLoader's (tested).
    data_on_device: bool = False
    max_steps: int | None = None  # total optimiser steps of the run, across resumes
    max_minutes: float | None = None  # wall-time budget of this invocation
    log_every: int = 10  # steps between TensorBoard points
    # Share of slowing-down frames (expert brake > BRAKE_LABEL at over BRAKE_MIN_SPEED) in each epoch, drawn
    # with replacement; None keeps the data's own share (about 0.07 in town01). Ours, not the paper's.
    brake_fraction: float | None = None
    # Share of the draws per epoch for the frames of each named expert reason (schema-2 `speed_reason`, e.g.
    # {"vehicle": 0.2}), the other frames sharing the rest; drawn with replacement. Why: the expert slows for a
    # vehicle ahead on ~4 % of town01's frames, too few for a small net to learn to see the car. Ours.
    reason_fractions: dict[str, float] = field(default_factory=dict)
    # Inertia countermeasure (CILRS, Codevilla et al. 2019): with this probability per training sample the
    # speed input is replaced by the training mean (0 once normalised), so the net cannot copy its speed.
    speed_dropout: float = 0.0
    # Weight of the aux heads' loss on the expert's privileged labels (a model built with aux=true); 0: off.
    aux_weight: float = 0.0
    # Criterion of the aux head's regression terms (target speed, lead distance, lead speed): "same" as `loss`,
    # or one of LOSSES. Why "mse": under L1 a head predicts the median, and the frames that matter (a lead
    # vehicle close ahead: 4 % of them) never move the median; the mean they do (docs/experiments.md).
    aux_loss: str = "same"
    # The lead-stop output's positives also include the frames where the expert stops for a pedestrian (its
    # reason `pedestrian`, its target under STOP_TARGET): one "a road user stands in my way" class. Why: the dense
    # cell's pedestrian collisions come at cruise speed, the head never slowing (docs/experiments.md, 2026-12-07
    # second session); a rare event is what a weighted class learns, as the vehicle stop did. Ours.
    stop_pedestrians: bool = False
    # The same for the expert's stops of each reason named (STOP_LABEL_REASONS; "pedestrian" is stop_pedestrians):
    # "vehicle" and "junction" add the stops for crossing and turning traffic, which the lead-stop label (a standing
    # car ahead) leaves out: the shipped model's Dense vehicle collisions (docs/experiments.md, 2026-12-07 seventh
    # session; TransFuser++'s brake class is set for every reason its expert brakes). Ours.
    stop_reasons: list[str] = field(default_factory=list)
    # "same": the brake is one of the three action components under `loss`; "bce": binary cross-entropy of
    # the (sigmoid) brake output against the expert's brake. L1's optimum is the conditional median, which
    # for a brake pressed on ~7 % of the frames is 0 wherever the image leaves doubt; BCE's is the mean.
    brake_loss: str = "same"
    # Decay of an exponential moving average of the weights (yawil.learn.ema; 0: off, e.g. 0.995: about the last
    # 200 steps). The checkpoints then drive with the average and validate it. Ours, not the paper's: one
    # checkpoint's driving varied by 23 points out of 100 between steps 750 and 1,500 of one run.
    ema: float = 0.0
    # Start from the weights and normalisation of this yawil checkpoint (fine-tuning, e.g. a DAgger round).
    init_from: str | None = None
    # Optimiser steps after which the checkpoint is also kept as step_NNNNNN.pt (learning curves, selection).
    keep_steps: list[int] = field(default_factory=list)
    progress: bool = True
    augment: AugmentConfig = field(default_factory=AugmentConfig)

    def __post_init__(self) -> None:
        if isinstance(self.augment, Mapping):
            self.augment = augment_from_dict(self.augment, "augment")
        if isinstance(self.data, str):
            self.data = [self.data]
        self.data = [str(d) for d in self.data]
        self.validate()

    def validate(self) -> None:
        def need(ok: bool, name: str, want: str) -> None:
            if not ok:
                raise ValueError(f"train config: {name}={getattr(self, name)!r}, expected {want}")

        need(isinstance(self.model, str) and bool(self.model), "model", "a model name")
        need(isinstance(self.model_args, dict), "model_args", "a mapping of model options")
        from yawil import models

        models.registry.check_options(self.model, **self.model_args)  # before any data is read
        for name in ("epochs", "batch_size", "lr_step_epochs", "log_every"):
            need(_is_int(getattr(self, name)) and getattr(self, name) >= 1, name, "an integer >= 1")
        for name in ("workers", "threads", "seed"):
            need(_is_int(getattr(self, name)) and getattr(self, name) >= 0, name, "an integer >= 0")
        for name in ("lr", "lr_gamma"):
            need(_is_num(getattr(self, name)) and getattr(self, name) > 0, name, "a number > 0")
        for name in ("weight_decay", "alpha", "beta"):
            need(_is_num(getattr(self, name)) and getattr(self, name) >= 0, name, "a number >= 0")
        need(_is_num(self.val_fraction) and 0.0 <= self.val_fraction < 1.0, "val_fraction",
             "a number in [0, 1) (0: no validation, best.pt is the last checkpoint)")
        need(self.loss in LOSSES, "loss", f"one of {LOSSES}")
        need(self.brake_loss in BRAKE_LOSSES, "brake_loss", f"one of {BRAKE_LOSSES}")
        need(self.aux_loss == "same" or self.aux_loss in LOSSES, "aux_loss", f"'same' or one of {LOSSES}")
        need(self.device in DEVICES, "device", f"one of {DEVICES}")
        need(self.precision in PRECISIONS, "precision", f"one of {PRECISIONS}")
        need(self.channels_last in SWITCHES, "channels_last", f"one of {SWITCHES}")
        need(self.max_steps is None or (_is_int(self.max_steps) and self.max_steps >= 1), "max_steps", "None or >= 1")
        need(self.max_minutes is None or (_is_num(self.max_minutes) and self.max_minutes > 0), "max_minutes", "None or > 0")
        need(isinstance(self.progress, bool), "progress", "true or false")
        need(isinstance(self.data_on_device, bool), "data_on_device", "true or false")
        need(self.brake_fraction is None or (_is_num(self.brake_fraction) and 0.0 < self.brake_fraction < 1.0),
             "brake_fraction", "None or a number in (0, 1)")
        from yawil.data.schema import SPEED_REASONS

        need(isinstance(self.reason_fractions, dict) and all(
            k in SPEED_REASONS and _is_num(v) and 0.0 < v < 1.0 for k, v in self.reason_fractions.items())
             and sum(self.reason_fractions.values()) < 1.0, "reason_fractions",
             f"a mapping of expert reasons ({', '.join(SPEED_REASONS)}) to shares in (0, 1) summing to under 1")
        need(not (self.reason_fractions and self.brake_fraction is not None), "reason_fractions",
             "not together with brake_fraction (both set the epoch's sampling)")
        need(_is_num(self.speed_dropout) and 0.0 <= self.speed_dropout <= 1.0, "speed_dropout", "a number in [0, 1]")
        need(_is_num(self.aux_weight) and self.aux_weight >= 0.0, "aux_weight", "a number >= 0")
        if self.alpha == 0 and self.beta == 0 and self.aux_weight == 0:  # the steps would move no weight, exit 0
            raise ValueError("train config: every loss weight is 0 (alpha, beta, aux_weight): nothing would be learned")
        need(isinstance(self.stop_pedestrians, bool), "stop_pedestrians", "true or false")
        need(not self.stop_pedestrians or self.aux_weight > 0, "stop_pedestrians",
             "false unless aux_weight > 0 (it labels the aux head's lead-stop output)")
        need(isinstance(self.stop_reasons, list) and all(r in STOP_LABEL_REASONS for r in self.stop_reasons)
             and len(set(self.stop_reasons)) == len(self.stop_reasons), "stop_reasons",
             f"a list of distinct expert reasons among {', '.join(STOP_LABEL_REASONS)}")
        need(not self.stop_reasons or self.aux_weight > 0, "stop_reasons",
             "empty unless aux_weight > 0 (they label the aux head's lead-stop output)")
        need(_is_num(self.ema) and 0.0 <= self.ema < 1.0, "ema", "a decay in [0, 1) (0: no weight average)")
        need(self.init_from is None or (isinstance(self.init_from, str) and bool(self.init_from)), "init_from",
             "None or a checkpoint path")
        need(isinstance(self.keep_steps, list) and all(_is_int(v) and v >= 1 for v in self.keep_steps), "keep_steps",
             "a list of step counts >= 1")

    def stop_label_reasons(self) -> tuple[str, ...]:
        """The expert reasons whose stops are positives of the lead-stop output (`stop_reasons`, and
        "pedestrian" where `stop_pedestrians`, its older spelling)."""
        return tuple(dict.fromkeys([*self.stop_reasons, *(["pedestrian"] if self.stop_pedestrians else [])]))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["augment"] = self.augment.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "config") -> TrainConfig:
        """Build from a mapping; an unknown key is an error naming it and where it came from."""
        if not isinstance(d, Mapping):
            raise ValueError(f"{source}: expected a mapping of train settings, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{source}: unknown train setting(s) {unknown}; known: {sorted(known)}")
        values = dict(d)
        if "augment" in values:
            values["augment"] = augment_from_dict(values["augment"], f"{source}: augment")
        return cls(**values)

    @classmethod
    def from_yaml(cls, path: str | os.PathLike[str], overrides: Mapping[str, Any] | None = None) -> TrainConfig:
        """Settings from a YAML file, then `overrides` (the command line) on top."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"train config file {path} does not exist")
        try:
            loaded = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            raise ValueError(f"{path}: not valid YAML: {err}") from err
        return cls.from_dict(merge_settings(loaded, overrides or {}, str(path)), str(path))


def augment_from_dict(d: Any, source: str) -> AugmentConfig:
    if isinstance(d, AugmentConfig):
        return d
    if not isinstance(d, Mapping):
        raise ValueError(f"{source}: expected a mapping of augmentation settings, got {d!r}")
    known = {f.name for f in fields(AugmentConfig)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"{source}: unknown augmentation setting(s) {unknown}; known: {sorted(known)}")
    return AugmentConfig(**dict(d))


def merge_settings(base: Mapping[str, Any], overrides: Mapping[str, Any], source: str = "config") -> dict[str, Any]:
    """`base` with `overrides` on top; `augment` is merged key by key so one option can be changed."""
    if not isinstance(base, Mapping):
        raise ValueError(f"{source}: expected a mapping of train settings, got {type(base).__name__}")
    merged = dict(base)
    for key, value in overrides.items():
        if key == "augment" and isinstance(value, Mapping):
            inner = merged.get("augment", {})
            inner = inner.to_dict() if isinstance(inner, AugmentConfig) else dict(inner or {})
            inner.update(value)
            merged["augment"] = inner
        else:
            merged[key] = value
    return merged


def _is_int(v: Any) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) and math.isfinite(float(v))


# ------------------------------------------------------------------------------------------ device, AMP
# Runtime, resolve_runtime and cpu_has_fast_bf16 live in yawil.policy.runtime (the agent shares them).


def auto_threads(workers: int) -> int:
    """Torch threads that leave a core to each DataLoader worker.

    Measured on the 2-core machine: a YILRatt step with 2 threads while other processes hold a core ran at
    1.3 samples/s, with 1 thread at 6.3 (OpenMP threads spin while they wait for a busy core), so the
    trainer never asks for more threads than the cores its own loader workers leave free.
    """
    return max(1, (os.cpu_count() or 1) - workers)
