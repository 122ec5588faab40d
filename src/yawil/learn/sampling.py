"""What one training step sees: the order of an epoch's samples (a permutation, or weighted draws for
`brake_fraction` / `oversample`), the step's own random generator, and the `Batch` of tensors made through
the model-input contract (`yawil.policy.inputs`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from yawil.policy.checkpoint import Norm
from yawil.policy.inputs import InputSpec, guidance_key
from yawil.policy.runtime import Runtime


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
    privileged: Tensor | None = None  # [B, 5] m/s, m, m/s, 0/1, reason (NaN / -1 unknown): aux-head targets


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
