"""Episodes/s of one benchmark slice under both executors: local processes, then Ray actors, same workers.

    .venv/bin/python benchmarks/executor.py        # nocrash, training, regular, routes 0:2, seed 1: 8 episodes

Runs `run_benchmark` (the expert, camera off, the protocol's weather rule) into temporary folders with the
local executor and with the ray executor on a local Ray of `--workers` CPUs, `--repeat` times in alternating
order (so that a load which changes during the run weighs on both). Starting Ray is timed apart: a cluster is
up before its jobs, a one-machine command pays it once. Checks that both give the same records but for their
wall time, and prints episodes/s of each and the ratio ray / local (target >= 0.9), with the load average
(another job on the machine slows both).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _records(folder: Path) -> list[dict[str, Any]]:
    lines = (folder / "episodes.jsonl").read_text().splitlines()
    recs = [{k: v for k, v in json.loads(x).items() if k != "wall_s"} for x in lines]
    return sorted(recs, key=lambda r: (r["route_id"], r["seed"], r["weather"]))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", default="nocrash")
    p.add_argument("--condition", default="training")
    p.add_argument("--tasks", default="regular")
    p.add_argument("--routes", default="0:2")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--repeat", type=int, default=2,
                   help="passes of each executor, in alternating order (local first, then ray first, ...): a load "
                        "that changes during the run weighs on both (default 2)")
    args = p.parse_args(argv)

    import ray

    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.bench.suites import episodes
    from yawil.executor import ExecutorConfig, init_ray

    eps = episodes(args.suite, conditions=[args.condition], tasks=args.tasks.split(","), routes=args.routes,
                   seeds=args.seeds)
    spec = AgentSpec("expert")
    print(f"{len(eps)} episodes ({args.suite} {args.condition} {args.tasks} routes {args.routes} seeds {args.seeds}), "
          f"--agent expert, camera off, {args.workers} workers; load average before {os.getloadavg()}")
    seconds: dict[str, list[float]] = {"local": [], "ray": []}
    starts: list[float] = []
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            for kind in ("local", "ray") if i % 2 == 0 else ("ray", "local"):
                if kind == "ray":  # up for the ray pass only: the local one runs without Ray's daemons
                    t = time.perf_counter()
                    init_ray(None, args.workers)
                    starts.append(time.perf_counter() - t)
                t = time.perf_counter()
                try:
                    run_benchmark(eps, spec, Path(tmp) / f"{kind}{i}", workers=args.workers, progress=False, label="x",
                                  executor=ExecutorConfig(kind))
                finally:
                    seconds[kind].append(time.perf_counter() - t)
                    ray.shutdown()
                print(f"  pass {i + 1} {kind:>5}: {seconds[kind][-1]:.1f} s"
                      + (f" (+ {starts[-1]:.1f} s starting Ray)" if kind == "ray" else "")
                      + f"; load average {os.getloadavg()[0]:.2f}", flush=True)
            same = same and _records(Path(tmp) / f"local{i}") == _records(Path(tmp) / f"ray{i}")
    rate = {kind: len(eps) * len(s) / sum(s) for kind, s in seconds.items()}
    for kind, r in rate.items():
        print(f"{kind:>6}: {r:.3f} episodes/s over {len(seconds[kind])} pass(es)")
    with_start = len(eps) * len(starts) / (sum(seconds["ray"]) + sum(starts))
    print(f"ray / local: {rate['ray'] / rate['local']:.2f}; counting the start of a local Ray "
          f"({sum(starts) / len(starts):.1f} s): {with_start / rate['local']:.2f}; records identical but wall_s: {same}")
    print(f"load average after {os.getloadavg()}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
