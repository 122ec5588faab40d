"""Training samples/s with the DataLoader and with the dataset held on the device (`--data-on-device`).

    nice -n 19 .venv/bin/python benchmarks/train_modes.py                  # CPU: cil and yilratt, both modes
    .venv/bin/python benchmarks/train_modes.py --device cuda --models yilratt --batch-size 512 --steps 200

Writes a synthetic dataset (88x200 street-like images, `--episodes` x `--frames`) to a temporary folder, then
trains each model for `--steps` optimiser steps in each mode (alternating, `--repeat` times) and prints the
samples/s of the steps (the run's own count: step time including the wait for the batch, without validation
and, for --data-on-device, without the one load of the splits, timed apart) with the load average before and
after (another job on the machine slows every figure).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any


def measure(data: Path, out: Path, model: str, *, device: str, data_on_device: bool, steps: int, batch_size: int,
            precision: str = "auto", channels_last: str = "auto", workers: int = 0, threads: int = 0) -> dict[str, Any]:
    """Train `steps` steps; the samples/s of the steps (metrics.csv's count) and the wall time of the run."""
    from yawil.learn.config import TrainConfig
    from yawil.learn.loop import train

    cfg = TrainConfig(model=model, data=[str(data)], out=str(out), batch_size=batch_size, max_steps=steps,
                      epochs=10**6, val_fraction=0.05, device=device, precision=precision,
                      channels_last=channels_last, data_on_device=data_on_device, workers=workers, threads=threads,
                      progress=False)  # fmt: skip
    start = time.perf_counter()
    result = train(cfg)
    wall = time.perf_counter() - start
    samples = sum(r["samples_per_s"] * r["time"] for r in result.metrics)
    seconds = sum(r["time"] for r in result.metrics)
    return {"samples_per_s": samples / seconds, "step_s": seconds, "wall_s": wall, "steps": result.steps}


def load() -> str:
    return ", ".join(f"{v:.2f}" for v in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="cil,yilratt")
    p.add_argument("--device", default="cpu")
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--workers", type=int, default=0, help="DataLoader workers of the DataLoader mode")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1: a busy 2-core machine)")
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args(argv)

    from yawil.data import write_synthetic_dataset

    print(f"load average before: {load()}")
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        write_synthetic_dataset(data, episodes=args.episodes, frames=args.frames, k=15, seed=0)
        print("| model | mode | batch | steps | samples/s (each pass) | wall s (each pass) |\n|---|---|---|---|---|---|")
        for model in args.models.split(","):
            figures: dict[bool, list[dict[str, Any]]] = {False: [], True: []}
            for rep in range(args.repeat):
                for on in ((False, True) if rep % 2 == 0 else (True, False)):
                    out = Path(tmp) / f"{model}-{on}-{rep}"
                    figures[on].append(measure(data, out, model, device=args.device, data_on_device=on,
                                               steps=args.steps, batch_size=args.batch_size, workers=args.workers,
                                               threads=args.threads))
            for on, runs in figures.items():
                mode = "--data-on-device" if on else f"DataLoader ({args.workers} workers)"
                sps = " / ".join(f"{r['samples_per_s']:.1f}" for r in runs)
                wall = " / ".join(f"{r['wall_s']:.1f}" for r in runs)
                print(f"| {model} | {mode} | {args.batch_size} | {args.steps} | {sps} | {wall} |", flush=True)
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
