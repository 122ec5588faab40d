"""Training under torchrun, on 2 CPU processes (gloo): with global batch B they give the weights of one process
with batch B (SyncBatchNorm, DDP's gradient mean, an uneven last batch weighted), and a distributed run stopped
by SIGTERM on one rank and resumed gives the weights of one not stopped, bit for bit.

Adam's eps is raised from 1e-8 to 1e-4 here (`Adam4`): with 1e-8, Adam moves a weight whose gradient float
rounding leaves at ~1e-9 by a whole +-lr, so two summation orders of one gradient (1 process or 2) part by
2 lr on a few weights from the first step, and the differences grow over the steps (ReLU kinks, L1's sign).
With eps 1e-4 the updates follow the gradients, which agree to ~2e-6, and the weights to 1e-5 of their scale.

oneDNN is switched off in every process here (ATen's own convolutions): on an Intel Xeon with AMX its kernels
left the updates of the uneven batch (3 as 2 + 1, or 5 as 3 + 2) 3e-4 to 4e-4 apart, while the even batch stayed
at 1e-6; with ATen's kernels both agree to 5e-7 there (measured 2026-12-05). The test checks the arithmetic of
data parallelism, not which kernel a CPU picks for a batch size.
"""

from __future__ import annotations

import os
import signal
import socket
import time
from pathlib import Path
from typing import Any

import pytest
import torch
import torch.multiprocessing as mp

from yawil import models
from yawil.learn.config import TrainConfig
from yawil.learn.distributed import WorldSizeError, shard
from yawil.learn.loop import train
from yawil.policy.checkpoint import load_checkpoint

K = 4
B = 8  # global batch: 4 per rank


