"""Speed of every registered model on this machine: inference latency and training throughput.

For each model (default config, 88 x 200 input) it prints
- batch-1 inference latency in ms (median of --runs), fp32 and bf16 autocast + channels_last;
- training samples/s at --batch (forward + backward + Adam step, after --warmup steps, median of --steps);
- the bf16/fp32 speed ratio of both;
then YILRatt's training samples/s at batch 128 with bf16 + channels_last (the training target is >= 40),
by default (layer4 skipped) and with `compute_global=True` (layer4 run as the paper writes it), and their ratio.

    .venv/bin/python benchmarks/models.py [--models yilratt,cil] [--batch 64] [--steps 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import torch
import torch.nn.functional as F

from yawil.models import DrivingModel, create, list_models


def make_inputs(model: DrivingModel, batch: int, channels_last: bool, seed: int = 0) -> dict[str, Any]:
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, 88, 200, generator=g)
    if channels_last:
        image = image.contiguous(memory_format=torch.channels_last)
    return {
        "image": image,
        "speed": torch.rand(batch, 1, generator=g),
        "guidance": torch.rand(batch, model.guidance_dim, generator=g) if model.guidance else None,
        "command": torch.randint(0, 4, (batch,), generator=g) if model.uses_command else None,
    }


def precision(bf16: bool) -> AbstractContextManager[Any]:
    return torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else nullcontext()


def build(name: str, bf16: bool, **cfg: Any) -> DrivingModel:
    model = create(name, seed=0, **cfg)
    if bf16:
        model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    return model


def latency_ms(name: str, bf16: bool, runs: int, warmup: int) -> float:
    """Median batch-1 forward time in eval mode."""
    model = build(name, bf16).eval()
    x = make_inputs(model, 1, bf16)
    times = []
    with torch.inference_mode(), precision(bf16):
        for i in range(warmup + runs):
            t0 = time.perf_counter()
            model(**x)
            if i >= warmup:
                times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def train_samples_per_s(name: str, bf16: bool, batch: int, steps: int, warmup: int,
                        **cfg: Any) -> tuple[float, float]:
    """Samples per second of full training steps (the trainer's loss: actions + 0.1 * speed).

    Returns (wall, idle estimate). Uses the median step time: on a shared machine a burst from another
    process then spoils one step, not the figure. The idle estimate divides the process's CPU time by the
    thread count: what the step would take with the cores to itself (an upper bound on throughput).
    """
    model = build(name, bf16, **cfg).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    x = make_inputs(model, batch, bf16)
    g = torch.Generator().manual_seed(1)
    target = torch.rand(batch, 3, generator=g)
    target_speed = torch.rand(batch, 1, generator=g)
    times, cpu = [], []
    for i in range(warmup + steps):
        t0, c0 = time.perf_counter(), time.process_time()
        with precision(bf16):
            out = model(**x)
            loss = F.l1_loss(out.actions.float(), target) + 0.1 * F.l1_loss(out.speed.float(), target_speed)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    return batch / statistics.median(times), batch * torch.get_num_threads() / statistics.median(cpu)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default=",".join(list_models()), help="comma-separated names (default: all)")
    p.add_argument("--batch", type=int, default=64, help="training batch size")
    p.add_argument("--steps", type=int, default=5, help="timed training steps")
    p.add_argument("--warmup", type=int, default=2, help="untimed warm-up steps / forwards")
    p.add_argument("--runs", type=int, default=30, help="timed batch-1 forwards (median)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--big-batch", type=int, default=128, help="YILRatt bf16 training batch (0 to skip)")
    args = p.parse_args()
    names = [n.strip() for n in args.models.split(",") if n.strip()]
    unknown = [n for n in names if n not in list_models()]
    if unknown:
        p.error(f"--models: unknown {unknown}; known: {list_models()}")
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}; input 3x88x200; train batch {args.batch}, {args.steps} steps")
    print()
    print("| model | latency fp32 (ms) | latency bf16+CL (ms) | ratio | train fp32 (samples/s) "
          "| train bf16+CL (samples/s) | ratio | idle est. fp32 | idle est. bf16+CL |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name in names:
        lat = [latency_ms(name, bf16, args.runs, args.warmup) for bf16 in (False, True)]
        (thr32, est32), (thr16, est16) = (
            train_samples_per_s(name, bf16, args.batch, args.steps, args.warmup) for bf16 in (False, True)
        )
        print(f"| {name} | {lat[0]:.1f} | {lat[1]:.1f} | {lat[0] / lat[1]:.2f}x | {thr32:.1f} | {thr16:.1f} "
              f"| {thr16 / thr32:.2f}x | {est32:.1f} | {est16:.1f} |", flush=True)
    if args.big_batch:
        print()
        runs = {}
        for glob in (False, True):  # interleaved pairs: a load burst then spoils both sides alike
            runs[glob] = train_samples_per_s("yilratt", True, args.big_batch, args.steps, args.warmup,
                                             compute_global=glob)
        (sps, est), (sps4, est4) = runs[False], runs[True]
        print(f"yilratt training, batch {args.big_batch}, bf16 autocast + channels_last: {sps:.1f} samples/s wall, "
              f"{est:.1f} idle estimate (target >= 40); load average {os.getloadavg()[0]:.2f}")
        print(f"  with layer4 run (compute_global=True): {sps4:.1f} samples/s wall, {est4:.1f} idle estimate; "
              f"skipping it: {sps / sps4:.2f}x wall, {est / est4:.2f}x idle estimate")

if __name__ == "__main__":
    main()
