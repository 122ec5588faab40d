"""Buildings along the blocks and street furniture on the sidewalks, placed from the style's seed."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from yawil.sim.town.map.geometry import Box
from yawil.sim.town.map.lanes import LaneGraph
from yawil.sim.town.map.layout import Layout, setback
from yawil.sim.town.map.regions import RegionMap

POLE_COLOR = (0.25, 0.25, 0.27)
TREE_COLOR = (0.2, 0.4, 0.18)


def road_frames(layout: Layout, lanes: LaneGraph) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, float, float]]:
    """Each road as (node a, node b, position of a, unit direction a -> b, length, heading)."""
    for a, b in layout.roads:
        pa, pb = lanes.node_xy[a], lanes.node_xy[b]
        length = float(np.linalg.norm(pb - pa))
        u = (pb - pa) / length
        yield a, b, pa, u, length, math.atan2(u[1], u[0])


def place_buildings(layout: Layout, lanes: LaneGraph, regions: RegionMap) -> list[Box]:
    """Rows of buildings behind both sidewalks of every road, never on road, sidewalk or each other."""
    rng = np.random.default_rng(layout.buildings.seed)
    bs = layout.buildings
    palette = layout.style.building_palette
    W, sw = layout.lane_width, layout.sidewalk_width
    out: list[Box] = []
    for a, b, pa, u, length, yaw in road_frames(layout, lanes):
        for side in (1.0, -1.0):
            n = side * np.array([-u[1], u[0]])
            s = setback(layout, a) + sw
            end = length - setback(layout, b) - sw
            while s < end - 6.0:
                blen = float(rng.uniform(8.0, 20.0))
                depth = float(rng.uniform(*bs.depth))
                height = float(rng.uniform(*bs.height))
                gap = float(rng.uniform(0.5, 3.0))
                color = palette[int(rng.integers(len(palette)))]
                keep = rng.random() < bs.density
                blen = min(blen, end - s)
                centre = pa + u * (s + blen / 2) + n * (W + sw + 1.0 + depth / 2)
                box = Box(float(centre[0]), float(centre[1]), yaw, blen, depth, height, color)
                if keep and blen >= 5.0 and regions.box_free(box):
                    out.append(box)
                    regions.add_boxes([box])
                s += blen + gap
    return out


def place_props(layout: Layout, lanes: LaneGraph, regions: RegionMap) -> list[Box]:
    """Street lamps at the kerb and trees at the back of the sidewalks, at regular spacing."""
    rng = np.random.default_rng(layout.buildings.seed + 1)
    W, sw = layout.lane_width, layout.sidewalk_width
    out: list[Box] = []
    for a, b, pa, u, length, yaw in road_frames(layout, lanes):
        lo, hi = setback(layout, a) + 6.0, length - setback(layout, b) - 6.0
        for side in (1.0, -1.0):
            n = side * np.array([-u[1], u[0]])
            start = lo + float(rng.uniform(0.0, 10.0))
            for k, s in enumerate(np.arange(start, hi, 15.0)):
                if k % 2 == 0:
                    p = pa + u * s + n * (W + 0.4)
                    out.append(Box(float(p[0]), float(p[1]), yaw, 0.3, 0.3, 6.0, POLE_COLOR, kind="pole"))
                elif rng.random() < 0.7:
                    p = pa + u * s + n * (W + sw - 0.6)
                    out.append(Box(float(p[0]), float(p[1]), yaw, 0.5, 0.5, float(rng.uniform(4.0, 7.0)), TREE_COLOR,
                                   kind="tree"))
    return out