class Adam4(torch.optim.Adam):
    def __init__(self, params: Any, **kwargs: Any) -> None:
        super().__init__(params, **{**kwargs, "eps": 1e-4})


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 episodes of 11 synthetic frames: 1 to train (an epoch is 2 batches: 8, split 4 / 4, then 3, split 2 / 1)
    and 1 to validate."""
    from yawil.data import write_synthetic_dataset

    root = tmp_path_factory.mktemp("ddp") / "data"
    write_synthetic_dataset(root, episodes=2, frames=11, k=K, seed=0)
    return root


def config(data: Path, out: Path, augment: bool, epochs: int) -> TrainConfig:
    """CIL (BatchNorm in every conv block) in fp32 NCHW: on this CPU oneDNN's channels_last convolutions give
    gradients 0.5 % away from NCHW's, for 1 process as for 2."""
    return TrainConfig(
        model="cil", data=[str(data)], out=str(out), epochs=epochs, batch_size=B, val_fraction=0.5, progress=False,
        precision="fp32", channels_last="off", threads=1, model_args={"dropout": 0.0}, keep_steps=[1],
        augment={"enabled": augment},
    )  # fmt: skip


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def _worker(rank: int, world: int, ports: list[int], data: Path, tmp: Path) -> None:
    """One rank, as torchrun would start it; runs the phases one after the other, each a process group."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world),
                      MASTER_ADDR="127.0.0.1")  # fmt: skip
    import yawil.learn.loop as train_module

    torch.optim.Adam = Adam4  # type: ignore[misc]
    torch.backends.mkldnn.enabled = False  # a flag of this process (module docstring)
    os.environ["MASTER_PORT"] = str(ports[0])
    train(config(data, tmp / "ddp", augment=False, epochs=1))
    os.environ["MASTER_PORT"] = str(ports[1])
    train(config(data, tmp / "aug", augment=True, epochs=2))

    real = train_module.prepare_batch
    calls = {"n": 0}

    def sigterm_on_third_batch(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*args, **kwargs)

    if rank == 1:  # one rank only is told to stop: both must stop after the same step
        train_module.prepare_batch = sigterm_on_third_batch  # type: ignore[assignment]
    os.environ["MASTER_PORT"] = str(ports[2])
    try:
        train(config(data, tmp / "stop", augment=True, epochs=2))  # stops after step 3 (of 4)
    except KeyboardInterrupt:
        pass
    else:
        raise AssertionError(f"rank {rank}: the run was not stopped")
    train_module.prepare_batch = real  # type: ignore[assignment]
    os.environ["MASTER_PORT"] = str(ports[3])
    train(config(data, tmp / "stop", augment=True, epochs=2), resume=True)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["state_dict"]


def num_batches(ckpt: dict[str, Any]) -> list[int]:
    return [int(v) for k, v in ckpt["state_dict"].items() if k.endswith("num_batches_tracked")]


def test_two_processes_equal_one_and_resume_across_them(data: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(torch.optim, "Adam", Adam4)
    monkeypatch.setattr(torch.backends.mkldnn, "enabled", False)  # undone after the test, as Adam is
    started = time.monotonic()
    ctx = mp.start_processes(_worker, args=(2, _free_ports(4), data, tmp_path), nprocs=2, join=False,
                             start_method="spawn")  # fmt: skip
    single = train(config(data, tmp_path / "single", augment=False, epochs=1))  # one process, meanwhile
    while not ctx.join(timeout=2):
        if time.monotonic() - started > 400:
            for p in ctx.processes:
                p.kill()
            pytest.fail("the 2-process training did not finish in 400 s")

    assert (single.epochs_done, single.steps) == (1, 2)
    start = models.create("cil", seed=0, dropout=0.0).state_dict()  # the weights both runs start from
    for name in ("step_000001.pt", "last.pt"):  # after the even batch, then after the uneven one
        one, two = load_checkpoint(tmp_path / "single" / name), load_checkpoint(tmp_path / "ddp" / name)
        assert two["step"] == one["step"] and len(two["rng_ranks"]) == 2
        assert any(".running_var" in k for k in one["state_dict"])  # BatchNorm's statistics are compared too
        keys = [k for k, v in one["state_dict"].items() if v.is_floating_point()]
        moved1 = torch.cat([(one["state_dict"][k] - start[k]).flatten().double() for k in keys])
        moved2 = torch.cat([(two["state_dict"][k] - start[k]).flatten().double() for k in keys])
        # what training changed, to 1e-5 relative (the weights themselves agree 100x closer)
        apart = float((moved2 - moved1).norm() / moved1.norm())
        assert apart < 1e-5, f"{name}: the updates of 2 processes and 1 differ by {apart:.2e} relative"
        assert num_batches(two) == num_batches(one)
    for row1, row2 in zip(one["metrics"], two["metrics"], strict=True):  # the loss of the global batch
        for col in ("train_loss", "val_loss"):
            assert row2[col] == pytest.approx(row1[col], rel=1e-5), col
    assert len((tmp_path / "ddp" / "metrics.csv").read_text().splitlines()) == 2  # rank 0 writes: header, 1 epoch
    assert list((tmp_path / "ddp" / "tb").iterdir())

    full, resumed = _weights(tmp_path / "aug" / "last.pt"), load_checkpoint(tmp_path / "stop" / "last.pt")
    assert resumed["step"] == 4 and [m["epoch"] for m in resumed["metrics"]] == [1.0, 1.5, 2.0]
    assert resumed["metrics"][1]["step"] == 3  # both ranks stopped after the step rank 1 was signalled in
    for key, value in full.items():
        assert torch.equal(resumed["state_dict"][key], value), key


def test_a_batch_size_the_world_size_does_not_divide_is_refused(tmp_path: Path, data: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    cfg = config(data, tmp_path / "x", augment=False, epochs=1)
    cfg.batch_size = 7
    with pytest.raises(WorldSizeError, match="--batch-size 7 is not divisible by the world size 2"):
        train(cfg)


def test_each_rank_takes_its_slice_of_the_global_batch() -> None:
    assert [shard(range(8), r, 2) for r in range(2)] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert [shard([9, 8, 7], r, 2) for r in range(2)] == [[9, 8], [7]]
    assert [shard(range(5), r, 3) for r in range(3)] == [[0, 1], [2, 3], [4]]
