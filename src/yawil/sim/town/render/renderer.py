"""The embedded simulator's forward camera: Panda3D offscreen, 200x88 RGB, CIL's crop rendered directly.

This module holds the Panda3D side: the engine and pipes, the scene graph built from the static meshes of
`scene_mesh` (one Geom per (layer, tile)), a pool of reusable actor nodes, and per-weather lights, sky,
wet road and puddles; the camera model is in `camera` and the haze and rain in `weather_fx`. Panda3D allows
one ShowBase per process, so we use a module-level GraphicsEngine and one offscreen buffer per renderer; a
renderer's buffer is active only while it renders, so several renderers may coexist.

One file of ~510 lines on purpose: its parts share that module-level engine and the Panda3D state it
holds; the parts without Panda3D (camera, meshes, weather effects) are already the modules beside it.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from yawil.sim.town.map.geometry import ActorView, TownGeometry
from yawil.sim.town.render.camera import CameraConfig, camera_pose, sky_card_extent
from yawil.sim.town.render.scene_mesh import (
    PUDDLE_GROUPS,
    Mesh,
    Tiles,
    build_lamps,
    build_puddles,
    build_static,
    lamp_colors,
)
from yawil.sim.town.render.weather_fx import haze_map, post_effects, rain_layers
from yawil.sim.types import Pose
from yawil.sim.weather import Weather, get_weather

BACKENDS: dict[str, str] = {"software": "p3tinydisplay", "opengl": "p3headlessgl"}
SEMANTIC_TAG = "yawil-class"  # on each actor shape node, its kind: the semantic camera (`semantic`) colours by it
LIGHT_STATES: tuple[str, ...] = ("red", "yellow", "green", "off")

_SKIN = (0.86, 0.68, 0.56)
_WINDOW = (0.16, 0.18, 0.22)
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
    paint, fixed = Mesh(), Mesh()
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


def render_frame() -> None:
    """One frame of the process's engine (its active buffers), drawn from an empty transform cache.

    Why: Panda3D keeps the TransformStates that culling computes (a camera's inverse composed with each node's
    net transform) in a process-wide cache, and a newly computed matrix is replaced by a cached state equal to
    it within a tolerance (~1e-6 per entry). The sky card, a child of the camera, is drawn with such a
    near-identity matrix every frame; which earlier one it got depended on what the process had rendered
    before (earlier frames, episodes, renderers), and one sky pixel changed an episode's record (issue 38).
    Emptying the cache, and freeing the states only it held, before each frame makes an image depend on its
    own inputs alone; it costs ~0.01 ms.
    """
    from panda3d.core import TransformState

    TransformState.clearCache()
    while TransformState.garbageCollect():  # states the cache alone held (garbage-collect-states is on)
        pass
    _engine().renderFrame()


def changed_lights(drawn: Mapping[int, str], light_states: Mapping[int, str]) -> list[tuple[int, str]]:
    """(light id, new state) of the heads whose drawn state (`drawn`) differs from `light_states`; a light not
    listed is off, one without a post in this geometry is not drawn. Shared by the RGB and semantic passes."""
    changed = []
    for lid, st in light_states.items():
        old = drawn.get(lid)
        if old is None:
            continue
        if st != old:
            if st not in LIGHT_STATES:
                raise ValueError(f"render: light {lid} state {st!r}; expected one of {', '.join(LIGHT_STATES)}")
            changed.append((lid, st))
    changed += [(lid, "off") for lid, old in drawn.items() if old != "off" and lid not in light_states]
    return changed


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
        tiles = Tiles(config.tile_size)
        build_static(geometry, tiles, rng)  # validates the geometry before any buffer is opened
        self._lamp_rows = build_lamps(geometry, tiles)
        build_puddles(geometry, tiles, rng)

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
        self._semantic: Any = None  # the semantic camera's scene, built on the first render_semantic

    def _build_nodes(self, tiles: Tiles) -> None:
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
        self._puddle_meshes: dict[tuple[int, int], list[Mesh]] = {}
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
            pud = [tiles.meshes.get((f"puddle{g}", i, j)) for g in range(PUDDLE_GROUPS)]
            if any(m is not None and len(m) for m in pud):
                self._puddle_meshes[(i, j)] = [m if m is not None else Mesh() for m in pud]
        self._puddle_geom: dict[tuple[int, int], int] = {}

    def _add_geom(self, node: Any, mesh: Mesh, layer: str, state: Any) -> None:
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

    def _add_lod(self, parent: Any, tiles: Tiles, i: int, j: int, state: Any) -> None:
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
            render_frame()
        finally:
            self._buf.setActive(False)
        return post_effects(self._grab(), self._haze, self._haze_color, self._rain_layers, int(frame))

    def render_semantic(self, ego: Pose, actors: Sequence[ActorView], light_states: Mapping[int, str]) -> np.ndarray:
        """The (height, width) uint8 class ids (`yawil.sim.semantic.CLASSES`) of what `render` shows from `ego`,
        pixel for pixel, whatever the weather. Its scene and buffer are built on the first call, so that a
        renderer never asked pays nothing; the RGB images are the same either way."""
        if self._closed:
            raise RuntimeError("CameraRenderer.render_semantic called after close()")
        if not all(math.isfinite(v) for v in (ego.x, ego.y, ego.yaw)):
            raise ValueError(f"render_semantic: ego pose must be finite, got {ego}")
        if self._semantic is None:
            from yawil.sim.town.render.semantic import SemanticPass

            self._semantic = SemanticPass(self)
        cam = camera_pose(ego, self.config)
        self._set_actors(actors, cam)
        ids: np.ndarray = self._semantic.render(cam, light_states)
        return ids

    def _grab(self) -> np.ndarray:
        raw = np.frombuffer(self._tex.getRamImage(), np.uint8)
        comps = raw.size // (self.config.width * self.config.height)
        return raw.reshape(self.config.height, self.config.width, comps)[::-1, :, 2::-1]  # BGR(A), bottom-up

    def _set_lights(self, light_states: Mapping[int, str]) -> None:
        for lid, st in changed_lights(self._lamp_state, light_states):
            tile, row = self._lamp_rows[lid]
            node, gi = self._lamp_geoms[tile]
            vdata = node.modifyGeom(gi).modifyVertexData()
            arr = np.frombuffer(memoryview(vdata.modifyArray(0)).cast("B"), np.float32).reshape(-1, 10)
            arr[row: row + 12, 6:9] = lamp_colors(st)
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

    def forget_actors(self) -> None:
        """A new episode: every actor slot free, so that actors take slots in the order this episode shows them,
        whatever earlier episodes left (an episode's images never depend on the renderer's history)."""
        for slot in self._slot_of.values():
            slot.release()
        self._slot_of.clear()

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
            for node in self._shapes[key]:  # the semantic camera's flat colour per kind (no effect on RGB)
                node.setTag(SEMANTIC_TAG, key[0])
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
        self._haze, self._haze_color = haze_map(w, self.config), np.asarray(w.sky_horizon, np.float32) * 255
        self._rain_layers = rain_layers(w.rain, self.config.height, self.config.width)
        self._weather = w

    def _set_puddles(self, w: Weather, wet: np.ndarray) -> None:
        """Rebuild each tile's puddle Geom: the first ceil(puddles * groups) groups, tinted by the sky."""
        groups = math.ceil(w.puddles * PUDDLE_GROUPS - 1e-9)
        tint = np.clip(0.35 * np.asarray(w.sky_horizon) + 0.45 * np.asarray(w.sky_top) + 0.05, 0, 1) / wet
        for tile, meshes in self._puddle_meshes.items():
            node = self._tile_nodes[("road", *tile)].node()
            if tile in self._puddle_geom:
                node.removeGeom(self._puddle_geom.pop(tile))
            merged = Mesh()
            for m in meshes[:groups]:
                for pos, col in zip(m.pos, m.col, strict=True):
                    merged.poly(pos, col[:, :3] * tint, (0, 0, 1))
            if len(merged):
                node.addGeom(merged.geom("puddles"), self._puddle_state)
                self._puddle_geom[tile] = node.getNumGeoms() - 1

    def _build_sky(self, w: Weather) -> None:
        """A camera-fixed card: sky gradient with soft cloud blobs above the horizon, far ground below."""
        if self._sky is not None:
            self._sky.removeNode()
        dist, half_w, top, bottom = sky_card_extent(self.config)
        el, sun = math.radians(w.sun_elevation_deg), np.asarray(w.sun_color)
        far_ground = np.clip(np.asarray(self.geometry.style.ground) * (np.asarray(w.ambient) + sun * max(0.0, math.sin(el))), 0, 1)
        rng = np.random.default_rng(zlib.crc32(w.name.encode()))
        nx, nz = 16, 8
        xs = np.linspace(-half_w, half_w, nx)
        zs = np.linspace(0.0, top, nz)
        cloud = np.clip(0.8 * np.asarray(w.sky_horizon) + 0.25, 0, 1)
        noise = rng.uniform(0, 1, (nz, nx)) * w.cloudiness
        mesh = Mesh()
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
        if self._semantic is not None:
            self._semantic.close()
            self._semantic = None
        _engine().removeWindow(self._buf)
        self.root.removeNode()
        self._buf = None
        self._tex = None

    def __enter__(self) -> CameraRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

