"""Evaluation throughput: one fixed episode set driven with K=1 and with K episodes per worker, in one run.

    .venv/bin/python benchmarks/eval_throughput.py [--agent zoo:yilratt-dagger-ego] [--workers 2] [--k 4]
        [--routes 0:4] [--device cpu|cuda] [--configs torch:1,auto:1,auto:4]

The set: NoCrash Regular and Dense, both conditions (town01 training weathers, town02 test weathers), routes
`--routes`, seed 0, one weather per route (`cycle`): 16 episodes with the defaults. Each configuration
(ENGINE:K) drives the whole set into its own temporary folder with `yawil.bench.runner.run_benchmark`; the first
is the baseline of the ratios (by default the torch engine at K=1, the benchmark as it ran before batching).
Prints a markdown table (episodes/s, frames/s, wall time, ratio) with the CPU model, its cores and the load
average, then whether the records of the configurations that share an engine are identical (every field but
wall_s): they must be, since an episode's record does not depend on K.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from yawil.bench.runner import AgentSpec, drive_options, run_benchmark  # noqa: E402
from yawil.bench.suites import episodes  # noqa: E402


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def comparable(records: list[dict]) -> dict[str, dict]:
    out = {}
    for r in records:
        key = f"{r['task']}/{r['condition']}/{r['weather']}/{r['route_id']}/{r['seed']}"
        out[key] = {k: v for k, v in r.items() if k not in ("wall_s", "agent_options")}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agent", default="zoo:yilratt-dagger-ego")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--routes", default="0:4")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--keep", default=None, help="keep each configuration's results folder under this folder")
    ap.add_argument("--configs", default="torch:1,auto:1,auto:4",
                    help="ENGINE:K pairs, the first the baseline (default torch:1,auto:1,auto:4)")
    args = ap.parse_args()
    configs = [(c.split(":")[0], int(c.split(":")[1])) for c in args.configs.split(",")]
    eps = episodes("nocrash", conditions=["training", "new-town-weather"], tasks=["regular", "dense"],
                   routes=args.routes, seeds=1, weather_rule="cycle")
    drive = drive_options(argparse.Namespace(agent=args.agent, speed_control=False, stop_release=0.0))
    load0 = os.getloadavg()
    print(f"{len(eps)} episodes (NoCrash regular + dense, both conditions, routes {args.routes}, seed 0), "
          f"agent {args.agent}, {args.workers} workers, device {args.device}")
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores; load average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}")
    rows, records = [], {}
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.keep or scratch
        for engine, k in configs:
            spec = AgentSpec(args.agent, device=args.device, engine=engine, **drive)
            label = f"{spec.engine_label()} K={k}"
            t0 = time.perf_counter()
            summary = run_benchmark(eps, spec, Path(tmp) / f"{engine}{k}", workers=args.workers, progress=False,
                                    episodes_per_worker=k)
            wall = time.perf_counter() - t0
            frames = sum(int(r["steps"]) for r in summary.records)
            rows.append((label, wall, frames, summary.successes))
            records[(spec.engine_label(), k)] = comparable(summary.records)
            print(f"  {label}: {wall:.1f} s, {frames} frames, {summary.successes}/{len(eps)} successful", flush=True)
    base = rows[0][1]
    print(f"\n| configuration | wall s | episodes/s | frames/s | successes | speed-up vs {rows[0][0]} |")
    print("|---|---|---|---|---|---|")
    for label, wall, frames, ok in rows:
        print(f"| {label} | {wall:.1f} | {len(eps) / wall:.3f} | {frames / wall:.1f} | {ok}/{len(eps)} | {base / wall:.2f}x |")
    load1 = os.getloadavg()
    print(f"\nload average after: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    same = True
    engines = {e for e, _ in records}
    for e in sorted(engines):
        ks = sorted(k for ee, k in records if ee == e)
        for k in ks[1:]:
            a, b = records[(e, ks[0])], records[(e, k)]
            differ = sorted(key for key in a if a[key] != b.get(key))
            same &= not differ
            print(f"records of {e}: K={ks[0]} and K={k} {'identical' if not differ else 'DIFFER'} (every field but wall_s)")
            for key in differ:
                fields = [f for f in a[key] if a[key][f] != b[key].get(f)]
                print(f"  {key}: {', '.join(fields)} (steps {a[key]['steps']} and {b[key]['steps']})")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
