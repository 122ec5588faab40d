"""Embedded simulator speed: world steps per second with and without the camera, and where the time goes.

    .venv/bin/python benchmarks/sim.py [--town town01] [--steps 2000] [--camera-steps 300]

Runs 50 vehicles + 30 pedestrians with a pure-pursuit ego, single process. The cost split times each part
of `EmbeddedWorld.step` by wrapping it (the wrappers add a little overhead, so the split is measured in a
separate run from the headline figure).
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from typing import Any

from yawil.sim.cli import follow_route
from yawil.sim.town import world as world_mod
from yawil.sim.town.world import EmbeddedWorld
from yawil.sim.types import Scenario


def run(town: str, steps: int, camera: bool, split: bool) -> tuple[float, float, dict[str, float]]:
    w = EmbeddedWorld()
    sc = Scenario(town=town, vehicles=50, pedestrians=30, camera=camera, min_route_length=200.0)
    cost: dict[str, float] = defaultdict(float)
    originals: list[tuple[Any, str, Any]] = []

    def wrap(owner: Any, name: str, label: str) -> None:
        fn = getattr(owner, name)
        originals.append((owner, name, fn))

        def timed(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            out = fn(*a, **k)
            cost[label] += time.perf_counter() - t0
            return out

        setattr(owner, name, timed)

    obs = w.reset(sc, seed=0)
    if split:
        wrap(world_mod, "step_bicycle", "dynamics")
        wrap(w.vehicles, "step", "traffic (vehicles)")
        wrap(w.pedestrians, "step", "traffic (pedestrians)")
        wrap(w, "_criteria", "criteria")
        wrap(w, "_privileged", "observation (privileged)")
        if camera:
            wrap(w._renderer, "render", "render")
    n = 0
    t0, c0 = time.perf_counter(), time.process_time()
    driver_time = driver_cpu = 0.0
    while n < steps:
        t1, c1 = time.perf_counter(), time.process_time()
        control = follow_route(obs)
        driver_time += time.perf_counter() - t1
        driver_cpu += time.process_time() - c1
        obs = w.step(control)
        n += 1
        if obs.done:
            obs = w.reset(sc, seed=n)
    total = time.perf_counter() - t0 - driver_time
    cpu = time.process_time() - c0 - driver_cpu
    for owner, name, fn in originals:
        setattr(owner, name, fn)
    w.close()
    return n / total, n / cpu, {k: v / n * 1e6 for k, v in cost.items()} | {"total": total / n * 1e6}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--town", default="town01")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--camera-steps", type=int, default=300)
    args = ap.parse_args()
    rows: list[tuple[str, float, float]] = []
    for camera, steps in ((False, args.steps), (True, args.camera_steps)):
        sps, cps, _ = run(args.town, steps, camera, split=False)
        rows.append((f"{args.town}, 50 vehicles + 30 pedestrians, camera {'on (200x88)' if camera else 'off'}", sps, cps))
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print("| setting | world steps/s (wall) | steps per CPU-second |\n|---|---|---|")
    for name, sps, cps in rows:
        print(f"| {name} | {sps:.0f} | {cps:.0f} |")
    for camera, steps in ((False, args.steps), (True, args.camera_steps)):
        _, _, cost = run(args.town, steps, camera, split=True)
        print(f"\ncost split per step, camera {'on' if camera else 'off'} (microseconds):")
        print("| part | us/step |\n|---|---|")
        other = cost["total"] - sum(v for k, v in cost.items() if k != "total")
        for k, v in sorted(cost.items(), key=lambda kv: -kv[1]):
            if k != "total":
                print(f"| {k} | {v:.0f} |")
        print(f"| other (step glue, region queries, observation) | {other:.0f} |")
        print(f"| total | {cost['total']:.0f} |")


if __name__ == "__main__":
    main()
