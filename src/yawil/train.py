"""Training loop of every registered model, with the paper's settings as defaults (docs/training.md).

    cfg = TrainConfig(model="yilratt", data=["data/town01"], out="runs/yilratt")
    result = train(cfg)                  # runs/yilratt/{best.pt,last.pt,config.yaml,metrics.csv,loss.png,tb/}
    result = train(cfg, resume=True)     # continues from runs/yilratt/last.pt, exactly

Determinism: the data order of epoch e is drawn from (seed, e) (a permutation, or draws with replacement
with `brake_fraction`), the augmentation of step s
uses a generator seeded from (seed, s), the model is built with `seed`, and the torch/numpy/python RNG
states are saved, so a stopped run resumed gives the weights an uninterrupted run would have.

Under `torchrun` (WORLD_SIZE > 1) the same loop runs on every rank with DistributedDataParallel, each rank
on its slice of every global batch; rank 0 validates and writes (yawil.distributed, docs/training.md).
"""

from __future__ import annotations

import csv
import io
import math
import os
import random
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import Tensor

from yawil import distributed
from yawil.augment import AugmentConfig, augment_batch
from yawil.checkpoint import Norm, load_checkpoint, make_checkpoint, save_checkpoint
from yawil.distributed import Dist
from yawil.fileio import write_atomic
from yawil.policy.inputs import InputSpec, guidance_key
from yawil.policy.runtime import DEVICES, PRECISIONS, Runtime, resolve_runtime

