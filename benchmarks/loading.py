"""Data loading speed: samples/s into augmented training batches, and bytes per frame on disk.

    .venv/bin/python benchmarks/loading.py                 # 3000 frames, batch 128, 2 workers
    .venv/bin/python benchmarks/loading.py --compare       # also: image compression x chunk shape

Writes a synthetic dataset (`yawil.data.synthetic`: smooth street-like images with mild pixel noise, so
compression behaves as on rendered frames) into a temporary directory, then times
`DrivingDataset` -> `DataLoader(batch_size=128, shuffle=True, num_workers=2)` -> uint8->float ->
augmentation in the main process, as training does: none, torchvision v2 GaussianBlur + ColorJitter (batch-wise),
and `yawil.learn.augment.augment_batch` (the trainer's own, per-sample parameters).
The files are in the page cache (just written): this measures decoding and batching, not the disk.
Target: >= 300 samples/s (5x YILRatt's training throughput on this machine).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from yawil.data.dataset import DrivingDataset
from yawil.data.synthetic import write_synthetic_dataset


def make(root: Path, frames: int, per_episode: int, **writer_kwargs: Any) -> tuple[float, float]:
    """Write the dataset; returns (bytes per frame of the episode files, seconds)."""
    t = time.perf_counter()
    m = write_synthetic_dataset(root, episodes=max(frames // per_episode, 1), frames=per_episode, k=15,
                                writer_kwargs=writer_kwargs)  # fmt: skip
    seconds = time.perf_counter() - t
    size = sum(os.path.getsize(m.path_of(e)) for e in m.episodes)
    return size / m.frames, seconds


def augmenter(kind: str) -> Any:
    """Batch augmentation in the main process: the trainer's (`yawil`), torchvision v2 blur + jitter, or none."""
    if kind == "yawil":
        from yawil.learn.augment import AugmentConfig, augment_batch

        cfg, gen = AugmentConfig(), torch.Generator().manual_seed(0)
        return lambda x: augment_batch(x, cfg, gen, inplace=True)
    if kind == "torchvision":
        from torchvision.transforms import v2

        tf = v2.Compose([v2.GaussianBlur(5, sigma=(0.1, 1.5)), v2.ColorJitter(brightness=0.4, contrast=0.4)])
        return tf
    return lambda x: x


def loader_rate(root: Path, batch: int, workers: int, augment: str, epochs: int) -> float:
    """Samples/s over `epochs` shuffled passes, after one warm-up batch."""
    aug = augmenter(augment)
    ds = DrivingDataset(root)
    loader = torch.utils.data.DataLoader(
        ds, batch_size=batch, shuffle=True, num_workers=workers, persistent_workers=workers > 0,
        generator=torch.Generator().manual_seed(0), drop_last=True,
    )  # fmt: skip
    it = iter(loader)
    next(it)  # worker start-up is paid once per run, not per batch
    n, t = 0, time.perf_counter()
    for epoch in range(epochs):
        for b in it if epoch == 0 else iter(loader):
            x = aug(b["image"].float().div_(255.0))
            n += x.shape[0]
    return n / (time.perf_counter() - t)


def random_read_rate(root: Path, n: int = 400) -> float:
    """Single-process random single-frame reads per second (what each DataLoader worker does)."""
    ds = DrivingDataset(root)
    idx = np.random.default_rng(0).integers(0, len(ds), n)
    ds[0]
    t = time.perf_counter()
    for i in idx:
        ds.image(int(i))
    return n / (time.perf_counter() - t)


def compare(tmp: Path, frames: int) -> None:
    print("\nimage storage options (raw frame 52800 B):")
    print("| compression | chunk (frames) | bytes/frame | write frames/s | random reads/s (1 process) |")
    print("|---|---|---|---|---|")
    options: list[tuple[str, str | None, int | None, int]] = [
        ("none", None, None, 1), ("lzf", "lzf", None, 1), ("gzip 1", "gzip", 1, 1), ("gzip 4", "gzip", 4, 1),
        ("lzf", "lzf", None, 8), ("gzip 1", "gzip", 1, 8),
    ]  # fmt: skip
    for i, (name, comp, opts, chunk) in enumerate(options):
        root = tmp / f"cmp{i}"
        bpf, secs = make(root, frames, 100, image_compression=comp, image_compression_opts=opts,
                         image_chunk_frames=chunk)  # fmt: skip
        print(f"| {name} | {chunk} | {bpf:,.0f} | {frames / secs:,.0f} | {random_read_rate(root):,.0f} |", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=3000)
    p.add_argument("--per-episode", type=int, default=100)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--threads", type=int, default=2, help="torch threads of the main process (augmentation)")
    p.add_argument("--compare", action="store_true", help="also compare image compression and chunk shapes")
    p.add_argument("--compare-frames", type=int, default=500)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    print(f"load average at start: {os.getloadavg()[0]:.2f} (2 cores shared); main process {args.threads} torch thread(s)")
    with tempfile.TemporaryDirectory(prefix="yawil-loading-") as tmp_name:
        tmp = Path(tmp_name)
        bpf, secs = make(tmp / "main", args.frames, args.per_episode)
        print(f"dataset: {args.frames} frames (K=15), {bpf:,.0f} bytes/frame on disk (raw image 52,800 B), "
              f"written in {secs:.1f} s ({args.frames / secs:,.0f} frames/s incl. image synthesis)")  # fmt: skip
        print(f"DrivingDataset index build: {timed(lambda: DrivingDataset(tmp / 'main')):.2f} s")
        print(f"random single-frame reads, 1 process: {random_read_rate(tmp / 'main'):,.0f} /s")
        runs = [(args.workers, "none"), (args.workers, "torchvision"), (args.workers, "yawil"), (0, "none")]
        for workers, augment in runs:
            rate = loader_rate(tmp / "main", args.batch, workers, augment, args.epochs)
            print(f"batch {args.batch}, {workers} workers, shuffle, augment={augment}: {rate:,.0f} samples/s", flush=True)
        if args.compare:
            compare(tmp, args.compare_frames)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


def timed(fn: Any) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


if __name__ == "__main__":
    main()
