"""Training data held on the training device (`--data-on-device`).

Why: on a GPU a ResNet34 step at batch 512 is faster than reading, decoding and copying its 512 frames from
the host, so the loader, not the GPU, would set the pace. Here each split is read once into tensors on the
device (images uint8 [N, 3, H, W], the labels the steps read) and every batch is drawn by indexing on the
device, in the seeded order of `yawil.learn.sampling` (the epoch's order goes to the device once per epoch).
The samples are read through the dataset's own `__getitem__` and the DataLoader's collate, in order, so a
batch drawn here equals the loader's batch of the same indices, value, dtype and shape (tested); the steps
then prepare and augment it on the device exactly as they do a loader's batch.

Memory: 200k frames of 3x88x200 uint8 are 10.6 GB; on CUDA a split that would take more than
`MEMORY_SHARE` of the free memory is refused in one line. On the CPU there is no check (it is host memory).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence
from typing import Any

import torch
from torch import Tensor

from yawil.learn.config import TrainConfig
from yawil.learn.sampling import sequential_batches
from yawil.learn.setup import make_loader
from yawil.policy.inputs import guidance_key
from yawil.policy.runtime import Runtime

KEEP = ("image", "speed", "action", "command", "privileged")  # with guidance_<kind>: what prepare_batch reads
MEMORY_SHARE = 0.8  # of the device's free memory; the rest is left to the model, the optimiser and activations
LOAD_BATCH = 1024  # samples read and copied to the device at a time while loading


def kept_keys(kind: str | None) -> tuple[str, ...]:
    """The sample fields held on the device: those a training or validation step reads, no others."""
    return KEEP if kind is None else (*KEEP, guidance_key(kind))


def sample_bytes(dataset: Any, keys: Sequence[str]) -> int:
    """Bytes one sample of `dataset` takes on the device (image and labels), from its first sample."""
    from torch.utils.data import default_collate

    one = default_collate([dataset[0]])
    return sum(one[k].numel() * one[k].element_size() for k in keys if k in one)


def check_fits(need: int, device: torch.device, free: int | None = None) -> None:
    """Refuse (ValueError, one line) when `need` bytes would not fit in MEMORY_SHARE of the device's free memory.
    `free` defaults to what torch.cuda.mem_get_info reports; on the CPU nothing is checked."""
    if free is None:
        if device.type != "cuda":
            return
        free = int(torch.cuda.mem_get_info(device)[0])
    if need > MEMORY_SHARE * free:
        raise ValueError(
            f"--data-on-device: the training and validation splits need {need / 1e9:.1f} GB on {device}, but "
            f"{free / 1e9:.1f} GB are free (at most {MEMORY_SHARE:.0%} of it is given to data); train without "
            "--data-on-device, or on fewer frames"
        )


class ResidentData:
    """One split as tensors on the device, indexed along their first dimension."""

    def __init__(self, tensors: dict[str, Tensor]) -> None:
        sizes = {t.shape[0] for t in tensors.values()}
        if len(sizes) != 1:
            raise ValueError(f"resident data: fields differ in length ({sorted(sizes)})")
        self.tensors = tensors
        self.n = sizes.pop()

    def __len__(self) -> int:
        return self.n

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.tensors.values())

    @classmethod
    def load(cls, dataset: Any, keys: Sequence[str], cfg: TrainConfig, runtime: Runtime) -> ResidentData:
        """Read every sample of `dataset` in order (through a DataLoader with `cfg.workers` workers) into tensors
        on `runtime.device`, allocated once at their final size."""
        n = len(dataset)
        dev = runtime.device
        tensors: dict[str, Tensor] = {}
        for rows, raw in zip(sequential_batches(n, LOAD_BATCH), make_loader(dataset, sequential_batches(n, LOAD_BATCH),
                                                                           cfg, runtime), strict=True):
            for key in keys:
                if key not in raw:
                    continue
                part = torch.as_tensor(raw[key])
                if key not in tensors:
                    tensors[key] = torch.empty((n, *part.shape[1:]), dtype=part.dtype, device=dev)
                tensors[key][rows[0] : rows[-1] + 1].copy_(part, non_blocking=True)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        return cls(tensors)

    def batch(self, index: Tensor) -> dict[str, Tensor]:
        """The samples at `index` (an int64 tensor on the device), as the loader's collated batch."""
        return {k: t.index_select(0, index) for k, t in self.tensors.items()}

    def batches(self, batches: Sequence[Sequence[int]]) -> DeviceBatches:
        """An iterable of the batches `batches` names (re-iterable: validation runs it once per epoch)."""
        return DeviceBatches(self, batches)


class DeviceBatches:
    """Batches of a ResidentData in a given order; the order is copied to the device once, then sliced."""

    def __init__(self, data: ResidentData, batches: Sequence[Sequence[int]]) -> None:
        self.data = data
        self.sizes = [len(b) for b in batches]
        flat = [i for b in batches for i in b]
        device = next(iter(data.tensors.values())).device
        self.order = torch.as_tensor(flat, dtype=torch.int64).to(device)

    def __len__(self) -> int:
        return len(self.sizes)

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        start = 0
        for size in self.sizes:
            yield self.data.batch(self.order[start : start + size])
            start += size


def load_splits(
    train_ds: Any, val_ds: Any, kind: str | None, cfg: TrainConfig, runtime: Runtime, announce: bool
) -> tuple[ResidentData, ResidentData | None]:
    """Both splits on the device (validation too: its batches then cost no host reads either), after checking
    that they fit."""
    keys = kept_keys(kind)
    per_sample = sample_bytes(train_ds, keys)
    n = len(train_ds) + len(val_ds)
    check_fits(n * per_sample, runtime.device)
    if announce:
        print(f"holding {n:,} frames on {runtime.device} ({n * per_sample / 1e9:.2f} GB: --data-on-device)",
              file=sys.stderr)
    train = ResidentData.load(train_ds, keys, cfg, runtime)
    val = ResidentData.load(val_ds, keys, cfg, runtime) if len(val_ds) else None
    return train, val
