"""A built town: layout, lane graph, scene geometry, region raster, walkways and static footprints.

Building a town takes a fraction of a second; `get_town` caches it per layout file, so episodes and worlds
share one copy (towns are never mutated after building).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from yawil.sim.town.map.buildings import place_buildings, place_props
from yawil.sim.town.map.geometry import Box, TownGeometry
from yawil.sim.town.map.lanes import LaneGraph
from yawil.sim.town.map.layout import Layout, load_layout, resolve_town
from yawil.sim.town.map.regions import RegionMap
from yawil.sim.town.map.scenery import build_geometry, light_post_boxes
from yawil.sim.town.map.walkways import Walkways


@dataclass
class Town:
    layout: Layout
    lanes: LaneGraph
    geometry: TownGeometry
    regions: RegionMap
    walkways: Walkways
    statics: np.ndarray  # (K, 5) x, y, yaw, length, width of everything solid that stands still
    static_radius: np.ndarray  # (K,) bounding-circle radius of each

    @property
    def name(self) -> str:
        return self.layout.name


def build_town(layout: Layout) -> Town:
    lanes = LaneGraph(layout)
    geo = build_geometry(layout, lanes)
    regions = RegionMap(layout, lanes, geo)
    geo.buildings = place_buildings(layout, lanes, regions)
    geo.props = place_props(layout, lanes, regions)
    lo, hi = lanes.CROSSWALK
    walk = Walkways(layout, lanes.node_xy, lanes.degree, (lo + hi) / 2)
    solid: list[Box] = [*geo.buildings, *geo.props, *light_post_boxes(geo)]
    statics = np.array([(b.x, b.y, b.yaw, b.length, b.width) for b in solid], dtype=np.float64).reshape(-1, 5)
    radius = 0.5 * np.hypot(statics[:, 3], statics[:, 4])
    return Town(layout, lanes, geo, regions, walk, statics, radius)


_CACHE: dict[tuple[str, float], Town] = {}


def get_town(town: str) -> Town:
    """The built town for a built-in name or a layout path (cached; rebuilt if the file changed)."""
    path = resolve_town(town)
    key = (str(path.resolve()), Path(path).stat().st_mtime)
    if key not in _CACHE:
        _CACHE[key] = build_town(load_layout(town))
    return _CACHE[key]


def lane_heading_at(town: Town, x: float, y: float, yaw: float) -> float:
    """Heading of the nearest lane going roughly the ego's way (the map's own lane yaw)."""
    lane, s, _ = town.lanes.snap(x, y, yaw)
    _, (h,) = town.lanes.lanes[lane].evaluate(np.array([s]))
    return float(math.remainder(h, 2 * math.pi))
