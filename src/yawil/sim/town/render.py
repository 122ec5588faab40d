"""The embedded simulator's forward camera: Panda3D offscreen, 200x88 RGB, CIL's crop rendered directly.

The camera is the benchmark's 800x600, FOV 100 camera at (2.0, 0, 1.4) m in the vehicle frame, of which
rows 115..509 are kept and resized to 200x88. We render only that window, with an off-centre lens that
has the same projection (docs/rendering.md derives it; `reference_projection` is the 800x600 + crop +
resize pipeline in numpy, against which the tests check the lens). Static geometry is baked once per town
into one Geom per (layer, tile); actors come from a pool of reusable nodes; weather sets the lights, the
sky, the wet road and puddles, and numpy adds haze and rain streaks after the render.

Panda3D allows one ShowBase per process, so we use a module-level GraphicsEngine and one offscreen buffer
per renderer; a renderer's buffer is active only while it renders, so several renderers may coexist.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from yawil.sim.town.geometry import ActorView, Box, LightPost, Marking, TownGeometry
from yawil.sim.types import Pose
from yawil.sim.weather import Weather, get_weather

BACKENDS: dict[str, str] = {"software": "p3tinydisplay", "opengl": "p3headlessgl"}
LIGHT_STATES: tuple[str, ...] = ("red", "yellow", "green", "off")

_GROUND_Z, _ROAD_Z, _PUDDLE_Z, _MARK_Z, _SIDEWALK_H = -0.03, 0.0, 0.01, 0.02, 0.15
_CELL = 10.0  # tinydisplay mis-handles large triangles: flat surfaces are cut into cells of this size
_DASH, _GAP = 3.0, 3.0  # dashed markings (m)
_PUDDLE_GROUPS = 4
_SKIN = (0.86, 0.68, 0.56)
_WINDOW = (0.16, 0.18, 0.22)
_LAMP = {"red": (1.0, 0.12, 0.08), "yellow": (1.0, 0.8, 0.1), "green": (0.15, 1.0, 0.35)}
_HEAD_BOTTOM, _HEAD_H, _HEAD_W, _HEAD_D, _POLE_H = 2.6, 1.1, 0.5, 0.35, 3.75


@dataclass(frozen=True)
class CameraConfig:
    """The camera of the benchmark protocol, and how much of the town is drawn."""

    width: int = 200
    height: int = 88
    full_width: int = 800
    full_height: int = 600
    fov_deg: float = 100.0  # horizontal, of the full image
    mount: tuple[float, float, float] = (2.0, 0.0, 1.4)  # vehicle frame: x forward, y left, z up
    crop_top: int = 115  # rows [crop_top, crop_bottom) of the full image are kept
    crop_bottom: int = 510
    near: float = 0.3
    far: float = 120.0
    tile_size: float = 40.0  # static geometry is grouped in tiles this big for frustum culling
    lod_distance: float = 70.0  # buildings of tiles farther than this are drawn without window bands
    haze_ceiling: float = 6.0  # assumed height of what is seen above the horizon (haze approximation)
    haze_max_depth: float = 60.0  # cap of that depth estimate, so the horizon rows do not fog near walls

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.full_width <= 0 or self.full_height <= 0:
            raise ValueError(f"CameraConfig sizes must be positive, got {self}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"CameraConfig.fov_deg={self.fov_deg} must be in (0, 180)")
        if not 0 <= self.crop_top < self.crop_bottom <= self.full_height:
            raise ValueError(
                f"CameraConfig crop rows [{self.crop_top}, {self.crop_bottom}) must lie in [0, {self.full_height}]"
            )
        if not 0.0 < self.near < self.far:
            raise ValueError(f"CameraConfig needs 0 < near < far, got near={self.near} far={self.far}")
        if self.tile_size < 0.0 or self.haze_ceiling <= self.mount[2]:
            raise ValueError("CameraConfig.tile_size must be >= 0 and haze_ceiling above the camera height")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels of the full image."""
        return self.full_width / 2.0 / math.tan(math.radians(self.fov_deg) / 2.0)

    @property
    def film_offset_px(self) -> float:
        """Vertical offset (up positive) of the crop window's centre from the principal point."""
        return self.full_height / 2.0 - (self.crop_top + self.crop_bottom) / 2.0


def camera_pose(ego: Pose, config: CameraConfig = CameraConfig()) -> tuple[float, float, float, float]:
    """World position (x, y, z) and yaw of the camera mounted on `ego`."""
    mx, my, mz = config.mount
    c, s = math.cos(ego.yaw), math.sin(ego.yaw)
    return ego.x + c * mx - s * my, ego.y + s * mx + c * my, mz, ego.yaw


