"""The GPU recipe's figures on one GPU node, in at most 10 minutes (issue 18, item 3; docs/scale.md).

    .venv/bin/python benchmarks/gpu_check.py                     # one H100/H200 node: every core, CUDA
    .venv/bin/python benchmarks/gpu_check.py --device cpu --tiny # the same steps at toy sizes (a CPU check)

1. collection: `--frames` expert frames of town01 on `--workers` processes (default: every core) -> frames/s;
2. training: YILRatt with --data-on-device, bf16 autocast, channels_last, batch 512, `--steps` steps ->
   samples/s of the steps (target: >= 8,000 on one H100/H200: the paper's 100 epochs of 200k frames in
   under 45 min), and the seconds the splits took to load onto the device;
3. a benchmark slice (`--episodes` CoRL2017 training-condition episodes, one weather each) with the trained
   checkpoint driven on `--device` by every worker -> episodes/s.

Prints a Markdown table to paste into docs/performance.md, with the GPU's name, the command and the load.
The run's folders are temporary unless `--keep DIR`.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_modes import load, measure  # noqa: E402  (the same training measurement as the CPU comparison)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    p.add_argument("--tiny", action="store_true", help="toy sizes (120 frames, 2 steps of 8, 1 episode): a CPU check")
    p.add_argument("--workers", type=int, default=0, help="collection and benchmark processes (default: every core)")
    p.add_argument("--frames", type=int, default=30_000)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--batch-size", type=int, default=512)
    p.add_argument("--episodes", type=int, default=16, help="benchmark episodes, at most 25 (default 16)")
    p.add_argument("--keep", default=None, metavar="DIR", help="keep the dataset, run and results in DIR")
    args = p.parse_args(argv)
    if args.tiny:
        args.frames, args.steps, args.batch_size, args.episodes = 120, 2, 8, 1
        args.workers = args.workers or 1
    workers = args.workers or (os.cpu_count() or 1)
    if not 1 <= args.episodes <= 25:
        p.error(f"--episodes {args.episodes}: expected 1 to 25 (the CoRL2017 straight routes)")

    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        print("gpu_check: --device cuda: torch sees no CUDA device here (use --device cpu --tiny for a CPU check)",
              file=sys.stderr)
        return 2
    name = torch.cuda.get_device_name(0) if args.device == "cuda" else "cpu"
    started = time.perf_counter()
    before = load()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        rows = run_checks(root, args, workers)
    after = load()
    total = time.perf_counter() - started
    command = "benchmarks/gpu_check.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"\n`{command.strip()}` on {name}, {os.cpu_count()} cores, torch {torch.__version__}; {total:.0f} s in all; "
          f"load average {before} before, {after} after\n")
    print("| step | figure |\n|---|---|")
    for step, figure in rows:
        print(f"| {step} | {figure} |")
    return 0


def run_checks(root: Path, args: argparse.Namespace, workers: int) -> list[tuple[str, str]]:
    """Collect, train, benchmark; the (step, figure) rows of the table."""
    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.bench.suites import episodes
    from yawil.data.collect import collect

    rows: list[tuple[str, str]] = []
    data = root / "data"
    t = time.perf_counter()
    s = collect(data, town="town01", weathers="train", frames=args.frames, workers=workers, seed=0, progress=False)
    wall = time.perf_counter() - t
    rows.append((f"collect town01, {_n(workers, 'worker')}", f"{s.dataset_frames:,} frames in {wall:.1f} s: "
                 f"{s.dataset_frames / wall:,.0f} frames/s (process starts included)"))

    precision = "bf16"
    r = measure(data, root / "run", "yilratt", device=args.device, data_on_device=True, steps=args.steps,
                batch_size=args.batch_size, precision=precision, channels_last="on", workers=workers)
    rows.append((f"train yilratt --data-on-device --device {args.device} --precision {precision} --channels-last on "
                 f"--batch-size {args.batch_size}, {r['steps']} steps",
                 f"**{r['samples_per_s']:,.0f} samples/s** of the steps ({r['step_s']:.1f} s; run {r['wall_s']:.1f} s "
                 "wall with loading the splits, validation and saving)"))

    eps = episodes("corl2017", conditions=["training"], tasks=["straight"], routes=f"0:{args.episodes}", seeds=1,
                   weather_rule="cycle")
    spec = AgentSpec(str(root / "run" / "best.pt"), device=args.device).validate()
    t = time.perf_counter()
    b = run_benchmark(eps, spec, root / "results", workers=min(workers, len(eps)), progress=False)
    wall = time.perf_counter() - t
    rows.append((f"bench corl2017 straight, {_n(len(eps), 'episode')}, agent on {args.device}, "
                 f"{_n(min(workers, len(eps)), 'worker')}", f"{_n(b.ran, 'episode')} in {wall:.1f} s: "
                 f"{b.ran / wall:.2f} episodes/s (an agent of a few hundred steps: many end early)"))
    return rows


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}" + ("" if count == 1 else "s")


if __name__ == "__main__":
    raise SystemExit(main())
