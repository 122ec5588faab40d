"""The static scene of a town: road and sidewalk polygons, markings, buildings, props, light posts.

Produces the `TownGeometry` the renderers draw, and the footprints the collision check uses. Buildings are
placed along the blocks from the layout's style seed, so a town looks the same every time it is built.
"""

from __future__ import annotations

import math

import numpy as np

from yawil.sim.town.map.geometry import Box, LightPost, Marking, TownGeometry
from yawil.sim.town.map.lanes import LaneGraph, bezier_handle
from yawil.sim.town.map.layout import Layout, setback

WHITE = (0.92, 0.92, 0.9)
YELLOW = (0.9, 0.75, 0.2)


def ccw(poly: np.ndarray) -> np.ndarray:
    """The polygon with counter-clockwise vertex order."""
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return poly if area >= 0 else poly[::-1].copy()


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain, CCW."""
    pts = sorted(set(map(tuple, np.round(points, 6))))
    if len(pts) < 3:
        return np.array(pts)

    def cross(o: tuple[float, ...], a: tuple[float, ...], b: tuple[float, ...]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, ...]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, ...]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)


def curve(p0: np.ndarray, h0: float, p3: np.ndarray, h1: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points (and headings) of the arc-like Bezier from (p0, h0) to (p3, h1)."""
    k = bezier_handle(p0, h0, p3, h1)
    c = np.array([p0, p0 + k * np.array([math.cos(h0), math.sin(h0)]), p3 - k * np.array([math.cos(h1), math.sin(h1)]), p3])
    t = np.linspace(0.0, 1.0, n)[:, None]
    u = 1.0 - t
    xy = u**3 * c[0] + 3 * u * u * t * c[1] + 3 * u * t * t * c[2] + t**3 * c[3]
    d = 3 * u * u * (c[1] - c[0]) + 6 * u * t * (c[2] - c[1]) + 3 * t * t * (c[3] - c[2])
    return xy, np.arctan2(d[:, 1], d[:, 0])


def offset(xy: np.ndarray, yaw: np.ndarray, d: float) -> np.ndarray:
    """Points shifted d metres to the left of the heading."""
    return xy + d * np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)


def band(xy: np.ndarray, yaw: np.ndarray, d0: float, d1: float) -> list[np.ndarray]:
    """Convex quads covering the strip between lateral offsets d0 and d1 along a polyline."""
    a, b = offset(xy, yaw, d0), offset(xy, yaw, d1)
    return [ccw(np.array([a[i], a[i + 1], b[i + 1], b[i]])) for i in range(len(xy) - 1)]


def node_roads(layout: Layout, node: int) -> list[tuple[int, np.ndarray]]:
    """(road, unit direction away from the node) for the roads at a node, sorted counter-clockwise."""
    out = []
    nx_, ny_ = layout.nodes[node][1:]
    for r, (a, b) in enumerate(layout.roads):
        if node in (a, b):
            o = b if a == node else a
            v = np.array([layout.nodes[o][1] - nx_, layout.nodes[o][2] - ny_])
            out.append((r, v / np.linalg.norm(v)))
    out.sort(key=lambda rv: math.atan2(rv[1][1], rv[1][0]))
    return out


