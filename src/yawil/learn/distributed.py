"""Training on several processes or GPUs under `torchrun` (DistributedDataParallel); docs/training.md.

    torchrun --nproc_per_node 2 -m yawil.cli train --data data/town01 --out runs/x --batch-size 512

`yawil.learn.loop` calls `start` when WORLD_SIZE > 1 in the environment (torchrun sets it, with RANK, LOCAL_RANK,
MASTER_ADDR and MASTER_PORT) and runs today's single-process code otherwise. Under torchrun every rank
builds the same epoch order and takes its slice of each global batch (`rank_batches`); BatchNorm layers
become SyncBatchNorm (`sync_batchnorm`), so that W ranks with B / W samples each compute what one process
with B computes: the same batch statistics, and DDP's mean of the ranks' gradients is the gradient of the
mean loss over the global batch. Ranks agree after every step on the loss, a stop request and the time
budget (`sum_across`), so they all stop at the same step.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, TypeVar, cast

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.modules.batchnorm import _BatchNorm

T = TypeVar("T")
BACKENDS = ("gloo", "nccl")
# How long a rank waits for the others at a collective. Rank 0 validates and saves while the others wait at
# the next step; a dead rank is noticed by torchrun, which stops the others, long before this.
TIMEOUT = timedelta(minutes=60)


class WorldSizeError(ValueError):
    """A setting that does not fit the world size; every rank raises it alike, rank 0 reports it."""


@dataclass(frozen=True)
class Dist:
    """This process's place in the run."""

    rank: int
    world: int
    local_rank: int
    local_world: int
    backend: str
    owns_group: bool  # init_process_group was called here (and destroy_process_group is, at the end)

    @property
    def main(self) -> bool:
        return self.rank == 0