LOSSES = ("l1", "mse", "smooth_l1")
BRAKE_LOSSES = ("same", "bce")
SWITCHES = ("auto", "on", "off")
# What may change when a run is resumed: budgets and where/how it runs, never what it learns from.
RESUMABLE_CHANGES = frozenset(
    {"epochs", "max_steps", "max_minutes", "device", "precision", "channels_last", "workers", "threads", "progress",
     "keep_steps"}
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
    # "same": the brake is one of the three action components under `loss`; "bce": binary cross-entropy of
    # the (sigmoid) brake output against the expert's brake. L1's optimum is the conditional median, which
    # for a brake pressed on ~7 % of the frames is 0 wherever the image leaves doubt; BCE's is the mean.
    brake_loss: str = "same"
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
        need(self.device in DEVICES, "device", f"one of {DEVICES}")
        need(self.precision in PRECISIONS, "precision", f"one of {PRECISIONS}")
        need(self.channels_last in SWITCHES, "channels_last", f"one of {SWITCHES}")
        need(self.max_steps is None or (_is_int(self.max_steps) and self.max_steps >= 1), "max_steps", "None or >= 1")
        need(self.max_minutes is None or (_is_num(self.max_minutes) and self.max_minutes > 0), "max_minutes", "None or > 0")
        need(isinstance(self.progress, bool), "progress", "true or false")
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
        need(self.init_from is None or (isinstance(self.init_from, str) and bool(self.init_from)), "init_from",
             "None or a checkpoint path")
        need(isinstance(self.keep_steps, list) and all(_is_int(v) and v >= 1 for v in self.keep_steps), "keep_steps",
             "a list of step counts >= 1")

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
# Runtime, resolve_runtime and cpu_has_fast_bf16 live in yawil.policy.runtime (the agent shares them); Runtime and
# resolve_runtime are imported above, so `from yawil.train import Runtime, resolve_runtime` keeps working.


def auto_threads(workers: int) -> int:
    """Torch threads that leave a core to each DataLoader worker.

    Measured on the 2-core machine: a YILRatt step with 2 threads while other processes hold a core ran at
    1.3 samples/s, with 1 thread at 6.3 (OpenMP threads spin while they wait for a busy core), so the
    trainer never asks for more threads than the cores its own loader workers leave free.
    """
    return max(1, (os.cpu_count() or 1) - workers)


# ------------------------------------------------------------------------------------------------- data
@dataclass
class Batch:
    """A training batch on the device, preprocessed exactly as the agent preprocesses an observation."""

    image: Tensor  # [B, 3, H, W] float in [0, 1]
    speed: Tensor  # [B, 1] normalised
    guidance: Tensor | None  # [B, D] normalised
    command: Tensor | None  # [B] int64 branch index
    action: Tensor  # [B, 3] targets
    speed_raw: Tensor  # [B, 1] m/s
    privileged: Tensor | None = None  # [B, 4] m/s, m, m/s, 0/1 (NaN / -1 unknown): aux-head targets


def prepare_batch(
    raw: Mapping[str, Any], norm: Norm, kind: str | None, uses_command: bool, runtime: Runtime
) -> Batch:
    """The model inputs through the one contract (`yawil.policy.inputs`, as the agent's), plus the targets."""
    x = InputSpec(norm, kind, uses_command, runtime).from_batch(raw)
    assert x.speed_raw is not None  # from_batch always keeps it
    dev = runtime.device
    action = torch.as_tensor(raw["action"]).to(dev).float()
    privileged = torch.as_tensor(raw["privileged"]).to(dev).float() if "privileged" in raw else None
    return Batch(x.image, x.speed, x.guidance, x.command, action, x.speed_raw, privileged)


def label_arrays(dataset: Any, kind: str | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Speed and guidance of every training sample, for the normalisation statistics."""
    cols = label_columns(dataset, ["speed"] + ([] if kind is None else [guidance_key(kind)]))
    return cols[0].reshape(-1), (cols[1] if kind is not None else None)


def label_columns(dataset: Any, names: Sequence[str]) -> list[np.ndarray]:
    """Label columns of every sample: `dataset.labels(name)` (no image decoded) when it has it, else read
    sample by sample once (correct, but it decodes the images). "brake" is the action's third component."""
    if hasattr(dataset, "labels"):
        return [np.asarray(dataset.labels(n), dtype=np.float64) for n in names]
    rows = [dataset[i] for i in range(len(dataset))]

    def value(r: Mapping[str, Any], n: str) -> np.ndarray:
        return np.asarray(r["action"], dtype=np.float64)[2] if n == "brake" else np.asarray(r[n], dtype=np.float64)

    return [np.stack([value(r, n) for r in rows]) if rows else np.zeros(0) for n in names]


def epoch_batches(n: int, batch_size: int, seed: int, epoch: int, p: np.ndarray | None = None) -> list[list[int]]:
    """The batches of one epoch, drawn from (seed, epoch) so that a resumed run finds them again.

    Without `p` a permutation; with `p` (a probability per sample) n draws with replacement.
    """
    rng = np.random.default_rng([seed, epoch])
    order = rng.permutation(n) if p is None else rng.choice(n, size=n, replace=True, p=p)
    return [order[i : i + batch_size].tolist() for i in range(0, n, batch_size)]


BRAKE_LABEL = 0.1  # an expert brake above this marks a braking frame (the agent's own brake threshold)
# Standing frames are not oversampled: counting them too (brake_fraction 0.3) taught a YILRatt to stay
# standing once stopped (docs/training.md, "A third run").
BRAKE_MIN_SPEED = 1.0  # m/s


def brake_weights(brake: np.ndarray, speed: np.ndarray, fraction: float) -> np.ndarray:
    """Sampling probabilities that give slowing-down frames `fraction` of the draws, uniform within each group."""
    brake = np.asarray(brake, dtype=np.float64).reshape(-1)
    speed = np.asarray(speed, dtype=np.float64).reshape(-1)
    if brake.shape != speed.shape:
        raise ValueError(f"brake ({brake.size}) and speed ({speed.size}) labels differ in length")
    slowing = (brake > BRAKE_LABEL) & (speed > BRAKE_MIN_SPEED)
    k = int(slowing.sum())
    if k == 0 or k == slowing.size:
        raise ValueError(
            f"brake_fraction={fraction}: the training split has {k} slowing-down frames of {slowing.size} "
            f"(brake > {BRAKE_LABEL} at over {BRAKE_MIN_SPEED} m/s); both kinds are needed to rebalance"
        )
    return np.where(slowing, fraction / k, (1.0 - fraction) / (slowing.size - k))


def reason_weights(reason: np.ndarray, fractions: Mapping[str, float]) -> np.ndarray:
    """Sampling probabilities that give the frames of each named expert reason (SPEED_REASONS) its share of the
    draws and the other frames the rest, uniform within each group."""
    from yawil.data.schema import SPEED_REASONS

    reason = np.asarray(reason, dtype=np.int64).reshape(-1)
    p = np.zeros(reason.size, dtype=np.float64)
    rest = np.ones(reason.size, dtype=bool)
    for name, share in fractions.items():
        group = reason == SPEED_REASONS.index(name)
        if not group.any():
            raise ValueError(f"reason_fractions: the training split has no frame whose expert reason is {name!r} "
                             "(schema-1 data has no reasons; `yawil data stats` counts them)")
        p[group] = share / group.sum()
        rest &= ~group
    if not rest.any():
        raise ValueError("reason_fractions: every training frame is in a named group; nothing is left for the rest")
    p[rest] = (1.0 - sum(fractions.values())) / rest.sum()
    return p


def sequential_batches(n: int, batch_size: int) -> list[list[int]]:
    return [list(range(i, min(i + batch_size, n))) for i in range(0, n, batch_size)]


def drop_speed(speed: Tensor, p: float, gen: torch.Generator) -> Tensor:
    """Speed-input dropout: each sample's normalised speed becomes 0 (the training mean) with probability p."""
    keep = torch.rand(speed.shape, generator=gen, device=speed.device) >= p
    return speed * keep.to(speed.dtype)


def step_generator(seed: int, step: int, device: torch.device, rank: int | None = None) -> torch.Generator:
    """Augmentation randomness of one step, independent of everything else that happened; under torchrun
    each rank draws its own, from (seed, step, rank)."""
    entropy = [seed, step, 0xA5] if rank is None else [seed, step, 0xA5, rank]
    g = torch.Generator(device=device)
    g.manual_seed(int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0] >> 1))
    return g


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
        loss = loss + cfg.aux_weight * aux_loss(out.aux.float(), batch.privileged, norm, cfg.loss)
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

    ts, ld, ls, light = privileged.unbind(dim=1)
    target = torch.stack([norm.speed(ts[:, None])[:, 0], ld / LEAD_RANGE, norm.speed(ls[:, None])[:, 0], light], dim=1)
    known = torch.stack([ts.isfinite(), ld.isfinite(), ls.isfinite(), light >= 0], dim=1)
    return torch.where(known, target, torch.zeros_like(target)), known