def corner_curve(layout: Layout, node: int, n: int = 12) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Centre line of a corner (degree-2 node) from road r1's end to road r2's start."""
    (r1, u1), (r2, u2) = node_roads(layout, node)
    c = np.array(layout.nodes[node][1:])
    R = layout.corner_setback
    xy, yaw = curve(c + R * u1, math.atan2(-u1[1], -u1[0]), c + R * u2, math.atan2(u2[1], u2[0]), n)
    return xy, yaw, r1, r2


def bisector_point(c: np.ndarray, u1: np.ndarray, u2: np.ndarray, dist: float) -> np.ndarray:
    """Point at `dist` from both road lines, in the wedge turning CCW from u1 to u2."""
    a1 = math.atan2(u1[1], u1[0])
    gap = (math.atan2(u2[1], u2[0]) - a1) % (2 * math.pi)
    b = a1 + gap / 2
    return c + dist / math.sin(gap / 2) * np.array([math.cos(b), math.sin(b)])


def junction_hull(layout: Layout, node: int) -> np.ndarray:
    """The drivable polygon of a junction: the hull of its road ends (corners chamfered)."""
    c = np.array(layout.nodes[node][1:])
    S, W = layout.junction_setback, layout.lane_width
    ends = []
    for _, u in node_roads(layout, node):
        n = np.array([-u[1], u[0]])
        ends += [c + S * u + W * n, c + S * u - W * n]
    return ccw(convex_hull(np.array(ends)))


def build_geometry(layout: Layout, lanes: LaneGraph) -> TownGeometry:
    W, sw = layout.lane_width, layout.sidewalk_width
    nodes = lanes.node_xy
    xmin, ymin = nodes.min(axis=0) - layout.margin
    xmax, ymax = nodes.max(axis=0) + layout.margin
    geo = TownGeometry(layout.name, (float(xmin), float(ymin), float(xmax), float(ymax)), style=layout.style)
    for a, b in layout.roads:
        u = (nodes[b] - nodes[a]) / np.linalg.norm(nodes[b] - nodes[a])
        p0, p1 = nodes[a] + u * setback(layout, a), nodes[b] - u * setback(layout, b)
        line = np.array([p0, p1])
        yaw = np.full(2, math.atan2(u[1], u[0]))
        geo.road_polygons += band(line, yaw, -W, W)
        geo.sidewalk_polygons += band(line, yaw, W, W + sw) + band(line, yaw, -W - sw, -W)
        geo.markings.append(Marking(line.copy(), YELLOW, 0.15, False, "center"))
        geo.markings += [Marking(offset(line, yaw, d), WHITE, 0.12, False, "edge") for d in (W - 0.2, -W + 0.2)]
    for node in range(len(nodes)):
        c = nodes[node]
        roads = node_roads(layout, node)
        if lanes.degree[node] == 2:
            xy, yaw, _, _ = corner_curve(layout, node)
            geo.road_polygons += band(xy, yaw, -W, W)
            geo.sidewalk_polygons += band(xy, yaw, W, W + sw) + band(xy, yaw, -W - sw, -W)
            geo.markings.append(Marking(xy, YELLOW, 0.15, False, "center"))
            geo.markings += [Marking(offset(xy, yaw, d), WHITE, 0.12, False, "edge") for d in (W - 0.2, -W + 0.2)]
            continue
        S = layout.junction_setback
        for _, u in roads:
            n = np.array([-u[1], u[0]])
            lo, hi = lanes.CROSSWALK
            for lat in np.arange(-W + 0.5, W - 0.4, 1.0):
                p = c + n * lat
                geo.markings.append(Marking(np.array([p + (S + lo) * u, p + (S + hi) * u]), WHITE, 0.5, False, "crosswalk"))
        geo.road_polygons.append(junction_hull(layout, node))
        for k in range(len(roads)):
            u1, u2 = roads[k][1], roads[(k + 1) % len(roads)][1]
            n1, n2 = np.array([-u1[1], u1[0]]), np.array([-u2[1], u2[0]])
            a_in, a_out = c + S * u1 + W * n1, c + S * u1 + (W + sw) * n1
            b_in, b_out = c + S * u2 - W * n2, c + S * u2 - (W + sw) * n2
            c_in, c_out = bisector_point(c, u1, u2, W), bisector_point(c, u1, u2, W + sw)
            geo.sidewalk_polygons += [ccw(np.array([a_in, a_out, c_out, c_in])), ccw(np.array([c_in, c_out, b_out, b_in]))]
            tri = np.array([a_in, c_in, b_in])
            (ax, ay), (bx, by) = tri[1] - tri[0], tri[2] - tri[0]
            if abs(ax * by - ay * bx) > 0.5:
                geo.sidewalk_polygons.append(ccw(tri))
    for ap in lanes.approaches:
        geo.markings.append(Marking(np.array([ap.centre_xy, ap.kerb_xy]), WHITE, 0.4, False, "stop"))
        lane = lanes.lanes[ap.lane]
        (end,), (yaw_end,) = lane.evaluate(np.array([lane.length]))
        right = np.array([math.sin(yaw_end), -math.cos(yaw_end)])
        pos = end + right * (W / 2 + 1.0)
        geo.light_posts.append(LightPost(ap.light, float(pos[0]), float(pos[1]), ap.yaw))
    return geo


def light_post_boxes(geo: TownGeometry) -> list[Box]:
    """Collision footprints of the light poles (the renderer draws the posts themselves)."""
    return [Box(p.x, p.y, p.yaw, 0.4, 0.4, 5.0, (0.2, 0.2, 0.2), kind="pole") for p in geo.light_posts]
