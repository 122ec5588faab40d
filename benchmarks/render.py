"""Camera render speed at 200x88 for a town-size scene (400 x 330 m grid, 50 vehicles, 30 pedestrians).

    .venv/bin/python benchmarks/render.py [--frames 600] [--backends software,opengl] [--no-semantic]

Prints frames/s and ms/frame per backend and weather, the cost split (scene graph + raster, numpy
post-processing), the software/opengl ratio, and the semantic camera's pass (`render_semantic` over the same
frames: ms/frame, its ratio to the RGB frame, and the one-off build of its scene). The town is synthetic: a grid of crossings and
T-junctions with two-lane roads, sidewalks, markings, lit crossings and buildings on every block side.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from yawil.sim.town.map.geometry import ActorView, Box, LightPost, Marking, Style, TownGeometry
from yawil.sim.town.render.renderer import CameraRenderer
from yawil.sim.town.render.weather_fx import post_effects
from yawil.sim.types import Pose

R, WALK = 3.5, 3.0  # road half width, sidewalk width
XS = (0.0, 100.0, 200.0, 300.0, 400.0)  # north-south roads
YS = (0.0, 110.0, 220.0, 330.0)  # east-west roads


def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def grid_town(seed: int = 0) -> TownGeometry:
    """A CARLA-Town01-sized grid of junctions, built for the benchmark."""
    rng = np.random.default_rng(seed)
    style = Style()
    roads, walks, marks, buildings, props, lights = [], [], [], [], [], []
    yellow, white = (0.9, 0.75, 0.1), (0.95, 0.95, 0.95)
    for x in XS:
        roads.append(rect(x - R, YS[0] - R, x + R, YS[-1] + R))
        marks.append(Marking(np.array([[x, YS[0]], [x, YS[-1]]]), yellow, 0.15, dashed=True))
    for y in YS:
        roads.append(rect(XS[0] - R, y - R, XS[-1] + R, y + R))
        marks.append(Marking(np.array([[XS[0], y], [XS[-1], y]]), yellow, 0.15, dashed=True))
    lid = 0
    for x in XS:
        for y in YS:
            for yaw in (0.0, math.pi / 2, math.pi, -math.pi / 2):
                u, n = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
                stop = np.array([x, y]) - u * (R + 4.0)
                marks.append(Marking(np.array([stop, stop - n * R]), white, 0.4, kind="stop"))
                for lat in np.arange(-R + 0.5, R - 0.4, 1.0):  # one Marking per crosswalk stripe
                    p = np.array([x, y]) + n * lat
                    marks.append(Marking(np.array([p - u * (R + 0.5), p - u * (R + 3.5)]), white, 0.5, kind="crosswalk"))
                post = stop - n * (R + 1.0)
                lights.append(LightPost(lid, float(post[0]), float(post[1]), yaw))
                lid += 1
    for x0, x1 in zip(XS[:-1], XS[1:], strict=True):
        for y0, y1 in zip(YS[:-1], YS[1:], strict=True):
            a, b, c, d = float(x0 + R), float(y0 + R), float(x1 - R), float(y1 - R)
            walks += [rect(a, b, c, b + WALK), rect(a, d - WALK, c, d), rect(a, b + WALK, a + WALK, d - WALK),
                      rect(c - WALK, b + WALK, c, d - WALK)]
            inner = (a + WALK + 1, b + WALK + 1, c - WALK - 1, d - WALK - 1)
            for side in range(4):  # buildings lined along each block side
                along = (inner[2] - inner[0]) if side < 2 else (inner[3] - inner[1])
                pos = 0.0
                while pos < along - 8:
                    w = float(rng.uniform(10, 18))
                    w = min(w, along - pos)
                    depth, h = float(rng.uniform(8, 14)), float(rng.uniform(6, 22))
                    col = style.building_palette[int(rng.integers(len(style.building_palette)))]
                    t = pos + w / 2
                    if side == 0:
                        buildings.append(Box(inner[0] + t, inner[1] + depth / 2, 0.0, w, depth, h, col))
                    elif side == 1:
                        buildings.append(Box(inner[0] + t, inner[3] - depth / 2, 0.0, w, depth, h, col))
                    elif side == 2:
                        buildings.append(Box(inner[0] + depth / 2, inner[1] + t, math.pi / 2, w, depth, h, col))
                    else:
                        buildings.append(Box(inner[2] - depth / 2, inner[1] + t, math.pi / 2, w, depth, h, col))
                    pos += w + float(rng.uniform(0.5, 4))
            for _ in range(3):
                px = float(rng.uniform(a + 5, c - 5))
                props.append(Box(px, b + 1.0, 0.15, 0.25, 0.25, 5.0, (0.3, 0.3, 0.3), kind="pole"))
                props.append(Box(px + 3, d - 1.0, 0.15, 2.0, 2.0, 5.5, (0.2, 0.5, 0.2), kind="tree"))
    return TownGeometry("bench-grid", (XS[0] - 20, YS[0] - 20, XS[-1] + 20, YS[-1] + 20), roads, walks, marks,
                        buildings, props, lights, style)


def traffic(rng: np.random.Generator, vehicles: int, pedestrians: int) -> list[ActorView]:
    actors = []
    for i in range(vehicles):
        if i % 2:
            x, y, yaw = float(rng.choice(XS)) + 1.75, float(rng.uniform(0, YS[-1])), math.pi / 2
        else:
            x, y, yaw = float(rng.uniform(0, XS[-1])), float(rng.choice(YS)) - 1.75, 0.0
        actors.append(ActorView(i, "vehicle", x, y, yaw, 4.5, 1.9, 1.5, tuple(rng.uniform(0.1, 0.9, 3))))
    for i in range(pedestrians):
        x, y = float(rng.uniform(0, XS[-1])), float(rng.choice(YS)) + R + 1.5
        actors.append(ActorView(1000 + i, "pedestrian", x, y, 0.0, 0.4, 0.5, 1.75, tuple(rng.uniform(0.1, 0.9, 3))))
    return actors


def load_town(name: str) -> TownGeometry:
    """The synthetic grid, or a map of the embedded simulator by name (town01, town02, square)."""
    if name == "grid":
        return grid_town()
    from yawil.sim.town.map.town import get_town

    return get_town(name).geometry


def run(backend: str, frames: int, weather: str, town_name: str = "grid", semantic: bool = True) -> dict[str, float]:
    town = load_town(town_name)
    xmin, ymin, xmax, ymax = town.bounds
    t0 = time.perf_counter()
    r = CameraRenderer(town, backend=backend)
    build = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    actors = traffic(rng, 50, 30)
    if town_name != "grid":  # spread the same traffic over the map's bounds (rendering cost only)
        actors = [ActorView(a.id, a.kind, xmin + (a.x / XS[-1]) * (xmax - xmin), ymin + (a.y / YS[-1]) * (ymax - ymin),
                            a.yaw, a.length, a.width, a.height, a.color) for a in actors]
    states = ("red", "yellow", "green")
    if town_name == "grid":
        poses = [Pose(5.0 + (i * 0.6) % 390, YS[1] - 1.75, 0.0) for i in range(frames)]  # drive east along a road
    else:
        from yawil.sim.town.map.town import get_town

        lanes = get_town(town_name).lanes  # drive along the lanes in turn
        poses = []
        for i in range(frames):
            lane = lanes.lanes[(i // 100) % len(lanes.lanes)]
            (p,), (yaw,) = lane.evaluate(np.array([lane.length * (i % 100) / 100]))
            poses.append(Pose(float(p[0]), float(p[1]), float(yaw)))
    r.render(poses[0], actors, {}, weather, 0)
    t_total = t_post = 0.0
    for i, pose in enumerate(poses):
        moved = [ActorView(a.id, a.kind, a.x + 0.05 * i * math.cos(a.yaw), a.y + 0.05 * i * math.sin(a.yaw), a.yaw,
                           a.length, a.width, a.height, a.color) for a in actors]
        lights = {lp.id: states[(i // 50 + lp.id) % 3] for lp in town.light_posts}
        t = time.perf_counter()
        r.render(pose, moved, lights, weather, i)
        t_total += time.perf_counter() - t
    img = r._grab()
    t = time.perf_counter()
    for i in range(frames):
        post_effects(img, r._haze, r._haze_color, r._rain_layers, i)
    t_post = time.perf_counter() - t
    out = {"build_s": build, "ms": 1e3 * t_total / frames, "post_ms": 1e3 * t_post / frames}
    if semantic:  # the same frames through the semantic camera (its scene built by the first call)
        t = time.perf_counter()
        r.render_semantic(poses[0], actors, {})
        out["sem_build_s"] = time.perf_counter() - t
        t_sem = 0.0
        for i, pose in enumerate(poses):
            moved = [ActorView(a.id, a.kind, a.x + 0.05 * i * math.cos(a.yaw), a.y + 0.05 * i * math.sin(a.yaw), a.yaw,
                               a.length, a.width, a.height, a.color) for a in actors]
            lights = {lp.id: states[(i // 50 + lp.id) % 3] for lp in town.light_posts}
            t = time.perf_counter()
            r.render_semantic(pose, moved, lights)
            t_sem += time.perf_counter() - t
        out["sem_ms"] = 1e3 * t_sem / frames
    r.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--backends", default="software,opengl")
    ap.add_argument("--weathers", default="ClearNoon,HardRainNoon")
    ap.add_argument("--town", default="grid", help="grid (synthetic, default) or a simulator map name")
    ap.add_argument("--no-semantic", action="store_true", help="skip the semantic camera's pass")
    args = ap.parse_args()
    town = load_town(args.town)
    print(f"town {town.name}: {len(town.buildings)} buildings, {len(town.road_polygons)} road polygons, "
          f"{len(town.markings)} markings, {len(town.light_posts)} lights; 50 vehicles, 30 pedestrians; 200x88")
    print("(ms/frame is wall time of CameraRenderer.render: scene update, Panda3D render, copy, haze/rain;")
    print(" semantic ms/frame that of CameraRenderer.render_semantic on the same frames, after the RGB ones)")
    print(f"{'backend':10s} {'weather':14s} {'frames/s':>9s} {'ms/frame':>9s} {'numpy post ms':>14s} {'build s':>8s}"
          f" {'semantic ms/frame':>18s} {'semantic/RGB':>13s} {'semantic build s':>17s}")
    per_backend: dict[str, float] = {}
    for backend in args.backends.split(","):
        for weather in args.weathers.split(","):
            try:
                res = run(backend, args.frames, weather, args.town, semantic=not args.no_semantic)
            except RuntimeError as e:
                print(f"{backend:10s} unavailable: {e}")
                break
            per_backend.setdefault(backend, res["ms"])
            sem = (f" {res['sem_ms']:18.3f} {res['sem_ms'] / res['ms']:13.2f} {res['sem_build_s']:17.2f}"
                   if "sem_ms" in res else "")
            print(f"{backend:10s} {weather:14s} {1e3 / res['ms']:9.0f} {res['ms']:9.3f} {res['post_ms']:14.3f} "
                  f"{res['build_s']:8.2f}{sem}")
    if "software" in per_backend and "opengl" in per_backend:
        print(f"software / opengl time ratio (first weather): {per_backend['software'] / per_backend['opengl']:.2f}")


if __name__ == "__main__":
    main()