def world_from_env() -> tuple[int, int, int, int] | None:
    """(rank, world size, local rank, local world size) when launched by torchrun with WORLD_SIZE > 1, else None."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1:
        return None
    rank = int(os.environ["RANK"])
    local_rank = int(os.environ.get("LOCAL_RANK", rank))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", world))
    return rank, world, local_rank, local_world


def check_batch_size(batch_size: int, world: int) -> None:
    if batch_size % world:
        raise WorldSizeError(
            f"--batch-size {batch_size} is not divisible by the world size {world}: each rank takes "
            f"batch_size / world_size samples of every global batch; use a multiple of {world}"
        )


def start(device_type: str, backend: str | None = None) -> Dist:
    """Join (or, when the caller has not, initialise) the process group of this torchrun job."""
    found = world_from_env()
    if found is None:
        raise ValueError("yawil.learn.distributed.start: WORLD_SIZE is not > 1 in the environment (not under torchrun)")
    rank, world, local_rank, local_world = found
    if device_type == "cuda":
        if local_rank >= torch.cuda.device_count():
            raise ValueError(f"local rank {local_rank} but torch sees {torch.cuda.device_count()} CUDA device(s): "
                             "give torchrun --nproc_per_node at most the number of GPUs")
        torch.cuda.set_device(local_rank)
    if dist.is_initialized():
        return Dist(rank, world, local_rank, local_world, str(dist.get_backend()), owns_group=False)
    backend = backend or ("nccl" if device_type == "cuda" else "gloo")
    if backend not in BACKENDS:
        raise ValueError(f"--dist-backend {backend!r}: expected one of {BACKENDS}")
    if backend == "nccl" and device_type != "cuda":
        raise ValueError("--dist-backend nccl needs --device cuda (gloo is the CPU backend)")
    kwargs: dict[str, Any] = {"device_id": torch.device("cuda", local_rank)} if backend == "nccl" else {}
    dist.init_process_group(backend, rank=rank, world_size=world, timeout=TIMEOUT, **kwargs)
    return Dist(rank, world, local_rank, local_world, backend, owns_group=True)


def stop(d: Dist) -> None:
    if d.owns_group and dist.is_initialized():
        dist.destroy_process_group()


def auto_threads(d: Dist, workers: int) -> int:
    """Torch threads of one rank: its share of the machine's cores, less its loader workers."""
    return max(1, (os.cpu_count() or 1) // max(1, d.local_world) - workers)


def rank_seed(seed: int, rank: int) -> int:
    """The seed of a rank's global generators (dropout): `seed` on rank 0, one drawn from (seed, rank) elsewhere."""
    return seed if rank == 0 else int(np.random.SeedSequence([seed, rank]).generate_state(1)[0])


# ------------------------------------------------------------------------------------------------- data
def shard(batch: Sequence[int], rank: int, world: int) -> list[int]:
    """This rank's contiguous slice of a global batch: B / W samples, or sizes that differ by one when W does
    not divide a short last batch (the earlier ranks take one more)."""
    q, r = divmod(len(batch), world)
    begin = rank * q + min(rank, r)
    return list(batch[begin : begin + q + (rank < r)])


def rank_batches(batches: Sequence[Sequence[int]], d: Dist) -> tuple[list[list[int]], list[int]]:
    """(this rank's slices, the global batch sizes) of an epoch's batches."""
    return [shard(b, d.rank, d.world) for b in batches], [len(b) for b in batches]


def usable_batches(batches: list[list[int]], world: int) -> list[list[int]]:
    """The epoch's batches that every rank has a sample of: a last batch smaller than the world is left out."""
    return [b for b in batches if len(b) >= world]


# ----------------------------------------------------------------------------------------- agreement
def _device(d: Dist) -> torch.device:
    return torch.device("cuda", d.local_rank) if d.backend == "nccl" else torch.device("cpu")


def sum_across(values: Sequence[float], d: Dist) -> list[float]:
    """Element-wise sums over the ranks (float64): the loss of the global batch, stop and budget flags."""
    t = torch.tensor(list(values), dtype=torch.float64, device=_device(d))
    dist.all_reduce(t)
    return t.cpu().tolist()


def gather_objects(obj: Any, d: Dist) -> list[Any]:
    """Every rank's `obj`, in rank order, on every rank."""
    out: list[Any] = [None] * d.world
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(obj: Any, d: Dist) -> Any:
    """Rank 0's `obj` on every rank."""
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def agreed(items: Iterator[T], d: Dist, error: type[Exception]) -> Iterator[T]:
    """`items` on every rank, each one given only when every rank has its own: an `error` on one rank (a
    batch that cannot be read) is raised on all, naming the rank, instead of leaving the others waiting in the
    step's collectives. Every rank must have as many items."""
    while True:
        item: Any = None
        failed: str | None = None
        try:
            item = next(items)
        except StopIteration:
            return
        except error as err:
            failed = f"rank {d.rank}: {err}"
        if sum_across([failed is not None], d)[0] > 0:
            raise error("; ".join(m for m in gather_objects(failed, d) if m))
        yield item


class NoWriter:
    """The TensorBoard writer of the ranks other than 0: writes nothing."""

    def add_scalar(self, *args: Any, **kwargs: Any) -> None:
        pass

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def barrier(d: Dist) -> None:
    if d.backend == "nccl":
        dist.barrier(device_ids=[d.local_rank])
    else:
        dist.barrier()


# ------------------------------------------------------------------------------------------------ model
class _SumAcross(torch.autograd.Function):
    """all_reduce(SUM) with its gradient: the sum over the ranks of the gradients of the summed tensor."""

    @staticmethod
    def forward(ctx: Any, tensor: torch.Tensor, group: Any) -> torch.Tensor:
        ctx.group = group
        out = tensor.clone()
        dist.all_reduce(out, group=group)
        return out

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        grad = grad.clone()
        dist.all_reduce(grad, group=ctx.group)
        return grad, None


class CpuSyncBatchNorm(_BatchNorm):
    """torch.nn.SyncBatchNorm for the CPU (torch's, and DDP, refuse it there): in training, each rank's count,
    sum and sum of squared deviations are summed over the ranks with their gradient (`_SumAcross`), and the
    global mean and variance combined in float64, so that both the normalisation and its gradient are those of
    BatchNorm over the global batch (as torch's CUDA kernels do). In eval mode it is BatchNorm."""

    process_group: Any = None

    def _check_input_dim(self, input: torch.Tensor) -> None:
        if input.dim() < 2:
            raise ValueError(f"expected at least 2D input (got {input.dim()}D input)")

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_initialized()):
            return super().forward(input)
        self._check_input_dim(input)
        factor = 0.0 if self.momentum is None else self.momentum
        if self.track_running_stats and self.num_batches_tracked is not None:
            self.num_batches_tracked.add_(1)
            if self.momentum is None:
                factor = 1.0 / float(self.num_batches_tracked.item())
        c = input.shape[1]
        dims = [i for i in range(input.dim()) if i != 1]
        x = input.float()
        n = float(input.numel() // max(1, c))
        mean_r = x.mean(dims)
        m2_r = ((x - mean_r.view(1, c, *[1] * (x.dim() - 2))) ** 2).sum(dims)
        mean_d = mean_r.double()
        local = torch.cat([n * mean_d, m2_r.double() + n * mean_d * mean_d,
                           torch.tensor([n], dtype=torch.float64)])  # fmt: skip
        total = _SumAcross.apply(local, self.process_group or dist.group.WORLD)
        count = total[2 * c]
        mean = total[:c] / count
        var = (total[c : 2 * c] / count - mean * mean).clamp_min(0.0)
        if self.track_running_stats and self.running_mean is not None and self.running_var is not None:
            with torch.no_grad():
                unbiased = var * count / (count - 1).clamp_min(1.0)
                self.running_mean.mul_(1.0 - factor).add_(mean.to(self.running_mean.dtype), alpha=factor)
                self.running_var.mul_(1.0 - factor).add_(unbiased.to(self.running_var.dtype), alpha=factor)
        shape = (1, c, *[1] * (x.dim() - 2))
        y = (x - mean.float().view(shape)) * torch.rsqrt(var.float() + self.eps).view(shape)
        if self.weight is not None and self.bias is not None:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        return y.to(input.dtype)


def sync_batchnorm(model: torch.nn.Module, device_type: str) -> torch.nn.Module:
    """BatchNorm layers to SyncBatchNorm (`torch.nn.SyncBatchNorm.convert_sync_batchnorm`; on the CPU the
    converted layers become `CpuSyncBatchNorm`, same state). State-dict keys are unchanged."""
    model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
    if device_type == "cpu":
        for m in model.modules():
            if type(m) is torch.nn.SyncBatchNorm:
                cast(Any, m).__class__ = CpuSyncBatchNorm
    return model


class DDP(torch.nn.parallel.DistributedDataParallel):
    """DistributedDataParallel that also answers the wrapped model's attributes (`uses_command`, `name`), so
    that the loss code takes either."""

    def __getattr__(self, name: str) -> Any:
        try:
            return super().__getattr__(name)
        except AttributeError:
            if name == "module":
                raise
            return getattr(self.module, name)


def wrap(model: torch.nn.Module, d: Dist, device: torch.device) -> DDP:
    """The model for the training steps. The graph is the same every step (a branched model computes every
    branch; an aux head unused by the loss stays unused), hence static_graph, which also allows parameters
    without a gradient. (DDP also broadcasts rank 0's buffers before each step; SyncBatchNorm keeps the
    running statistics equal on every rank anyway.)"""
    ids = [device.index if device.index is not None else d.local_rank] if device.type == "cuda" else None
    return DDP(model, device_ids=ids, static_graph=True)