def reference_projection(ego: Pose, points: np.ndarray, config: CameraConfig = CameraConfig()) -> np.ndarray:
    """Where world points land in the 200x88 image by the protocol's own pipeline.

    Pinhole projection into the full 800x600 image, crop of rows [crop_top, crop_bottom), resize of the
    window to width x height (pixel-centre convention of PIL/OpenCV: continuous coordinates scale). Returns
    (N, 2) continuous (column, row); NaN for points behind the camera.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cx, cy, cz, yaw = camera_pose(ego, config)
    dx, dy, dz = pts[:, 0] - cx, pts[:, 1] - cy, pts[:, 2] - cz
    fwd = dx * math.cos(yaw) + dy * math.sin(yaw)
    left = -dx * math.sin(yaw) + dy * math.cos(yaw)
    f = config.focal_px
    with np.errstate(divide="ignore", invalid="ignore"):
        u = config.full_width / 2.0 - f * left / fwd
        v = config.full_height / 2.0 - f * dz / fwd
    col = u * config.width / config.full_width
    row = (v - config.crop_top) * config.height / (config.crop_bottom - config.crop_top)
    out = np.stack([col, row], axis=1)
    out[fwd <= 0.0] = np.nan
    return out


# ----------------------------------------------------------------------------------------------- meshes
class _Mesh:
    """Indexed triangles with per-vertex normal and colour, built with numpy, baked into one Geom."""

    def __init__(self) -> None:
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.col: list[np.ndarray] = []
        self.idx: list[np.ndarray] = []
        self.count = 0

    def __len__(self) -> int:
        return self.count

    def poly(self, pts: np.ndarray, color: Sequence[float] | np.ndarray, normal: Sequence[float]) -> None:
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
        self.count += m

    def box(self, x: float, y: float, z: float, yaw: float, length: float, width: float, height: float,
            color: Sequence[float], skip_front: bool = False, window_color: Sequence[float] | None = None) -> None:
        """An oriented box; with `window_color` its sides get a darker band per floor."""
        c, s = math.cos(yaw), math.sin(yaw)
        fx, fy, lx, ly = c * length / 2, s * length / 2, -s * width / 2, c * width / 2
        base = np.array([[x + fx + lx, y + fy + ly], [x - fx + lx, y - fy + ly],
                         [x - fx - lx, y - fy - ly], [x + fx - lx, y + fy - ly]])
        top = z + height
        self.poly(np.column_stack([base, np.full(4, top)]), color, (0, 0, 1))
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
                self.poly(q, col, (nx / nn, ny / nn, 0.0))

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


def _clip_to_cells(poly: np.ndarray, cell: float) -> list[np.ndarray]:
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
class _Tiles:
    """Meshes keyed by (layer, tile) so that a tile out of view is culled as a whole."""

    def __init__(self, size: float) -> None:
        self.size = size
        self.meshes: dict[tuple[str, int, int], _Mesh] = {}

    def key(self, x: float, y: float) -> tuple[int, int]:
        return (0, 0) if self.size <= 0 else (int(x // self.size), int(y // self.size))

    def at(self, layer: str, x: float, y: float) -> _Mesh:
        return self.meshes.setdefault((layer, *self.key(x, y)), _Mesh())


def _build_static(geo: TownGeometry, tiles: _Tiles, rng: np.random.Generator) -> None:
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
            tiles.at("ground", x0 + 5, y0 + 5).poly(q, col, (0, 0, 1))
    road = np.asarray(style.road)
    for k, poly in enumerate(geo.road_polygons):
        poly = _check_poly(poly, f"road_polygons[{k}]", geo.name)
        for piece in _clip_to_cells(poly, _CELL):
            col = np.clip(road * (1.0 + rng.uniform(-0.03, 0.03)), 0, 1)
            c = piece.mean(0)
            tiles.at("road", c[0], c[1]).poly(np.column_stack([piece, np.full(len(piece), _ROAD_Z)]), col, (0, 0, 1))
    walk = np.asarray(style.sidewalk)
    for k, poly in enumerate(geo.sidewalk_polygons):
        poly = _check_poly(poly, f"sidewalk_polygons[{k}]", geo.name)
        for piece in _clip_to_cells(poly, _CELL):
            c = piece.mean(0)
            tiles.at("static", c[0], c[1]).poly(np.column_stack([piece, np.full(len(piece), _SIDEWALK_H)]), walk, (0, 0, 1))
        sign = 1.0 if _signed_area(poly) > 0 else -1.0
        for i in range(len(poly)):
            a, b = poly[i], poly[(i + 1) % len(poly)]
            n = sign * np.array([b[1] - a[1], a[0] - b[0]])
            n /= np.linalg.norm(n) or 1.0
            q = np.array([[a[0], a[1], _ROAD_Z], [b[0], b[1], _ROAD_Z], [b[0], b[1], _SIDEWALK_H], [a[0], a[1], _SIDEWALK_H]])
            c = (a + b) / 2
            tiles.at("static", c[0], c[1]).poly(q, walk * 0.8, (n[0], n[1], 0))
    for k, m in enumerate(geo.markings):
        _add_marking(tiles, m, f"markings[{k}]", geo.name)
    for b in geo.buildings:
        _check_box(b, geo.name)
        window = tuple(0.3 * np.asarray(b.color) + np.array([0.05, 0.06, 0.09]))
        tiles.at("near", b.x, b.y).box(b.x, b.y, b.z, b.yaw, b.length, b.width, b.height, b.color, window_color=window)
        tiles.at("far", b.x, b.y).box(b.x, b.y, b.z, b.yaw, b.length, b.width, b.height, b.color)
    for p in geo.props:
        _check_box(p, geo.name)
        mesh = tiles.at("static", p.x, p.y)
        if p.kind == "tree":
            trunk = min(0.3, p.width * 0.2)
            mesh.box(p.x, p.y, p.z, p.yaw, trunk, trunk, p.height * 0.4, (0.35, 0.25, 0.15))
            mesh.box(p.x, p.y, p.z + p.height * 0.4, p.yaw, p.length, p.width, p.height * 0.6, p.color)
        else:
            mesh.box(p.x, p.y, p.z, p.yaw, p.length, p.width, p.height, p.color)
    for lp in geo.light_posts:
        mesh = tiles.at("static", lp.x, lp.y)
        mesh.box(lp.x, lp.y, 0.0, lp.yaw, 0.16, 0.16, _POLE_H, (0.22, 0.22, 0.24))
        hx, hy = _head_centre(lp)
        mesh.box(hx, hy, _HEAD_BOTTOM, lp.yaw + math.pi, _HEAD_D, _HEAD_W, _HEAD_H, (0.1, 0.1, 0.1), skip_front=True)


def _build_lamps(geo: TownGeometry, tiles: _Tiles) -> dict[int, tuple[tuple[int, int], int]]:
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
        colors = _lamp_colors("off")
        for i in range(3):
            z0, z1 = _HEAD_BOTTOM + i * cell, _HEAD_BOTTOM + (i + 1) * cell
            q = np.array([[fx + lx, fy + ly, z0], [fx - lx, fy - ly, z0], [fx - lx, fy - ly, z1], [fx + lx, fy + ly, z1]])
            mesh.poly(q, colors[4 * i], (-c, -s, 0))
    return rows


def _lamp_colors(state: str) -> np.ndarray:
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


def _add_marking(tiles: _Tiles, m: Marking, field: str, town: str) -> None:
    """Thin quads along the polyline, `width` wide: solid, or dashed (3 m on, 3 m off).

    Every kind is painted the same way: a crosswalk is one Marking per stripe, a stop line one Marking.
    """
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2 or not np.all(np.isfinite(pts)):
        raise ValueError(f"TownGeometry {town!r}: {field}.points must be a finite (N>=2, 2) polyline, got shape {pts.shape}")
    if m.width <= 0:
        raise ValueError(f"TownGeometry {town!r}: {field}.width must be positive, got {m.width}")
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
            tiles.at("marking", c[0], c[1]).poly(np.column_stack([q2, np.full(4, _MARK_Z)]), m.color, (0, 0, 1))


def _build_puddles(geo: TownGeometry, tiles: _Tiles, rng: np.random.Generator) -> None:
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
            mesh = tiles.at(f"puddle{k % _PUDDLE_GROUPS}", c[0], c[1])
            shine = rng.uniform(0.85, 1.0)
            for i in range(10):
                tri = np.array([centre, rim[i], rim[(i + 1) % 10]])
                mesh.poly(tri, np.array([[shine] * 3, [0.55] * 3, [0.55] * 3]), (0, 0, 1))
            k += 1


_ACTOR_KINDS = ("vehicle", "pedestrian")


class _Slot:
    """A reusable actor node: a pose node over the shape's paint (colour-scaled) and fixed parts."""

    def __init__(self, parent: Any, index: int) -> None:
        self.node = parent.attachNewNode(f"actor{index}")
        self.paint = self.node.attachNewNode("paint")
        self.fixed = self.node.attachNewNode("fixed")
        self.key: tuple[str, float, float, float] | None = None
        self.color: tuple[float, ...] | None = None
        self.actor: int | None = None
        self.node.stash()

    def update(self, a: ActorView, renderer: CameraRenderer) -> None:
        key = (a.kind, round(a.length, 2), round(a.width, 2), round(a.height, 2))
        if key != self.key:
            paint, fixed = renderer._shape(key)
            self.paint.node().removeAllChildren()
            self.fixed.node().removeAllChildren()
            self.paint.node().addChild(paint)
            self.fixed.node().addChild(fixed)
            self.key = key
        if a.color != self.color:
            self.paint.setColorScale(a.color[0], a.color[1], a.color[2], 1.0)
            self.color = a.color
        self.node.setPosHpr(a.x, a.y, 0.0, math.degrees(a.yaw), 0.0, 0.0)
        if self.node.isStashed():
            self.node.unstash()

    def release(self) -> None:
        self.actor = None
        self.node.stash()


