"""Wall time of a whole benchmark evaluation (default: the expert, suites corl2017 + nocrash, one condition).

    .venv/bin/python benchmarks/bench_runs.py --condition training --workers 2 --out results/expert

Runs (or resumes) the evaluation with `yawil.bench.runner`, then prints, per task, episodes, simulated time,
summed episode wall time and steps per second, and the total wall time of this invocation. Re-running on a
finished folder only prints the per-task figures from the records (`wall_s` of each episode).
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

from yawil.bench.records import episode_key, iter_results
from yawil.bench.runner import AgentSpec, run_benchmark
from yawil.bench.suites import episodes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--condition", default="training")
    ap.add_argument("--suite", default="all")
    ap.add_argument("--agent", default="expert")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--routes", default=None)
    ap.add_argument("--out", default="results/expert")
    args = ap.parse_args()
    eps = episodes(args.suite, conditions=[args.condition], seeds=args.seeds, routes=args.routes)
    t0 = time.perf_counter()
    summary = run_benchmark(eps, AgentSpec(args.agent), args.out, workers=args.workers)
    wall = time.perf_counter() - t0
    keys = {e.key for e in eps}
    per: dict[str, list[dict]] = defaultdict(list)
    for r in iter_results(args.out):
        if episode_key(r) in keys:
            per[r["task"]].append(r)
    print(f"\n{args.agent}, suite {args.suite}, condition {args.condition}, workers {args.workers}")
    print(f"{'task':<12}{'episodes':>9}{'success':>9}{'sim s':>10}{'ep wall s':>11}{'steps/s':>9}")
    tot_sim = tot_wall = 0.0
    for task, recs in per.items():
        sim = sum(r["time_s"] for r in recs)
        ew = sum(r["wall_s"] for r in recs)
        steps = sum(r["steps"] for r in recs)
        tot_sim += sim
        tot_wall += ew
        ok = sum(bool(r["success"]) for r in recs)
        print(f"{task:<12}{len(recs):>9}{ok:>9}{sim:>10.0f}{ew:>11.1f}{steps / max(ew, 1e-9):>9.0f}")
    print(f"{'all':<12}{sum(map(len, per.values())):>9}{'':>9}{tot_sim:>10.0f}{tot_wall:>11.1f}")
    print(f"this invocation: {summary.ran} episodes run, {summary.skipped} already done, wall {wall:.1f} s "
          f"({wall / 60:.1f} min)")


if __name__ == "__main__":
    main()
