"""Speed of the training step, the batch augmentation and the agent's act() on this machine.

    .venv/bin/python benchmarks/agent.py [--models yilratt cil] [--threads 2] [--quick]

Prints three markdown tables (docs/performance.md, "Training and agent"):
- agent: median latency of a full `Agent.act(obs)` at batch 1 (guidance computation, preprocessing,
  forward under torch.inference_mode, post-processing) per model and numeric mode;
- augmentation: time per batch of `augment_batch` (all five operations on);
- training: samples/s of one optimiser step (forward, loss, backward, Adam) per numeric mode.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from yawil import models  # noqa: E402
from yawil.agent import Agent  # noqa: E402
from yawil.learn.augment import AugmentConfig, augment_batch  # noqa: E402
from yawil.learn.config import TrainConfig  # noqa: E402
from yawil.learn.loss import compute_loss  # noqa: E402
from yawil.learn.sampling import Batch  # noqa: E402
from yawil.policy.checkpoint import Norm, make_checkpoint, save_checkpoint  # noqa: E402
from yawil.policy.runtime import Runtime  # noqa: E402
from yawil.sim.types import Observation, Pose, RoadOption, Route  # noqa: E402

MODES = {"fp32": ("fp32", "off"), "fp32+cl": ("fp32", "on"), "bf16+cl": ("bf16", "on")}


def observation() -> Observation:
    xy = np.stack([np.arange(0.0, 200.0), np.zeros(200)], axis=1)
    route = Route(xy=xy, options=np.full(200, int(RoadOption.LANEFOLLOW), np.int8), lane_yaw=np.zeros(200))
    image = np.random.default_rng(0).integers(0, 256, (88, 200, 3), dtype=np.uint8)
    return Observation(
        image=image, speed=4.0, pose=Pose(20.0, 0.2, 0.0), route=route, route_index=20,
        command=RoadOption.LANEFOLLOW, events=(), time=0.0, frame=0, done=False, distance_driven=0.0,
        town="town01", bounds=(-10.0, -10.0, 210.0, 10.0), weather="ClearNoon",
    )  # fmt: skip


def median_ms(fn: object, repeats: int, warmup: int = 3) -> float:
    times = []
    for i in range(warmup + repeats):
        t = time.perf_counter()
        fn()  # type: ignore[operator]
        if i >= warmup:
            times.append(time.perf_counter() - t)
    return 1000.0 * statistics.median(times)


def bench_agent(names: list[str], repeats: int, folder: Path) -> None:
    print("\n| model | " + " | ".join(f"act() {m} (ms)" for m in MODES) + " |")
    print("|---|" + "---:|" * len(MODES))
    obs = observation()
    for name in names:
        model = models.create(name, seed=0)
        dim = model.guidance_dim if model.guidance else 0
        path = folder / f"{name}.pt"
        gc = {"spacing": 2.0, "count": dim // 2 if model.guidance == "xy" else max(dim, 1), "reference": "route"}
        save_checkpoint(make_checkpoint(model, Norm(3.0, 2.0, (0.0,) * dim, (1.0,) * dim), gc), path)
        row = []
        for precision, cl in MODES.values():
            agent = Agent.from_checkpoint(path, precision=precision, channels_last=cl)
            agent.reset()
            row.append(f"{median_ms(lambda a=agent: a.act(obs), repeats):.1f}")
        print(f"| {name} | " + " | ".join(row) + " |", flush=True)


def bench_augment(repeats: int) -> None:
    print("\n| augmentation batch | ms per batch | ms per 100 images |")
    print("|---|---:|---:|")
    cfg = AugmentConfig(brightness_p=1.0, contrast_p=1.0, blur_p=1.0, noise_p=1.0, dropout_p=1.0)
    for b in (64, 512):
        images = torch.rand(b, 3, 88, 200)
        gen = torch.Generator().manual_seed(0)
        ms = median_ms(lambda i=images, g=gen: augment_batch(i, cfg, g), repeats)
        print(f"| {b} x 3 x 88 x 200, all ops | {ms:.1f} | {100 * ms / b:.1f} |", flush=True)


def bench_train(names: list[str], batch: int, repeats: int) -> None:
    print(f"\n| model (batch {batch}) | " + " | ".join(f"train {m} (samples/s)" for m in MODES) + " |")
    print("|---|" + "---:|" * len(MODES))
    cfg = TrainConfig()
    for name in names:
        row = []
        for precision, cl in MODES.values():
            rt = Runtime(torch.device("cpu"), precision, cl == "on")
            model = models.create(name, seed=0).train()
            if rt.channels_last:
                model.to(memory_format=torch.channels_last)  # type: ignore[call-arg]
            opt = torch.optim.Adam(model.parameters(), lr=1e-3, foreach=True)
            image = torch.rand(batch, 3, 88, 200)
            if rt.channels_last:
                image = image.contiguous(memory_format=torch.channels_last)
            g = torch.zeros(batch, model.guidance_dim) if model.guidance else None
            c = torch.zeros(batch, dtype=torch.int64) if model.uses_command else None
            b = Batch(image, torch.zeros(batch, 1), g, c, torch.zeros(batch, 3), torch.zeros(batch, 1))

            def step(model: torch.nn.Module = model, opt: torch.optim.Optimizer = opt, b: Batch = b, rt: Runtime = rt) -> None:
                with rt.autocast():
                    loss, _, _ = compute_loss(model, b, cfg)
                opt.zero_grad()
                loss.backward()
                opt.step()

            ms = median_ms(step, repeats, warmup=1)
            row.append(f"{1000.0 * batch / ms:.0f}")
        print(f"| {name} | " + " | ".join(row) + " |", flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["yilratt", "cilrs", "cil", "yaw-guided"])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--train-models", nargs="+", default=["yilratt", "cil"])
    p.add_argument("--batch", type=int, default=64, help="training batch for the samples/s figure")
    p.add_argument("--quick", action="store_true", help="fewer repeats")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    print(f"torch {torch.__version__}, {args.threads} threads, {torch.backends.cpu.get_cpu_capability()}, load {load:.1f}")
    r = 5 if args.quick else 30
    with tempfile.TemporaryDirectory() as d:
        bench_agent(args.models, r, Path(d))
    bench_augment(3 if args.quick else 10)
    bench_train(args.train_models, args.batch, 2 if args.quick else 3)
    print(f"load average at the end: {os.getloadavg()[0]:.1f} (figures are only meaningful near 0)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