def _actor_shape(kind: str, length: float, width: float, height: float) -> tuple[Any, Any]:
    """(paint, fixed) GeomNodes of an actor in its own frame (x forward); paint takes the actor colour."""
    paint, fixed = _Mesh(), _Mesh()
    if kind == "vehicle":
        body_h = height * 0.55
        paint.box(0, 0, 0.25, 0, length, width, body_h - 0.25, (1, 1, 1))
        cab_l, cab_w = length * 0.5, width * 0.9
        fixed.box(-length * 0.05, 0, body_h, 0, cab_l, cab_w, height - body_h - 0.05, _WINDOW)
        paint.box(-length * 0.05, 0, height - 0.05, 0, cab_l, cab_w, 0.05, (1, 1, 1))
        for sx in (length * 0.32, -length * 0.32):
            for sy in (width * 0.42, -width * 0.42):
                fixed.box(sx, sy, 0.0, 0, 0.6, 0.22, 0.5, (0.05, 0.05, 0.05))
        for sy in (width * 0.32, -width * 0.32):  # head lamps and tail lamps tell front from back
            fixed.box(length / 2 - 0.02, sy, body_h - 0.35, 0, 0.06, 0.3, 0.15, (0.95, 0.95, 0.8))
            fixed.box(-length / 2 + 0.02, sy, body_h - 0.35, 0, 0.06, 0.3, 0.15, (0.8, 0.05, 0.05))
    elif kind == "pedestrian":
        head = min(0.25, height * 0.14)
        leg = (height - head) * 0.48
        paint.box(0, width * 0.22, 0, 0, length * 0.6, width * 0.4, leg, (0.55, 0.55, 0.6))
        paint.box(0, -width * 0.22, 0, 0, length * 0.6, width * 0.4, leg, (0.55, 0.55, 0.6))
        paint.box(0, 0, leg, 0, length, width, height - head - leg, (1, 1, 1))
        fixed.box(0, 0, height - head, 0, head * 0.9, head * 0.8, head, _SKIN)
    else:
        raise ValueError(f"ActorView.kind must be 'vehicle' or 'pedestrian', got {kind!r}")
    return paint.geom_node("paint"), fixed.geom_node("fixed")


