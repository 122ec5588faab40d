"""The static scene as numpy meshes: a town's geometry cut into cells, grouped by tile, ready to bake into Panda3D.

The renderer bakes each (layer, tile) mesh into one Geom once per town; this module builds those meshes
(ground, roads, sidewalks, markings, buildings, props, light posts and heads, puddles), validates the
geometry on the way, and needs Panda3D only to bake. Every polygon carries its semantic class
(`yawil.sim.semantic`), so that the semantic camera draws the very same triangles in class colours.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from yawil.sim import semantic as sem
from yawil.sim.town.map.geometry import Box, LightPost, Marking, TownGeometry

_GROUND_Z, _ROAD_Z, _PUDDLE_Z, _MARK_Z, _SIDEWALK_H = -0.03, 0.0, 0.01, 0.02, 0.15
_CELL = 10.0  # tinydisplay mis-handles large triangles: flat surfaces are cut into cells of this size
_DASH, _GAP = 3.0, 3.0  # dashed markings (m)
PUDDLE_GROUPS = 4
_LAMP = {"red": (1.0, 0.12, 0.08), "yellow": (1.0, 0.8, 0.1), "green": (0.15, 1.0, 0.35)}
_HEAD_BOTTOM, _HEAD_H, _HEAD_W, _HEAD_D, _POLE_H = 2.6, 1.1, 0.5, 0.35, 3.75


# ----------------------------------------------------------------------------------------------- meshes
class Mesh:
    """Indexed triangles with per-vertex normal and colour, built with numpy, baked into one Geom; each
    polygon keeps its semantic class id in `labels` (one per entry of `pos`)."""

    def __init__(self) -> None:
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.col: list[np.ndarray] = []
        self.idx: list[np.ndarray] = []
        self.labels: list[int] = []
        self.count = 0

    def __len__(self) -> int:
        return self.count

    def poly(self, pts: np.ndarray, color: Sequence[float] | np.ndarray, normal: Sequence[float],
             label: int = sem.UNLABELED) -> None:
        """A planar convex polygon (M, 3) as a fan, wound to face `normal`; colour per polygon or vertex."""
        pts = np.asarray(pts, dtype=np.float32)
        m = pts.shape[0]
        if m < 3:
            return
        n = np.asarray(normal, dtype=np.float32)
        cols = np.asarray(color, dtype=np.float32)
        cols = np.broadcast_to(cols[..., :3], (m, 3)) if cols.ndim == 1 else cols[:, :3]
        if float(np.dot(np.cross(pts[1] - pts[0], pts[2] - pts[0]), n)) < 0.0:
            pts, cols = pts[::-1], cols[::-1]
        fan = np.stack([np.zeros(m - 2, np.int64), np.arange(1, m - 1), np.arange(2, m)], axis=1).ravel()
        self.pos.append(pts)
        self.nrm.append(np.broadcast_to(n, (m, 3)))
        self.col.append(np.concatenate([cols, np.ones((m, 1), np.float32)], axis=1))
        self.idx.append(fan + self.count)
        self.labels.append(label)
        self.count += m

    def box(self, x: float, y: float, z: float, yaw: float, length: float, width: float, height: float,
            color: Sequence[float], skip_front: bool = False, window_color: Sequence[float] | None = None,
            label: int = sem.UNLABELED) -> None:
        """An oriented box; with `window_color` its sides get a darker band per floor."""
        c, s = math.cos(yaw), math.sin(yaw)
        fx, fy, lx, ly = c * length / 2, s * length / 2, -s * width / 2, c * width / 2
        base = np.array([[x + fx + lx, y + fy + ly], [x - fx + lx, y - fy + ly],
                         [x - fx - lx, y - fy - ly], [x + fx - lx, y + fy - ly]])
        top = z + height
        self.poly(np.column_stack([base, np.full(4, top)]), color, (0, 0, 1), label)
        bands = [(z, top, color)]
        if window_color is not None and height >= 4.0:
            # a 4 m ground floor with shop windows at 1.8-3.4 m (no band edge at the camera's 1.4 m, which
            # would draw one line along the horizon across every building), then 3 m floors
            edges = [(z + 1.8, z + 3.4)] + [(z + 4.0 + 3.0 * k + 0.9, z + 4.0 + 3.0 * k + 2.1)
                                            for k in range(int((height - 4.0) // 3.0))]
            bands, lo = [], z
            for w0, w1 in edges:
                bands += [(lo, w0, color), (w0, w1, window_color)]
                lo = w1
            bands.append((lo, top, color))
        for i in range(4):
            if skip_front and i == 3:  # edge 3->0 is the face at +length/2 (the front)
                continue
            a, b = base[i], base[(i + 1) % 4]
            nx, ny = b[1] - a[1], -(b[0] - a[0])
            nn = math.hypot(nx, ny) or 1.0
            for z0, z1, col in bands:
                q = np.array([[a[0], a[1], z0], [b[0], b[1], z0], [b[0], b[1], z1], [a[0], a[1], z1]])
                self.poly(q, col, (nx / nn, ny / nn, 0.0), label)

    def vertex_labels(self) -> np.ndarray:
        """(count,) uint8 class id of every vertex."""
        if not self.pos:
            return np.zeros(0, np.uint8)
        return np.repeat(np.asarray(self.labels, np.uint8), [len(p) for p in self.pos])

    def geom_node(self, name: str) -> Any:
        from panda3d.core import GeomNode

        node = GeomNode(name)
        node.addGeom(self.geom(name))
        return node

    def geom(self, name: str) -> Any:
        """Bake into one Geom: float32 vertex/normal/colour, uint32 indexed triangles."""
        from panda3d.core import Geom, GeomEnums, GeomTriangles, GeomVertexData

        data = np.concatenate(
            [np.concatenate(self.pos), np.concatenate(self.nrm), np.concatenate(self.col)], axis=1
        ).astype(np.float32)
        vdata = GeomVertexData(name, _vertex_format(), Geom.UHStatic)
        vdata.uncleanSetNumRows(data.shape[0])
        memoryview(vdata.modifyArray(0)).cast("B")[:] = np.ascontiguousarray(data).tobytes()
        idx = np.concatenate(self.idx).astype(np.uint32)
        prim = GeomTriangles(Geom.UHStatic)
        prim.setIndexType(GeomEnums.NT_uint32)
        handle = prim.modifyVertices()
        handle.uncleanSetNumRows(idx.size)
        memoryview(handle).cast("B")[:] = idx.tobytes()
        geom = Geom(vdata)
        geom.addPrimitive(prim)
        return geom


_FORMAT: list[Any] = []


def _vertex_format() -> Any:
    if not _FORMAT:
        from panda3d.core import Geom, GeomVertexArrayFormat, GeomVertexFormat, InternalName

        arr = GeomVertexArrayFormat()
        arr.addColumn(InternalName.getVertex(), 3, Geom.NTFloat32, Geom.CPoint)
        arr.addColumn(InternalName.getNormal(), 3, Geom.NTFloat32, Geom.CNormal)
        arr.addColumn(InternalName.getColor(), 4, Geom.NTFloat32, Geom.CColor)
        _FORMAT.append(GeomVertexFormat.registerFormat(GeomVertexFormat(arr)))
    return _FORMAT[0]


def clip_to_cells(poly: np.ndarray, cell: float) -> list[np.ndarray]:
    """Cut a convex polygon (M, 2) by a square grid: convex pieces no larger than one cell."""
    pieces = []
    lo, hi = np.floor(poly.min(0) / cell).astype(int), np.floor(poly.max(0) / cell).astype(int)
    for i in range(lo[0], hi[0] + 1):
        for j in range(lo[1], hi[1] + 1):
            p = poly
            for axis, bound, keep_below in ((0, i * cell, False), (0, (i + 1) * cell, True),
                                            (1, j * cell, False), (1, (j + 1) * cell, True)):
                p = _clip_half(p, axis, bound, keep_below)
                if p.shape[0] < 3:
                    break
            if p.shape[0] >= 3 and _area(p) > 1e-6:
                pieces.append(p)
    return pieces


def _clip_half(p: np.ndarray, axis: int, bound: float, keep_below: bool) -> np.ndarray:
    """Sutherland-Hodgman against one axis-aligned half-plane."""
    d = (bound - p[:, axis]) if keep_below else (p[:, axis] - bound)
    out = []
    for k in range(p.shape[0]):
        a, b, da, db = p[k], p[(k + 1) % p.shape[0]], d[k], d[(k + 1) % p.shape[0]]
        if da >= 0:
            out.append(a)
        if (da >= 0) != (db >= 0):
            out.append(a + (b - a) * (da / (da - db)))
    return np.array(out) if out else np.zeros((0, 2))


def _area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _inside_convex(poly: np.ndarray, pt: np.ndarray) -> bool:
    e = np.roll(poly, -1, axis=0) - poly
    r = pt - poly
    cross = e[:, 0] * r[:, 1] - e[:, 1] * r[:, 0]
    return bool(np.all(cross >= 0) or np.all(cross <= 0))


# ------------------------------------------------------------------------------------------- the scene
class Tiles:
    """Meshes keyed by (layer, tile) so that a tile out of view is culled as a whole."""

    def __init__(self, size: float) -> None:
        self.size = size
        self.meshes: dict[tuple[str, int, int], Mesh] = {}

    def key(self, x: float, y: float) -> tuple[int, int]:
        return (0, 0) if self.size <= 0 else (int(x // self.size), int(y // self.size))

    def at(self, layer: str, x: float, y: float) -> Mesh:
        return self.meshes.setdefault((layer, *self.key(x, y)), Mesh())


def build_static(geo: TownGeometry, tiles: Tiles, rng: np.random.Generator) -> None:
    """Ground, roads, sidewalks, markings, buildings, props, poles and light housings."""
    style = geo.style
    xmin, ymin, xmax, ymax = geo.bounds
    if not (xmax > xmin and ymax > ymin):
        raise ValueError(f"TownGeometry {geo.name!r}: bounds {geo.bounds} must be (xmin, ymin, xmax, ymax)")
    margin = 30.0
    gx = np.arange(math.floor((xmin - margin) / _CELL), math.ceil((xmax + margin) / _CELL)) * _CELL
    gy = np.arange(math.floor((ymin - margin) / _CELL), math.ceil((ymax + margin) / _CELL)) * _CELL
    ground = np.asarray(style.ground)
    for x0 in gx:
        for y0 in gy:
            col = np.clip(ground * (1.0 + rng.uniform(-0.05, 0.05)), 0, 1)
            q = np.array([[x0, y0, _GROUND_Z], [x0 + _CELL, y0, _GROUND_Z],
                          [x0 + _CELL, y0 + _CELL, _GROUND_Z], [x0, y0 + _CELL, _GROUND_Z]])
            tiles.at("ground", x0 + 5, y0 + 5).poly(q, col, (0, 0, 1), sem.TERRAIN)
    road = np.asarray(style.road)
    for k, poly in enumerate(geo.road_polygons):
        poly = _check_poly(poly, f"road_polygons[{k}]", geo.name)
        for piece in clip_to_cells(poly, _CELL):
            col = np.clip(road * (1.0 + rng.uniform(-0.03, 0.03)), 0, 1)
            c = piece.mean(0)
            tiles.at("road", c[0], c[1]).poly(np.column_stack([piece, np.full(len(piece), _ROAD_Z)]), col, (0, 0, 1),
                                              sem.ROAD)
    walk = np.asarray(style.sidewalk)
    for k, poly in enumerate(geo.sidewalk_polygons):
        poly = _check_poly(poly, f"sidewalk_polygons[{k}]", geo.name)
        for piece in clip_to_cells(poly, _CELL):
            c = piece.mean(0)
            tiles.at("static", c[0], c[1]).poly(np.column_stack([piece, np.full(len(piece), _SIDEWALK_H)]), walk,
                                                (0, 0, 1), sem.SIDEWALK)
        sign = 1.0 if _signed_area(poly) > 0 else -1.0
        for i in range(len(poly)):
            a, b = poly[i], poly[(i + 1) % len(poly)]
            n = sign * np.array([b[1] - a[1], a[0] - b[0]])
            n /= np.linalg.norm(n) or 1.0
            q = np.array([[a[0], a[1], _ROAD_Z], [b[0], b[1], _ROAD_Z], [b[0], b[1], _SIDEWALK_H], [a[0], a[1], _SIDEWALK_H]])
            c = (a + b) / 2
            tiles.at("static", c[0], c[1]).poly(q, walk * 0.8, (n[0], n[1], 0), sem.SIDEWALK)
    for k, m in enumerate(geo.markings):
        _add_marking(tiles, m, f"markings[{k}]", geo.name)
    for b in geo.buildings:
        _check_box(b, geo.name)
        window = tuple(0.3 * np.asarray(b.color) + np.array([0.05, 0.06, 0.09]))
        tiles.at("near", b.x, b.y).box(b.x, b.y, b.z, b.yaw, b.length, b.width, b.height, b.color, window_color=window,
                                       label=sem.BUILDING)
        tiles.at("far", b.x, b.y).box(b.x, b.y, b.z, b.yaw, b.length, b.width, b.height, b.color, label=sem.BUILDING)
    for p in geo.props:
        _check_box(p, geo.name)
        mesh = tiles.at("static", p.x, p.y)
        if p.kind == "tree":
            trunk = min(0.3, p.width * 0.2)
            mesh.box(p.x, p.y, p.z, p.yaw, trunk, trunk, p.height * 0.4, (0.35, 0.25, 0.15), label=sem.VEGETATION)
            mesh.box(p.x, p.y, p.z + p.height * 0.4, p.yaw, p.length, p.width, p.height * 0.6, p.color,
                     label=sem.VEGETATION)
        else:
            mesh.box(p.x, p.y, p.z, p.yaw, p.length, p.width, p.height, p.color, label=prop_class(p.kind))
    for lp in geo.light_posts:
        mesh = tiles.at("static", lp.x, lp.y)
        mesh.box(lp.x, lp.y, 0.0, lp.yaw, 0.16, 0.16, _POLE_H, (0.22, 0.22, 0.24), label=sem.POLE)
        hx, hy = _head_centre(lp)
        mesh.box(hx, hy, _HEAD_BOTTOM, lp.yaw + math.pi, _HEAD_D, _HEAD_W, _HEAD_H, (0.1, 0.1, 0.1), skip_front=True,
                 label=sem.TRAFFIC_LIGHT)


def prop_class(kind: str) -> int:
    """The semantic class of a prop by its `Box.kind` (trees are drawn, and labelled, apart)."""
    return {"pole": sem.POLE, "tree": sem.VEGETATION}.get(kind, sem.STATIC)


def build_lamps(geo: TownGeometry, tiles: Tiles) -> dict[int, tuple[tuple[int, int], int]]:
    """The heads' front faces, three cells each (green, yellow, red from the bottom); returns for each
    light id its tile and first vertex row, so that a state change rewrites 12 vertex colours."""
    rows: dict[int, tuple[tuple[int, int], int]] = {}
    for lp in geo.light_posts:
        if lp.id in rows:
            raise ValueError(f"TownGeometry {geo.name!r}: duplicate light post id {lp.id}")
        if not all(math.isfinite(v) for v in (lp.x, lp.y, lp.yaw)):
            raise ValueError(f"TownGeometry {geo.name!r}: light post {lp} needs a finite position and yaw")
        c, s = math.cos(lp.yaw), math.sin(lp.yaw)
        hx, hy = _head_centre(lp)
        fx, fy = hx - c * _HEAD_D / 2, hy - s * _HEAD_D / 2  # front face centre
        lx, ly = -s * _HEAD_W / 2, c * _HEAD_W / 2
        mesh = tiles.at("lamps", lp.x, lp.y)
        rows[lp.id] = (tiles.key(lp.x, lp.y), mesh.count)
        cell = _HEAD_H / 3
        colors = lamp_colors("off")
        for i in range(3):
            z0, z1 = _HEAD_BOTTOM + i * cell, _HEAD_BOTTOM + (i + 1) * cell
            q = np.array([[fx + lx, fy + ly, z0], [fx - lx, fy - ly, z0], [fx - lx, fy - ly, z1], [fx + lx, fy + ly, z1]])
            mesh.poly(q, colors[4 * i], (-c, -s, 0), sem.TRAFFIC_LIGHT)
    return rows


def lamp_colors(state: str) -> np.ndarray:
    """(12, 3) vertex colours of a head's three cells: the lit lamp bright, the others dark."""
    out = np.zeros((12, 3), np.float32)
    for i, name in enumerate(("green", "yellow", "red")):
        col = _LAMP[name] if name == state else tuple(0.12 * v + 0.04 for v in _LAMP[name])
        out[4 * i: 4 * i + 4] = col
    return out