def aux_loss(aux: Tensor, privileged: Tensor, norm: Norm, loss: str = "l1") -> Tensor:
    """Mean over the known labels: regression terms with the action loss's criterion, BCE for the light."""
    target, known = aux_targets(privileged, norm)
    crit = _criterion(loss)
    w = known.float()
    reg = crit(aux[:, :3], target[:, :3], reduction="none") * w[:, :3]
    bce = torch.nn.functional.binary_cross_entropy_with_logits(aux[:, 3], target[:, 3], reduction="none") * w[:, 3]
    return (reg.sum() + bce.sum()) / w.sum().clamp_min(1.0)


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


@dataclass
class TrainResult:
    out: Path
    epochs_done: int
    steps: int
    best_val: float
    metrics: list[dict[str, float]]
    stopped_by: str  # "epochs" | "max_steps" | "max_minutes"


# ------------------------------------------------------------------------------------------------- loop
METRIC_FIELDS = (
    "epoch", "step", "train_loss", "val_loss", "val_l1_steer", "val_l1_throttle", "val_l1_brake",
    "val_l1_speed", "val_brake_recall", "val_l1_target_speed", "val_stop_recall", "lr", "time", "samples_per_s",
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
    model.train(was_training)
    if n == 0:
        raise ValueError("the validation split is empty: use more episodes or a larger val_fraction")
    l1 = (abs_sum / n).tolist()
    recall = caught / slowing if slowing else math.nan  # the agent's brake threshold is BRAKE_LABEL too
    return {"val_loss": total / n, "val_l1_steer": l1[0], "val_l1_throttle": l1[1], "val_l1_brake": l1[2],
            "val_l1_speed": l1[3], "val_brake_recall": recall,
            "val_l1_target_speed": ts_err / ts_n if ts_n else math.nan,
            "val_stop_recall": stops_seen / stops if stops else math.nan}


VAL_KEYS = ("val_loss", "val_l1_steer", "val_l1_throttle", "val_l1_brake", "val_l1_speed", "val_brake_recall",
            "val_l1_target_speed", "val_stop_recall")


def _loader(dataset: Any, batches: list[list[int]], cfg: TrainConfig, runtime: Runtime) -> Any:
    from torch.utils.data import DataLoader

    return DataLoader(
        dataset,
        batch_sampler=batches,
        num_workers=cfg.workers,
        pin_memory=runtime.device.type == "cuda",
        generator=torch.Generator().manual_seed(cfg.seed),  # keeps the global RNG untouched
        persistent_workers=False,
    )


def open_splits(cfg: TrainConfig) -> tuple[Any, Any, dict[str, Any]]:
    """Train and validation datasets (split by episode) and the guidance config they were written with."""
    from yawil import data

    if not cfg.data:
        raise ValueError("train config: data is empty; give at least one dataset root (--data DIR)")
    for root in cfg.data:
        if not Path(root).exists():
            raise FileNotFoundError(f"dataset root {root} does not exist")
    fraction = cfg.val_fraction
    n = len(data.split_episodes(cfg.data, 0.0, cfg.seed)[0])
    if fraction > 0 and n < 2:  # the smallest natural first run (`collect --frames 400`) must train
        print(f"warning: {n} episode in {', '.join(map(str, cfg.data))}: too few to hold one out, training without "
              "validation (best.pt is the last checkpoint); collect more episodes for a validation loss",
              file=sys.stderr)
        fraction = 0.0
    train_eps, val_eps = data.split_episodes(cfg.data, fraction, cfg.seed)
    train_ds = data.DrivingDataset(cfg.data, episodes=train_eps)
    val_ds = data.DrivingDataset(cfg.data, episodes=val_eps)
    return train_ds, val_ds, dataset_guidance_config(train_ds)


def dataset_guidance_config(dataset: Any) -> dict[str, Any]:
    gc = dataset.guidance_config
    return dict(gc.to_dict() if hasattr(gc, "to_dict") else gc)


def build_model(cfg: TrainConfig, guidance_dims: Mapping[str, int]) -> Any:
    """Create the network; a guided model gets the guidance width of the dataset unless told otherwise."""
    from yawil import models

    args = dict(cfg.model_args)
    model = models.create(cfg.model, seed=cfg.seed, **args)
    kind = model.guidance
    if kind is not None and "guidance_dim" not in args and model.guidance_dim != guidance_dims[kind]:
        model = models.create(cfg.model, seed=cfg.seed, guidance_dim=guidance_dims[kind], **args)
    if kind is not None and model.guidance_dim != guidance_dims[kind]:
        raise ValueError(
            f"model_args.guidance_dim={model.guidance_dim} but the dataset's {kind} guidance has {guidance_dims[kind]} values"
        )
    if cfg.pretrained is not None:
        if not Path(cfg.pretrained).is_file():
            raise FileNotFoundError(f"pretrained weights {cfg.pretrained} do not exist")
        model.load_pretrained(cfg.pretrained)
    return model


def check_resumable(saved: Mapping[str, Any], cfg: TrainConfig, path: Path) -> None:
    now = cfg.to_dict()
    for key, value in now.items():
        if key in RESUMABLE_CHANGES or key == "out":
            continue
        if saved.get(key) != value:
            raise ValueError(
                f"cannot resume {path}: setting {key!r} was {saved.get(key)!r}, now {value!r} "
                f"(only {sorted(RESUMABLE_CHANGES)} may change on resume)"
            )


def train(
    cfg: TrainConfig, resume: bool = False, splits: tuple[Any, Any, Mapping[str, Any]] | None = None,
    dist_backend: str | None = None,
) -> TrainResult:  # fmt: skip
    """Train (or resume) a run in `cfg.out`; returns when the epochs or a budget are used up.

    `splits` = (train dataset, validation dataset, guidance config dict) replaces the datasets that
    `cfg.data` names, for data already in memory; the datasets follow yawil.data.DrivingDataset's contract
    (sample dicts, and `labels(name)` giving a label array without decoding images). One process at a time
    writes a run folder (yawil.locking). Under torchrun (WORLD_SIZE > 1) every rank calls this; the process
    group is initialised here unless the caller did (`dist_backend`: gloo or nccl; default by the device).
    """
    from yawil.locking import folder_lock

    world = distributed.world_from_env()
    if world is None:
        with folder_lock(cfg.out, "training run"):
            return _train(cfg, resume, splits)
    distributed.check_batch_size(cfg.batch_size, world[1])
    d = distributed.start(resolve_runtime(cfg.device, cfg.precision, cfg.channels_last).device.type, dist_backend)
    try:
        if not d.main:
            return _train(cfg, resume, splits, d)
        with folder_lock(cfg.out, "training run"):  # rank 0 writes the folder
            return _train(cfg, resume, splits, d)
    finally:
        distributed.stop(d)


def _train(
    cfg: TrainConfig, resume: bool, splits: tuple[Any, Any, Mapping[str, Any]] | None, d: Dist | None = None
) -> TrainResult:
    torch.set_num_threads(cfg.threads or (auto_threads(cfg.workers) if d is None else distributed.auto_threads(d, cfg.workers)))
    main = d is None or d.main  # the process that validates and writes
    out = Path(cfg.out)
    runtime = resolve_runtime(cfg.device, cfg.precision, cfg.channels_last)
    if d is not None and runtime.device.type == "cuda":
        runtime = replace(runtime, device=torch.device("cuda", d.local_rank))
    train_ds, val_ds, guidance_config = open_splits(cfg) if splits is None else splits
    guidance_config = dict(guidance_config)
    from yawil.guidance import GuidanceConfig

    dims = GuidanceConfig.from_dict(guidance_config).dims()
    model = build_model(cfg, dims)
    kind: str | None = model.guidance
    uses_command = bool(model.uses_command)

    ckpt: dict[str, Any] | None = None
    if resume:
        ckpt = load_checkpoint(out / "last.pt", map_location=runtime.device)
        check_resumable(ckpt["train_config"], cfg, out / "last.pt")
        model.load_state_dict(ckpt["state_dict"])
        norm = Norm.from_dict(ckpt["norm"])
    elif cfg.init_from is not None:
        init = load_checkpoint(cfg.init_from, map_location="cpu")
        if init["model_name"] != cfg.model:
            raise ValueError(f"init_from {cfg.init_from}: a {init['model_name']} checkpoint, but the model is {cfg.model}")
        if dict(init["guidance_config"]) != guidance_config:
            raise ValueError(f"init_from {cfg.init_from}: guidance config {init['guidance_config']} differs from the "
                             f"data's {guidance_config}")
        try:
            model.load_state_dict(init["state_dict"])
        except RuntimeError as err:
            raise ValueError(f"init_from {cfg.init_from}: weights do not fit model {cfg.model} "
                             f"with model_args {cfg.model_args}: {str(err).splitlines()[0]}") from None
        norm = Norm.from_dict(init["norm"])  # the inputs keep the scale the weights learned
    else:
        norm = Norm.from_arrays(*label_arrays(train_ds, kind))
    if d is not None:  # W ranks of B / W samples then compute the batch statistics of one process with B
        model = distributed.sync_batchnorm(model, runtime.device.type)
    model.to(runtime.device)
    if runtime.channels_last:
        model.to(memory_format=torch.channels_last)  # type: ignore[call-arg]
    trainee = model if d is None else distributed.wrap(model, d, runtime.device)  # what the steps run
    # foreach: one kernel per step for all tensors, measured 2x faster than the per-tensor loop on the CPU
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=True)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=cfg.lr_step_epochs, gamma=cfg.lr_gamma)
    scaler = torch.amp.GradScaler("cuda", enabled=runtime.precision == "fp16")
    pos = Position()
    metrics: list[dict[str, float]] = []
    if ckpt is not None:
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        if "scaler" in ckpt and runtime.precision == "fp16":
            scaler.load_state_dict(ckpt["scaler"])
        pos = Position(**ckpt["position"])
        metrics = list(ckpt["metrics"])
        ranks = ckpt.get("rng_ranks")
        if d is None:
            set_rng_states(ckpt["rng"])
        elif ranks is not None and len(ranks) == d.world:  # each rank goes on with its own generators
            set_rng_states(ranks[d.rank])
        else:  # another world size saved it: each rank's generators from (seed, rank, step)
            seed_globals(int(np.random.SeedSequence([cfg.seed, d.rank, pos.step]).generate_state(1)[0]))
    else:
        if out.joinpath("last.pt").exists():
            raise FileExistsError(f"{out} already holds a run (last.pt); use --resume or another --out")
        # Dropout draws from the global generators: seed them so that a fresh run is reproducible.
        seed_globals(cfg.seed if d is None else distributed.rank_seed(cfg.seed, d.rank))
    if main:
        write_atomic(out / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False))

    from tqdm import tqdm

    if main:
        from torch.utils.tensorboard import SummaryWriter

        writer: Any = SummaryWriter(str(out / "tb"), purge_step=pos.step if resume else None)
    else:
        writer = distributed.NoWriter()
    val_loader = _loader(val_ds, sequential_batches(len(val_ds), cfg.batch_size), cfg, runtime)
    started = time.monotonic()
    stopped_by = "epochs"

    def save(path: Path) -> None:
        """The checkpoint of this position; under torchrun every rank calls it (their RNG states are
        gathered: `rng_ranks`) and rank 0 writes it."""
        rng = rng_states()
        extra: dict[str, Any] = {}
        if d is not None:
            extra["rng_ranks"] = distributed.gather_objects(rng, d)
            if not d.main:
                return
        save_checkpoint(make_checkpoint(
            model, norm, guidance_config, cfg.to_dict(), pos.epoch, pos.step, metrics,
            optimizer=optimizer.state_dict(),
            scheduler=scheduler.state_dict(),
            scaler=scaler.state_dict(),
            rng=rng,
            position=asdict(pos),
            runtime={"device": runtime.device.type, "precision": runtime.precision, "channels_last": runtime.channels_last},
            **extra,
        ), path)  # fmt: skip

    def sync() -> None:
        """Under torchrun: no rank leaves before rank 0 has written (torchrun stops the others when one exits)."""
        if d is not None:
            distributed.barrier(d)

    def end_of_period(partial: bool) -> None:
        """Validate, log, keep best and last. `partial`: a budget stopped the epoch midway. Without a validation
        split the metrics' validation columns are NaN and best.pt follows last.pt."""
        val = None
        if main:
            val = validate(model, val_loader, norm, kind, cfg, runtime) if len(val_ds) else dict.fromkeys(VAL_KEYS, math.nan)
        if d is not None:
            val = distributed.broadcast_object(val, d)  # every rank keeps the same metrics and best_val
        assert val is not None
        row: dict[str, float] = {
            "epoch": pos.epoch + (pos.batch / max(1, n_batches) if partial else 1),
            "step": pos.step,
            "train_loss": pos.loss_sum / max(1, pos.samples),
            **val,
            "lr": optimizer.param_groups[0]["lr"],
            "time": pos.seconds,
            "samples_per_s": pos.samples / max(pos.seconds, 1e-9),
        }
        metrics.append(row)
        for key in ("train_loss", *val):
            writer.add_scalar(f"epoch/{key}", row[key], pos.step)
        improved = row["val_loss"] < pos.best_val or not len(val_ds)
        if improved and len(val_ds):
            pos.best_val = row["val_loss"]
        if not partial:
            scheduler.step()
            pos.epoch += 1
            pos.batch, pos.loss_sum, pos.samples, pos.seconds = 0, 0.0, 0, 0.0
        save(out / "last.pt")
        if main:
            if improved:
                link_or_copy(out / "last.pt", out / "best.pt")
            write_metrics(out, metrics)
        writer.flush()

    keep_at = set(cfg.keep_steps)

    def keep(step: int) -> None:
        """The checkpoint after `step` steps, kept apart (its position resumes mid-epoch like last.pt)."""
        if step in keep_at:
            save(out / f"step_{step:06d}.pt")

    model.train()
    n_batches = 0
    if len(train_ds) == 0:
        raise ValueError("the training split is empty: the dataset roots hold no training frames")
    p = None
    if cfg.brake_fraction is not None:
        brake, speed = label_columns(train_ds, ["brake", "speed"])
        p = brake_weights(brake, speed, cfg.brake_fraction)
    elif cfg.reason_fractions:
        (reason,) = label_columns(train_ds, ["speed_reason"])
        p = reason_weights(reason, cfg.reason_fractions)
    while pos.epoch < cfg.epochs:
        if cfg.max_steps is not None and pos.step >= cfg.max_steps:
            stopped_by = "max_steps"
            break
        batches = epoch_batches(len(train_ds), cfg.batch_size, cfg.seed, pos.epoch, p)
        sizes: list[int] | None = None  # global batch sizes, under torchrun
        if d is None:
            loader = _loader(train_ds, batches[pos.batch :], cfg, runtime)
        else:
            batches = distributed.usable_batches(batches, d.world)
            mine, sizes = distributed.rank_batches(batches[pos.batch :], d)
            loader = _loader(train_ds, mine, cfg, runtime)
        n_batches = len(batches)
        bar = tqdm(
            total=n_batches, initial=pos.batch, desc=f"epoch {pos.epoch + 1}/{cfg.epochs}",
            disable=not cfg.progress or not main, unit="batch", dynamic_ncols=True,
        )  # fmt: skip
        try:
            with _stop_between_steps(announce=main):
                stop = _train_epoch(trainee, loader, optimizer, scaler, norm, kind, uses_command, cfg, runtime, pos,
                                    writer, bar, started, keep, d, sizes)
        except _StopRequested:
            # Ctrl-C or SIGTERM, taken between two steps: the state saved is exactly that after pos.step steps,
            # so --resume gives the weights of an uninterrupted run
            bar.close()
            if pos.batch > 0:
                end_of_period(partial=True)
            writer.close()
            if main:
                plot_losses(out, metrics)
                print(f"interrupted at step {pos.step}; resume with --resume", file=sys.stderr)
            sync()
            raise KeyboardInterrupt(f"stopped at step {pos.step}") from None
        except _DataError as err:
            # the weights are those after pos.step whole steps: save them, then name the data problem
            bar.close()
            if pos.batch > 0:
                end_of_period(partial=True)
            writer.close()
            sync()
            raise ValueError(f"cannot read a training batch ({err}); the run is saved at step {pos.step}: "
                             "check the data (yawil data check; a resumed collect re-collects damaged episodes), "
                             "then --resume") from None
        except KeyboardInterrupt:
            # a second Ctrl-C stops mid-step: the weights may be half-updated, so nothing is saved
            bar.close()
            writer.close()
            print(f"stopped at once; --resume continues from {out / 'last.pt'} as last saved", file=sys.stderr)
            raise
        bar.close()
        if stop:
            stopped_by = stop
            if pos.batch > 0:
                end_of_period(partial=True)
            break
        end_of_period(partial=False)
    writer.close()
    if main:
        plot_losses(out, metrics)
    sync()
    return TrainResult(out, pos.epoch, pos.step, pos.best_val, metrics, stopped_by)

