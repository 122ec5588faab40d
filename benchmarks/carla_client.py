"""Client-side costs of the CARLA backend that need no server, on a real carla.Map built from OpenDRIVE.

    .venv/bin/python benchmarks/carla_client.py [--repeat 200]

Prints: building the planner's topology from carla.Map.get_topology() (GlobalRoutePlanner's 1 m sampling),
planning a route, the per-step map queries of the lane-invasion check (5 x get_waypoint), and the camera
pipeline (BGRA 800x600 -> RGB crop -> 200x88). The server's own tick time is not measured here (no server).
The map is tests/fixtures/carla/grid.xodr (300 x 300 m, 9 nodes); Town01 is about 4x its lane length.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import carla
import numpy as np

from yawil.sim.carla.convert import bgra_to_rgb, crop_resize
from yawil.sim.carla.topology import CarlaTopology
from yawil.sim.types import Pose

XODR = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "carla" / "grid.xodr"


def per_call(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=200)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}")
    cmap = carla.Map("grid", XODR.read_text(encoding="utf-8"))
    t_topo = per_call(lambda: CarlaTopology.from_carla_map(cmap), 3)
    topo = CarlaTopology.from_carla_map(cmap)
    start, goal = Pose(10.0, 1.0, 0.0), Pose(290.0, 290.0, math.pi / 2)
    t_plan = per_call(lambda: topo.plan(start, goal), max(5, args.repeat // 20))
    loc = carla.Location(x=50.0, y=-1.7, z=0.0)
    t_wp = per_call(lambda: [cmap.get_waypoint(loc, project_to_road=False, lane_type=carla.LaneType.Driving) for _ in range(5)], args.repeat)
    raw = np.random.default_rng(0).integers(0, 256, size=600 * 800 * 4, dtype=np.uint8).tobytes()
    t_img = per_call(lambda: crop_resize(bgra_to_rgb(raw)), args.repeat)
    print(f"topology from carla.Map ({len(topo.segments)} segments): {t_topo * 1e3:.1f} ms")
    print(f"plan a {topo.plan(start, goal).route.length:.0f} m route: {t_plan * 1e3:.2f} ms")
    print(f"lane-invasion map queries per step (5 x get_waypoint): {t_wp * 1e6:.0f} us")
    print(f"camera pipeline per frame (BGRA 800x600 -> 200x88 RGB): {t_img * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