def _signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _check_poly(poly: np.ndarray, field: str, town: str) -> np.ndarray:
    p = np.asarray(poly, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"TownGeometry {town!r}: {field} must be a finite (M>=3, 2) polygon, got shape {p.shape}")
    return p


def _check_box(b: Box, town: str) -> None:
    vals = (b.x, b.y, b.yaw, b.length, b.width, b.height, b.z)
    ok = all(isinstance(v, (int, float, np.number)) and math.isfinite(v) for v in vals) and len(b.color) == 3
    if not ok or min(b.length, b.width, b.height) <= 0:
        raise ValueError(f"TownGeometry {town!r}: box {b} needs finite values and positive sizes")


def _head_centre(lp: LightPost) -> tuple[float, float]:
    """The head sits on the pole, its lamps toward the traffic it governs (the -yaw side)."""
    return lp.x - math.cos(lp.yaw) * _HEAD_D / 2, lp.y - math.sin(lp.yaw) * _HEAD_D / 2


def _add_marking(tiles: Tiles, m: Marking, field: str, town: str) -> None:
    """Thin quads along the polyline, `width` wide: solid, or dashed (3 m on, 3 m off).

    Every kind is painted the same way: a crosswalk is one Marking per stripe, a stop line one Marking.
    """
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2 or not np.all(np.isfinite(pts)):
        raise ValueError(f"TownGeometry {town!r}: {field}.points must be a finite (N>=2, 2) polyline, got shape {pts.shape}")
    if m.width <= 0:
        raise ValueError(f"TownGeometry {town!r}: {field}.width must be positive, got {m.width}")
    label = sem.CROSSWALK if m.kind == "crosswalk" else sem.LANE_MARKING
    seg = np.diff(pts, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    total = float(cum[-1])
    if m.dashed:
        spans = [(s, min(s + _DASH, total), m.width) for s in np.arange(0.0, total, _DASH + _GAP)]
    else:
        n = max(1, math.ceil(total / _CELL))
        spans = [(total * i / n, total * (i + 1) / n, m.width) for i in range(n)]
    for s0, s1, w in spans:
        if s1 <= s0:
            continue
        # walk the polyline between arc lengths s0 and s1, one quad per polyline segment touched
        for k in range(len(seg)):
            a0, a1 = max(s0, cum[k]), min(s1, cum[k + 1])
            if a1 <= a0 or lengths[k] <= 0:
                continue
            d = seg[k] / lengths[k]
            p0, p1 = pts[k] + d * (a0 - cum[k]), pts[k] + d * (a1 - cum[k])
            nrm = np.array([-d[1], d[0]]) * (w / 2)
            q2 = np.array([p0 - nrm, p1 - nrm, p1 + nrm, p0 + nrm])
            c = q2.mean(0)
            tiles.at("marking", c[0], c[1]).poly(np.column_stack([q2, np.full(4, _MARK_Z)]), m.color, (0, 0, 1), label)


def build_puddles(geo: TownGeometry, tiles: Tiles, rng: np.random.Generator) -> None:
    """Elliptic patches on the roads, shown by weather; bright centre, dim rim (a sky reflection)."""
    k = 0
    for poly in geo.road_polygons:
        p = np.asarray(poly, dtype=np.float64)
        lo, hi = p.min(0), p.max(0)
        for _ in range(int(rng.poisson(_area(p) / 35.0))):
            c = rng.uniform(lo, hi)
            if not _inside_convex(p, c):
                continue
            a, b, th = rng.uniform(0.6, 2.2), rng.uniform(0.4, 1.2), rng.uniform(0, math.pi)
            t = np.linspace(0, 2 * math.pi, 11)[:-1]
            ex, ey = a * np.cos(t), b * np.sin(t)
            rim = np.column_stack([c[0] + ex * math.cos(th) - ey * math.sin(th),
                                   c[1] + ex * math.sin(th) + ey * math.cos(th), np.full(10, _PUDDLE_Z)])
            centre = np.array([c[0], c[1], _PUDDLE_Z])
            mesh = tiles.at(f"puddle{k % PUDDLE_GROUPS}", c[0], c[1])
            shine = rng.uniform(0.85, 1.0)
            for i in range(10):
                tri = np.array([centre, rim[i], rim[(i + 1) % 10]])
                mesh.poly(tri, np.array([[shine] * 3, [0.55] * 3, [0.55] * 3]), (0, 0, 1), sem.ROAD)
            k += 1

