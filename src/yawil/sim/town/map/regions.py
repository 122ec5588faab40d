"""A raster of what lies where (lane, junction, sidewalk, building, ground) for O(1) point queries.

The lane-invasion check, building placement and spawning ask "what is under this point" many times per
step; a 0.25 m grid drawn once with Pillow answers that with one array index.
"""

from __future__ import annotations

import math

import numpy as np
from PIL import Image, ImageDraw

from yawil.sim.town.map.geometry import Box, TownGeometry
from yawil.sim.town.map.lanes import LaneGraph
from yawil.sim.town.map.layout import Layout, setback
from yawil.sim.town.map.scenery import band, corner_curve, junction_hull, node_roads

GROUND = -1
SIDEWALK = -2
BUILDING = -3
JUNCTION_BASE = -100  # junction of node k is JUNCTION_BASE - k


def box_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = length / 2, width / 2
    return np.array([[x + c * dx - s * dy, y + s * dx + c * dy] for dx, dy in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))])


class RegionMap:
    """Cell value: lane id (>= 0) for each lane half of a road or corner, or one of the negative codes."""

    def __init__(self, layout: Layout, lanes: LaneGraph, geo: TownGeometry, res: float = 0.25) -> None:
        self.res = res
        self.xmin, self.ymin, xmax, ymax = geo.bounds
        self.w = int(math.ceil((xmax - self.xmin) / res)) + 1
        self.h = int(math.ceil((ymax - self.ymin) / res)) + 1
        img = Image.new("I", (self.w, self.h), GROUND)
        self._draw = ImageDraw.Draw(img)
        for poly in geo.sidewalk_polygons:
            self.fill(poly, SIDEWALK)
        W = layout.lane_width
        nodes = lanes.node_xy
        for r, (a, b) in enumerate(layout.roads):
            u = (nodes[b] - nodes[a]) / np.linalg.norm(nodes[b] - nodes[a])
            line = np.array([nodes[a] + u * setback(layout, a), nodes[b] - u * setback(layout, b)])
            yaw = np.full(2, math.atan2(u[1], u[0]))
            fwd, back = lanes.road_lanes[r]
            for poly in band(line, yaw, -W, 0.0):
                self.fill(poly, fwd)
            for poly in band(line, yaw, 0.0, W):
                self.fill(poly, back)
        for node in range(len(nodes)):
            if lanes.degree[node] == 2:
                xy, yaw, r1, _ = corner_curve(layout, node)
                conns = lanes.node_connectors[node]
                # the connector entering from road r1 drives along the curve's direction, on its right
                along = next(c for c in conns if lanes.lanes[lanes.lanes[c].entry].road == r1)
                other = next(c for c in conns if c != along)
                for poly in band(xy, yaw, -W, 0.0):
                    self.fill(poly, along)
                for poly in band(xy, yaw, 0.0, W):
                    self.fill(poly, other)
            else:
                self.fill(junction_hull(layout, node), JUNCTION_BASE - node)
        self.grid = np.array(img, dtype=np.int32)
        del self._draw
        self._node_roads = {n: node_roads(layout, n) for n in range(len(nodes))}

    def _pix(self, poly: np.ndarray) -> list[tuple[float, float]]:
        return [((x - self.xmin) / self.res, (y - self.ymin) / self.res) for x, y in poly]

    def fill(self, poly: np.ndarray, value: int) -> None:
        self._draw.polygon(self._pix(poly), fill=int(value))

    def add_boxes(self, boxes: list[Box], value: int = BUILDING) -> None:
        """Stamp box footprints into the grid (cells whose centre lies inside)."""
        for b in boxes:
            corners = box_corners(b.x, b.y, b.yaw, b.length, b.width)
            (i0, j0), (i1, j1) = self._cell(corners.min(axis=0)), self._cell(corners.max(axis=0))
            i0, j0, i1, j1 = max(i0, 0), max(j0, 0), min(i1 + 1, self.w), min(j1 + 1, self.h)
            if i0 >= i1 or j0 >= j1:
                continue
            gx, gy = np.meshgrid(self.xmin + np.arange(i0, i1) * self.res, self.ymin + np.arange(j0, j1) * self.res)
            c, s = math.cos(b.yaw), math.sin(b.yaw)
            dx, dy = gx - b.x, gy - b.y
            inside = (np.abs(c * dx + s * dy) <= b.length / 2) & (np.abs(-s * dx + c * dy) <= b.width / 2)
            self.grid[j0:j1, i0:i1][inside] = value

    def _cell(self, p: np.ndarray) -> tuple[int, int]:
        return (int(math.floor((p[0] - self.xmin) / self.res + 0.5)), int(math.floor((p[1] - self.ymin) / self.res + 0.5)))

    def query(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Region codes at points (vectorised); outside the map is GROUND."""
        ix = np.floor((np.asarray(x) - self.xmin) / self.res + 0.5).astype(np.int64)
        iy = np.floor((np.asarray(y) - self.ymin) / self.res + 0.5).astype(np.int64)
        inside = (ix >= 0) & (ix < self.w) & (iy >= 0) & (iy < self.h)
        out = np.full(ix.shape, GROUND, dtype=np.int32)
        out[inside] = self.grid[iy[inside], ix[inside]]
        return out

    def query_point(self, x: float, y: float) -> int:
        ix = int(math.floor((x - self.xmin) / self.res + 0.5))
        iy = int(math.floor((y - self.ymin) / self.res + 0.5))
        if 0 <= ix < self.w and 0 <= iy < self.h:
            return int(self.grid[iy, ix])
        return GROUND

    def box_free(self, b: Box) -> bool:
        """True when a box's footprint covers only ground (used to place buildings)."""
        corners = box_corners(b.x, b.y, b.yaw, b.length, b.width)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 0.5, 0.5), np.arange(lo[1], hi[1] + 0.5, 0.5))
        c, s = math.cos(b.yaw), math.sin(b.yaw)
        dx, dy = gx - b.x, gy - b.y
        inside = (np.abs(c * dx + s * dy) <= b.length / 2) & (np.abs(-s * dx + c * dy) <= b.width / 2)
        codes = self.query(gx[inside], gy[inside])
        return bool(np.all(codes == GROUND))


def is_drivable(code: np.ndarray) -> np.ndarray:
    return (code >= 0) | (code <= JUNCTION_BASE)