# ------------------------------------------------------------------------------------ engine and pipes
_STATE: dict[str, Any] = {}


def _engine() -> Any:
    """The process's one GraphicsEngine, configured once for headless offscreen work."""
    if "engine" not in _STATE:
        from panda3d.core import GraphicsEngine, loadPrcFileData

        loadPrcFileData("yawil-render", "\n".join([
            "window-type offscreen", "load-display none", "aux-display none", "audio-library-name null",
            "sync-video false", "notify-level warning", "notify-level-display fatal",
            "notify-level-x11display fatal", "notify-level-egldisplay fatal", "notify-level-glgsg fatal",
            "framebuffer-srgb false", "textures-power-2 none",
        ]))
        _STATE["engine"] = GraphicsEngine.getGlobalPtr()
    return _STATE["engine"]


def _pipe(backend: str) -> Any:
    if backend not in BACKENDS:
        raise ValueError(f"unknown render backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    key = f"pipe:{backend}"
    if key not in _STATE:
        from panda3d.core import GraphicsPipeSelection

        _engine()
        pipe = GraphicsPipeSelection.getGlobalPtr().makeModulePipe(BACKENDS[backend])
        if pipe is None:
            raise RuntimeError(f"render backend {backend!r}: Panda3D module {BACKENDS[backend]} is not usable here")
        _STATE[key] = pipe
    return _STATE[key]


def _cull_bins() -> None:
    """Flat layers first in a fixed order without depth test (ground < road < puddles < markings: they
    cannot hide one another), then everything else in scene-graph order. No state-sorted bin is used:
    its order among equal states depends on memory addresses, and shared tile edges would then differ
    between two renderers of the same town."""
    if "bins" not in _STATE:
        from panda3d.core import CullBinManager

        CullBinManager.getGlobalPtr().addBin("flat", CullBinManager.BTFixed, 15)
        CullBinManager.getGlobalPtr().addBin("solid", CullBinManager.BTUnsorted, 16)
        _STATE["bins"] = True


# ------------------------------------------------------------------------------------------- renderer
class CameraRenderer:
    """Forward camera of one town. Same inputs give the same image, bit for bit."""

    def __init__(self, geometry: TownGeometry, backend: str = "software", config: CameraConfig = CameraConfig()) -> None:
        from panda3d.core import (
            AmbientLight,
            Camera,
            DirectionalLight,
            FrameBufferProperties,
            GraphicsOutput,
            GraphicsPipe,
            Material,
            NodePath,
            PerspectiveLens,
            Texture,
            WindowProperties,
        )

        self.geometry, self.backend, self.config = geometry, backend, config
        self._closed = True
        engine, pipe = _engine(), _pipe(backend)
        rng = np.random.default_rng(zlib.crc32(geometry.name.encode()))
        tiles = _Tiles(config.tile_size)
        _build_static(geometry, tiles, rng)  # validates the geometry before any buffer is opened
        self._lamp_rows = _build_lamps(geometry, tiles)
        _build_puddles(geometry, tiles, rng)

        fb = FrameBufferProperties()
        fb.setRgbColor(True)
        fb.setColorBits(24)
        fb.setDepthBits(24)
        self._buf = engine.makeOutput(pipe, f"yawil-{geometry.name}", 0, fb,
                                      WindowProperties.size(config.width, config.height), GraphicsPipe.BFRefuseWindow)
        if self._buf is None:
            raise RuntimeError(f"render backend {backend!r}: could not open a {config.width}x{config.height} offscreen buffer")
        self._closed = False
        self._tex = Texture("frame")
        self._buf.addRenderTexture(self._tex, GraphicsOutput.RTMCopyRam, GraphicsOutput.RTPColor)
        self._buf.setClearColor((0, 0, 0, 1))
        self._buf.setActive(False)

        self.root = NodePath(f"town-{geometry.name}")
        lens = PerspectiveLens()
        lens.setFilmSize(config.full_width, config.crop_bottom - config.crop_top)
        lens.setFocalLength(config.focal_px)
        lens.setFilmOffset(0.0, config.film_offset_px)
        lens.setNearFar(config.near, config.far)
        self._lens = lens
        self._cam = self.root.attachNewNode(Camera("camera", lens))
        self._buf.makeDisplayRegion().setCamera(self._cam)
        self._build_nodes(tiles)

        self._sun = self.root.attachNewNode(DirectionalLight("sun"))
        self._amb = self.root.attachNewNode(AmbientLight("ambient"))
        self.root.setLight(self._sun)
        self.root.setLight(self._amb)
        if backend == "software":
            # tinydisplay multiplies a lit vertex colour in twice unless a white material is set; OpenGL
            # does it right without one and, with one, ignores vertex colours altogether
            white = Material("white")
            white.setAmbient((1, 1, 1, 1))
            white.setDiffuse((1, 1, 1, 1))
            self.root.setMaterial(white)
        self._sky: Any = None
        self._weather: Weather | None = None
        self._haze = np.zeros((config.height, 1, 1), np.float32)
        self._haze_color = np.zeros(3, np.float32)
        self._rain_layers: list[tuple[np.ndarray, np.ndarray]] = []
        self._lamp_state = {lid: "off" for lid in self._lamp_rows}

        self._actors_root = self.root.attachNewNode("actors")
        self._actors_root.setBin("solid", 0)
        self._shapes: dict[tuple[str, float, float, float], tuple[Any, Any]] = {}
        self._slots: list[_Slot] = []
        self._slot_of: dict[int, _Slot] = {}

    def _build_nodes(self, tiles: _Tiles) -> None:
        """Static and flat-road tiles under 4x4-tile groups, so culling prunes whole groups at once."""
        from panda3d.core import CullBinAttrib, DepthTestAttrib, GeomNode, LightAttrib, RenderState

        _cull_bins()
        solid = CullBinAttrib.make("solid", 0)
        no_test = DepthTestAttrib.make(DepthTestAttrib.MNone)
        states = {
            "static": RenderState.make(solid), "lamps": RenderState.make(solid, LightAttrib.makeAllOff()),
            "ground": RenderState.make(CullBinAttrib.make("flat", 0), no_test),
            "road": RenderState.make(CullBinAttrib.make("flat", 1), no_test),
            "marking": RenderState.make(CullBinAttrib.make("flat", 3), no_test),
        }
        self._puddle_state = RenderState.make(CullBinAttrib.make("flat", 2), no_test, LightAttrib.makeAllOff())
        self._static_root = self.root.attachNewNode("static")
        self._road_root = self.root.attachNewNode("road")  # the wet colour scale applies to roads and paint
        self._static_root.setLightOff(1)  # lit once per weather by _bake_light
        self._road_root.setLightOff(1)
        self._baked: list[tuple[Any, int, np.ndarray, np.ndarray]] = []
        groups: dict[tuple[str, int, int], Any] = {}
        self._tile_nodes: dict[tuple[str, int, int], Any] = {}
        self._lamp_geoms: dict[tuple[int, int], Any] = {}
        self._puddle_meshes: dict[tuple[int, int], list[_Mesh]] = {}
        keys = sorted({(i, j) for (_, i, j) in tiles.meshes})
        for i, j in keys:
            for part, layers in (("static", ("ground", "static", "lamps")), ("road", ("road", "marking"))):
                meshes = [(layer, tiles.meshes[(layer, i, j)]) for layer in layers
                          if (layer, i, j) in tiles.meshes and len(tiles.meshes[(layer, i, j)])]
                if not meshes and part == "static":
                    continue
                node = GeomNode(f"{part}-{i}-{j}")
                for layer, mesh in meshes:
                    self._add_geom(node, mesh, layer, states[layer])
                    if layer == "lamps":
                        self._lamp_geoms[(i, j)] = (node, node.getNumGeoms() - 1)
                gkey = (part, i // 4, j // 4)
                if gkey not in groups:
                    root = self._static_root if part == "static" else self._road_root
                    groups[gkey] = root.attachNewNode(f"{part}-group-{i // 4}-{j // 4}")
                self._tile_nodes[(part, i, j)] = groups[gkey].attachNewNode(node)
                if part == "static" and ("near", i, j) in tiles.meshes:
                    self._add_lod(self._tile_nodes[(part, i, j)], tiles, i, j, states["static"])
            pud = [tiles.meshes.get((f"puddle{g}", i, j)) for g in range(_PUDDLE_GROUPS)]
            if any(m is not None and len(m) for m in pud):
                self._puddle_meshes[(i, j)] = [m if m is not None else _Mesh() for m in pud]
        self._puddle_geom: dict[tuple[int, int], int] = {}

    def _add_geom(self, node: Any, mesh: _Mesh, layer: str, state: Any) -> None:
        """Add a tile's Geom; lit layers keep their base colours and normals for `_bake_light`."""
        node.addGeom(mesh.geom(layer), state)
        if layer != "lamps":
            col = np.concatenate(mesh.col)[:, :3].copy()
            self._baked.append((node, node.getNumGeoms() - 1, col, np.concatenate(mesh.nrm).astype(np.float32)))

    def _bake_light(self, w: Weather, sun_color: np.ndarray, to_sun: np.ndarray) -> None:
        """Write each static vertex's lit colour (ambient + sun * max(0, n.l), Panda's own formula).

        Static geometry is drawn unlit: lighting it once per weather instead of per frame saves a fifth
        of the frame in the software renderer. Actors are lit by Panda3D's lights as usual.
        """
        amb = np.asarray(w.ambient, np.float32)
        for node, gi, base, normals in self._baked:
            light = amb + np.maximum(normals @ to_sun, 0.0)[:, None] * sun_color
            vdata = node.modifyGeom(gi).modifyVertexData()
            arr = np.frombuffer(memoryview(vdata.modifyArray(0)).cast("B"), np.float32).reshape(-1, 10)
            arr[:, 6:9] = np.minimum(base * light, 1.0)

    def _add_lod(self, parent: Any, tiles: _Tiles, i: int, j: int, state: Any) -> None:
        """Buildings with window bands near the camera, plain boxes (a fifth of the vertices) beyond."""
        from panda3d.core import GeomNode, LODNode, Point3

        lod = LODNode(f"buildings-{i}-{j}")
        size = self.config.tile_size
        lod.setCenter(Point3((i + 0.5) * size, (j + 0.5) * size, 0.0) if size > 0 else Point3(0, 0, 0))
        for layer, near, far in (("near", self.config.lod_distance, 0.0), ("far", 1e6, self.config.lod_distance)):
            node = GeomNode(f"{layer}-{i}-{j}")
            self._add_geom(node, tiles.meshes[(layer, i, j)], layer, state)
            lod.addChild(node)
            lod.addSwitch(near, far)
        parent.attachNewNode(lod)

    # ------------------------------------------------------------------------------------ per frame
    def render(self, ego: Pose, actors: Sequence[ActorView], light_states: Mapping[int, str],
               weather: str, frame: int) -> np.ndarray:
        """The (height, width, 3) uint8 RGB image seen from `ego`. `frame` seeds the rain streaks."""
        if self._closed:
            raise RuntimeError("CameraRenderer.render called after close()")
        if not all(math.isfinite(v) for v in (ego.x, ego.y, ego.yaw)):
            raise ValueError(f"render: ego pose must be finite, got {ego}")
        self._set_weather(weather)
        cam = camera_pose(ego, self.config)
        self._cam.setPosHpr(cam[0], cam[1], cam[2], math.degrees(cam[3]) - 90.0, 0.0, 0.0)
        self._set_lights(light_states)
        self._set_actors(actors, cam)
        self._buf.setActive(True)
        try:
            _engine().renderFrame()
        finally:
            self._buf.setActive(False)
        return self._post(self._grab(), int(frame))

    def _grab(self) -> np.ndarray:
        raw = np.frombuffer(self._tex.getRamImage(), np.uint8)
        comps = raw.size // (self.config.width * self.config.height)
        return raw.reshape(self.config.height, self.config.width, comps)[::-1, :, 2::-1]  # BGR(A), bottom-up

    def _post(self, img: np.ndarray, frame: int) -> np.ndarray:
        """Haze toward the horizon colour by approximate depth, then rain streaks."""
        out = img.astype(np.float32)
        out += (self._haze_color - out) * self._haze
        if self._rain_layers:
            k = len(self._rain_layers)
            rows, cols = self._rain_layers[frame % k]
            cols = (cols + (frame // k) * 53) % self.config.width
            out[rows, cols] += (_RAIN_COLOR - out[rows, cols]) * _RAIN_ALPHA
        return (out + 0.5).astype(np.uint8)

    def _set_lights(self, light_states: Mapping[int, str]) -> None:
        changed = []
        for lid, st in light_states.items():
            old = self._lamp_state.get(lid)
            if old is None:
                continue  # a light without a post in this geometry is not drawn
            if st != old:
                if st not in LIGHT_STATES:
                    raise ValueError(f"render: light {lid} state {st!r}; expected one of {', '.join(LIGHT_STATES)}")
                changed.append((lid, st))
        for lid, old in self._lamp_state.items():
            if old != "off" and lid not in light_states:
                changed.append((lid, "off"))
        for lid, st in changed:
            tile, row = self._lamp_rows[lid]
            node, gi = self._lamp_geoms[tile]
            vdata = node.modifyGeom(gi).modifyVertexData()
            arr = np.frombuffer(memoryview(vdata.modifyArray(0)).cast("B"), np.float32).reshape(-1, 10)
            arr[row: row + 12, 6:9] = _lamp_colors(st)
            self._lamp_state[lid] = st

    def _set_actors(self, actors: Sequence[ActorView], cam: tuple[float, float, float, float]) -> None:
        """Actors in view get a pool slot kept by id; the others' slots are stashed out of the scene."""
        cx, cy, _, yaw = cam
        c, s = math.cos(yaw), math.sin(yaw)
        half = self.config.full_width / 2 / self.config.focal_px
        seen: set[int] = set()
        for a in actors:
            if a.kind not in _ACTOR_KINDS or not (a.length > 0 and a.width > 0 and a.height > 0) or not (
                    math.isfinite(a.x) and math.isfinite(a.y) and math.isfinite(a.yaw)):
                raise ValueError(f"render: actor {a.id} needs kind in {_ACTOR_KINDS}, a finite pose and "
                                 f"positive sizes, got {a}")
            fwd = (a.x - cx) * c + (a.y - cy) * s
            lat = -(a.x - cx) * s + (a.y - cy) * c
            reach = max(a.length, a.width) / 2 + 0.5
            if fwd < -reach or fwd > self.config.far + reach or abs(lat) > fwd * half + reach:
                continue
            if a.id in seen:
                raise ValueError(f"render: actor id {a.id} appears twice")
            seen.add(a.id)
            slot = self._slot_of.get(a.id)
            if slot is None:
                slot = self._free_slot()
                self._slot_of[a.id] = slot
                slot.actor = a.id
            slot.update(a, self)
        for aid in [aid for aid in self._slot_of if aid not in seen]:
            self._slot_of.pop(aid).release()

    def _free_slot(self) -> _Slot:
        for slot in self._slots:
            if slot.actor is None:
                return slot
        slot = _Slot(self._actors_root, len(self._slots))
        self._slots.append(slot)
        return slot

    def _shape(self, key: tuple[str, float, float, float]) -> tuple[Any, Any]:
        if key not in self._shapes:
            self._shapes[key] = _actor_shape(*key)
        return self._shapes[key]

    def _set_weather(self, name: str) -> None:
        if self._weather is not None and self._weather.name == name:
            return
        w = get_weather(name)
        el, az = math.radians(w.sun_elevation_deg), math.radians(w.sun_azimuth_deg)
        light_dir = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        sun_color = np.asarray(w.sun_color, np.float32) * (1.0 - 0.45 * w.cloudiness)
        self._sun.node().setColor((*sun_color, 1.0))
        self._sun.lookAt(*light_dir)
        self._bake_light(w, sun_color, -light_dir.astype(np.float32))
        self._amb.node().setColor((*w.ambient, 1.0))
        wet = 1.0 - w.wetness * np.array([0.36, 0.34, 0.27])
        self._road_root.setColorScale(*wet, 1.0)
        self._set_puddles(w, wet)
        self._build_sky(w)
        self._haze, self._haze_color = _haze_map(w, self.config), np.asarray(w.sky_horizon, np.float32) * 255
        self._rain_layers = _rain_layers(w.rain, self.config.height, self.config.width)
        self._weather = w

    def _set_puddles(self, w: Weather, wet: np.ndarray) -> None:
        """Rebuild each tile's puddle Geom: the first ceil(puddles * groups) groups, tinted by the sky."""
        groups = math.ceil(w.puddles * _PUDDLE_GROUPS - 1e-9)
        tint = np.clip(0.35 * np.asarray(w.sky_horizon) + 0.45 * np.asarray(w.sky_top) + 0.05, 0, 1) / wet
        for tile, meshes in self._puddle_meshes.items():
            node = self._tile_nodes[("road", *tile)].node()
            if tile in self._puddle_geom:
                node.removeGeom(self._puddle_geom.pop(tile))
            merged = _Mesh()
            for m in meshes[:groups]:
                for pos, col in zip(m.pos, m.col, strict=True):
                    merged.poly(pos, col[:, :3] * tint, (0, 0, 1))
            if len(merged):
                node.addGeom(merged.geom("puddles"), self._puddle_state)
                self._puddle_geom[tile] = node.getNumGeoms() - 1

    def _build_sky(self, w: Weather) -> None:
        """A camera-fixed card: sky gradient with soft cloud blobs above the horizon, far ground below."""
        cfg = self.config
        if self._sky is not None:
            self._sky.removeNode()
        dist = cfg.far * 0.9
        half_w = dist * (cfg.full_width / 2 / cfg.focal_px) * 1.05
        top = dist * (cfg.film_offset_px + (cfg.crop_bottom - cfg.crop_top) / 2) / cfg.focal_px * 1.05
        bottom = dist * (cfg.film_offset_px - (cfg.crop_bottom - cfg.crop_top) / 2) / cfg.focal_px * 1.05
        el, sun = math.radians(w.sun_elevation_deg), np.asarray(w.sun_color)
        far_ground = np.clip(np.asarray(self.geometry.style.ground) * (np.asarray(w.ambient) + sun * max(0.0, math.sin(el))), 0, 1)
        rng = np.random.default_rng(zlib.crc32(w.name.encode()))
        nx, nz = 16, 8
        xs = np.linspace(-half_w, half_w, nx)
        zs = np.linspace(0.0, top, nz)
        cloud = np.clip(0.8 * np.asarray(w.sky_horizon) + 0.25, 0, 1)
        noise = rng.uniform(0, 1, (nz, nx)) * w.cloudiness
        mesh = _Mesh()
        col = np.zeros((nz, nx, 3))
        for j, z in enumerate(zs):
            t = (z / top) ** 0.7 if top > 0 else 0.0
            base = (1 - t) * np.asarray(w.sky_horizon) + t * np.asarray(w.sky_top)
            col[j] = base + (cloud - base) * noise[j][:, None] * (0.3 + 0.7 * (j > 0))
        for j in range(nz - 1):
            for i in range(nx - 1):
                q = np.array([[xs[i], dist, zs[j]], [xs[i + 1], dist, zs[j]], [xs[i + 1], dist, zs[j + 1]], [xs[i], dist, zs[j + 1]]])
                mesh.poly(q, np.array([col[j, i], col[j, i + 1], col[j + 1, i + 1], col[j + 1, i]]), (0, -1, 0))
        q = np.array([[-half_w, dist, bottom], [half_w, dist, bottom], [half_w, dist, 0.0], [-half_w, dist, 0.0]])
        mesh.poly(q, far_ground, (0, -1, 0))
        sky = self._cam.attachNewNode(mesh.geom_node("sky"))
        sky.setBin("background", 0)
        sky.setDepthWrite(False)
        sky.setDepthTest(False)
        sky.setLightOff(1)
        self._sky = sky

    def close(self) -> None:
        """Free the offscreen buffer and the scene; the renderer cannot be used afterwards."""
        if self._closed:
            return
        self._closed = True
        _engine().removeWindow(self._buf)
        self.root.removeNode()
        self._buf = None
        self._tex = None

    def __enter__(self) -> CameraRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _haze_map(w: Weather, cfg: CameraConfig) -> np.ndarray:
    """Per-row haze weight (height, 1, 1) from an approximate depth (docs/rendering.md).

    Below the horizon a pixel is taken to see the ground: depth = f * cam_height / (v - v_horizon).
    Above it, a "ceiling" at `haze_ceiling` metres: depth = f * (ceiling - cam_height) / (v_horizon - v).
    Depth is capped at `haze_max_depth` (near the horizon the estimate grows without bound, while what
    is seen there is often a wall 20 m away). Weight = haze_max * (1 - exp(-depth / visibility)),
    visibility = 60 m / haze.
    """
    if w.haze <= 0.0:
        return np.zeros((cfg.height, 1, 1), np.float32)
    rows = (np.arange(cfg.height) + 0.5) * (cfg.crop_bottom - cfg.crop_top) / cfg.height + cfg.crop_top
    dv = rows - cfg.full_height / 2.0
    h = cfg.mount[2]
    with np.errstate(divide="ignore"):
        depth = np.where(dv > 0, cfg.focal_px * h / np.abs(dv), cfg.focal_px * (cfg.haze_ceiling - h) / np.abs(dv))
    depth = np.minimum(depth, cfg.haze_max_depth)
    vis = 60.0 / w.haze
    alpha = min(1.0, 0.6 + 0.4 * w.haze) * (1.0 - np.exp(-depth / vis))
    return alpha.astype(np.float32).reshape(-1, 1, 1)


_RAIN_COLOR = np.array([205.0, 208.0, 215.0], np.float32)
_RAIN_LAYERS = 8
_RAIN_ALPHA = np.float32(0.35)


def _rain_layers(rain: float, h: int, w: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A few layers of slanted streaks as (rows, cols) pixel lists; frame k shows layer k % 8, shifted
    sideways by a multiple of 53 px. Precomputed per weather so that a frame blends only the streak
    pixels; each image is a function of `frame` alone."""
    n = int(round(rain * 0.05 * h * w))
    if n == 0:
        return []
    layers = []
    for k in range(_RAIN_LAYERS):
        rng = np.random.default_rng([0x5241494E, k])
        x0, y0, length = rng.uniform(0, w, n), rng.uniform(-6, h, n), rng.integers(3, 8, n)
        t = np.arange(7)
        ys = (y0[:, None] + t).astype(np.int64)
        xs = (x0[:, None] + 0.3 * t).astype(np.int64) % w
        ok = (t < length[:, None]) & (ys >= 0) & (ys < h)
        flat = np.unique(ys[ok] * w + xs[ok])  # a pixel hit by two streaks is blended once
        layers.append((flat // w, flat % w))
    return layers