class _StopRequested(Exception):
    """Raised between two optimiser steps after a Ctrl-C or SIGTERM."""


_STOP = {"requested": False}


@contextmanager
def _stop_between_steps(announce: bool = True) -> Iterator[None]:
    """Ctrl-C and SIGTERM ask the loop to stop after the current step instead of interrupting it: a step cut
    in the middle has already moved BatchNorm's running statistics (or some of the weights), and a checkpoint
    of that would not resume to an uninterrupted run's weights. A second signal stops at once, unsaved."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if _STOP["requested"]:
            raise KeyboardInterrupt(f"signal {signum}")
        _STOP["requested"] = True
        if announce:
            print("stopping after this step (press Ctrl-C again to stop at once, unsaved)", file=sys.stderr, flush=True)

    _STOP["requested"] = False
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        _STOP["requested"] = False


def _check_stop() -> None:
    if _STOP["requested"]:
        raise _StopRequested


def _train_epoch(
    model: Any, loader: Any, optimizer: torch.optim.Optimizer, scaler: torch.amp.GradScaler, norm: Norm,
    kind: str | None, uses_command: bool, cfg: TrainConfig, runtime: Runtime, pos: Position, writer: Any,
    bar: Any, started: float, keep: Callable[[int], None] | None = None, d: Dist | None = None,
    sizes: Sequence[int] | None = None,
) -> str | None:  # fmt: skip
    """Run the rest of the current epoch; return the name of the budget that stopped it, or None.

    Under torchrun (`d`; `sizes` the global batch sizes) the ranks agree after each step on the loss of the
    global batch, a stop request and the time budget, so that every rank stops after the same step."""
    tick = time.perf_counter()
    for i, raw in enumerate(_iterate(loader) if d is None else distributed.agreed(_iterate(loader), d, _DataError)):
        if cfg.max_steps is not None and pos.step >= cfg.max_steps:
            return "max_steps"
        b = prepare_batch(raw, norm, kind, uses_command, runtime)
        gen = step_generator(cfg.seed, pos.step, runtime.device, None if d is None else d.rank)
        b.image = augment_batch(b.image, cfg.augment, gen, inplace=True)
        if cfg.speed_dropout > 0.0:
            b.speed = drop_speed(b.speed, cfg.speed_dropout, gen)
        with runtime.autocast():
            loss, _, _ = compute_loss(model, b, cfg, norm)
        size = b.image.shape[0]
        weighted = loss
        if d is not None and sizes is not None and size * d.world != sizes[i]:
            # a short last batch split unevenly: DDP's mean over the ranks must be the mean over its samples
            weighted = loss * (size * d.world / sizes[i])
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(weighted).backward()
        scaler.step(optimizer)
        scaler.update()
        value = float(loss.detach())
        stop_all = over_all = False
        if d is not None:
            over = cfg.max_minutes is not None and (time.monotonic() - started) / 60.0 >= cfg.max_minutes
            total, n, stops, overs = distributed.sum_across([value * size, size, _STOP["requested"], over], d)
            value, size, stop_all, over_all = total / n, int(n), stops > 0, overs > 0
        if not math.isfinite(value):
            raise FloatingPointError(f"training loss became {value} at step {pos.step} (epoch {pos.epoch + 1})")
        now = time.perf_counter()
        pos.seconds += now - tick
        tick = now
        pos.step += 1
        pos.batch += 1
        pos.loss_sum += value * size
        pos.samples += size
        if keep is not None:
            keep(pos.step)
        bar.update(1)
        bar.set_postfix(loss=f"{value:.4f}", sps=f"{pos.samples / max(pos.seconds, 1e-9):.0f}")
        if pos.step % cfg.log_every == 0:
            writer.add_scalar("train/loss", value, pos.step)
            writer.add_scalar("train/lr", optimizer.param_groups[0]["lr"], pos.step)
        if d is not None:
            if over_all:
                return "max_minutes"
            if stop_all:
                raise _StopRequested
            continue
        if cfg.max_minutes is not None and (time.monotonic() - started) / 60.0 >= cfg.max_minutes:
            return "max_minutes"
        _check_stop()
    return None


class _DataError(Exception):
    """A batch could not be read (a corrupt or vanished episode file); raised before its step began."""


def _iterate(loader: Any) -> Iterator[Any]:
    it = iter(loader)
    while True:
        try:
            raw = next(it)
        except StopIteration:
            return
        except (OSError, ValueError) as err:  # h5py's checksum or decode errors, a file gone
            raise _DataError(str(err).strip().splitlines()[-1]) from err
        yield raw


def link_or_copy(src: Path, dst: Path) -> None:
    """Make `dst` the same file as `src` atomically: a hard link (no copy; a later replace of `src` by
    rename leaves `dst` intact), or a copy where links are not supported."""
    import shutil

    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def write_metrics(out: Path, metrics: Sequence[Mapping[str, float]]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(METRIC_FIELDS), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for row in metrics:
        w.writerow({k: f"{row.get(k, math.nan):.6g}" for k in METRIC_FIELDS})  # older rows lack newer columns
    write_atomic(out / "metrics.csv", buf.getvalue())


def plot_losses(out: Path, metrics: Sequence[Mapping[str, float]]) -> None:
    """loss.png: train and validation loss per epoch (log scale), written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    x = [m["epoch"] for m in metrics]
    ax.plot(x, [m["train_loss"] for m in metrics], marker="o", label="train")
    ax.plot(x, [m["val_loss"] for m in metrics], marker="o", label="validation")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    if metrics and min(min(m["train_loss"], m["val_loss"]) for m in metrics) > 0:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    write_atomic(out / "loss.png", buf.getvalue())
