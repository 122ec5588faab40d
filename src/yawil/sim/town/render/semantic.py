"""The semantic camera: the forward camera's view as class ids (`yawil.sim.semantic`), pixel for pixel.

`SemanticPass` draws a second scene graph of the same town into its own offscreen buffer, through the same
lens from the same pose: the static meshes rebuilt by `scene_mesh` (the very same triangles, grouping and
level of detail) with each vertex coloured by its polygon's class, the renderer's actor nodes shared by
instancing (a tag on each actor shape gives a flat colour per kind), the light heads' faces coloured by state,
and a far-ground card below the horizon; what nothing covers keeps the clear colour, sky. Nothing is lit,
textured, fogged or blended and no post-effect runs, so weather cannot change an id (wet roads and their
puddles are road; puddles are not drawn). Class k is drawn as red = 8 k + 4 and decoded by k = red // 8,
which leaves room for a rasteriser's rounding.

Built on the first `CameraRenderer.render_semantic` call only: a renderer never asked for classes pays
nothing, and its RGB image is the same with or without this pass (tested).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from yawil.sim import semantic as sem
from yawil.sim.town.render.camera import sky_card_extent
from yawil.sim.town.render.renderer import (
    SEMANTIC_TAG,
    CameraRenderer,
    _cull_bins,
    _engine,
    _pipe,
    changed_lights,
    render_frame,
)
from yawil.sim.town.render.scene_mesh import Mesh, Tiles, build_lamps, build_static

_STEP, _OFFSET = 8, 4  # class k drawn as red = 8 k + 4


def encode(ids: np.ndarray | int) -> np.ndarray:
    """(..., 4) float32 RGBA drawing colour of class ids: red (8 id + 4) / 255, green and blue 0."""
    k = np.asarray(ids, dtype=np.float32)
    out = np.zeros(k.shape + (4,), np.float32)
    out[..., 0] = (_STEP * k + _OFFSET) / 255.0
    out[..., 3] = 1.0
    return out


_DECODE = (np.arange(256) // _STEP).astype(np.uint8)
_DECODE[_DECODE >= len(sem.CLASSES)] = sem.UNLABELED


def decode(red: np.ndarray) -> np.ndarray:
    """Class ids of drawn red values (uint8); a value of no class (none is drawn) reads as unlabeled."""
    out: np.ndarray = _DECODE[red]
    return out


class SemanticPass:
    """The semantic scene of one `CameraRenderer` and its offscreen buffer."""

    def __init__(self, r: CameraRenderer) -> None:
        from panda3d.core import (
            Camera,
            ColorAttrib,
            ColorScaleAttrib,
            CullBinAttrib,
            DepthTestAttrib,
            FrameBufferProperties,
            GeomNode,
            GraphicsOutput,
            GraphicsPipe,
            LightAttrib,
            NodePath,
            RenderState,
            Texture,
            WindowProperties,
        )

        cfg, geo = r.config, r.geometry
        self.config = cfg
        tiles = Tiles(cfg.tile_size)
        build_static(geo, tiles, np.random.default_rng(zlib.crc32(geo.name.encode())))  # colours unused
        self._lamp_rows = build_lamps(geo, tiles)
        for mesh in tiles.meshes.values():
            mesh.col = [np.broadcast_to(encode(k), (len(p), 4)) for p, k in zip(mesh.pos, mesh.labels, strict=True)]

        fb = FrameBufferProperties()
        fb.setRgbColor(True)
        fb.setColorBits(24)
        fb.setDepthBits(24)
        engine = _engine()
        self._buf = engine.makeOutput(_pipe(r.backend), f"yawil-semantic-{geo.name}", 0, fb,
                                      WindowProperties.size(cfg.width, cfg.height), GraphicsPipe.BFRefuseWindow)
        if self._buf is None:
            raise RuntimeError(f"render backend {r.backend!r}: could not open the semantic camera's buffer")
        self._tex = Texture("semantic")
        self._buf.addRenderTexture(self._tex, GraphicsOutput.RTMCopyRam, GraphicsOutput.RTPColor)
        self._buf.setClearColor(tuple(float(v) for v in encode(sem.SKY)))
        self._buf.setActive(False)

        self.root = NodePath(f"semantic-{geo.name}")
        self.root.setLightOff(1)
        self._cam = self.root.attachNewNode(Camera("semantic", r._lens))
        cam = self._cam.node()
        cam.setTagStateKey(SEMANTIC_TAG)
        for kind in ("vehicle", "pedestrian"):  # a flat colour wins over the paint's colour scale and the lights
            cam.setTagState(kind, RenderState.make(ColorAttrib.makeFlat(tuple(float(v) for v in encode(sem.CLASS_ID[kind]))),
                                                   ColorScaleAttrib.makeIdentity(), LightAttrib.makeAllOff(), 1000))
        self._buf.makeDisplayRegion().setCamera(self._cam)

        # the renderer's layer states, puddles left out (they lie on the road: the road under them is the class)
        _cull_bins()
        solid, no_test = CullBinAttrib.make("solid", 0), DepthTestAttrib.make(DepthTestAttrib.MNone)
        states = {"ground": RenderState.make(CullBinAttrib.make("flat", 0), no_test),
                  "road": RenderState.make(CullBinAttrib.make("flat", 1), no_test),
                  "marking": RenderState.make(CullBinAttrib.make("flat", 3), no_test),
                  "static": RenderState.make(solid), "lamps": RenderState.make(solid)}
        self._lamp_geoms: dict[tuple[int, int], tuple[Any, int]] = {}
        groups: dict[tuple[int, int], Any] = {}
        size = cfg.tile_size
        for i, j in sorted({(i, j) for (_, i, j) in tiles.meshes}):
            node = GeomNode(f"semantic-{i}-{j}")
            for layer in ("ground", "road", "marking", "static", "lamps"):
                m = tiles.meshes.get((layer, i, j))
                if m is not None and len(m):
                    node.addGeom(m.geom(layer), states[layer])
                    if layer == "lamps":
                        self._lamp_geoms[(i, j)] = (node, node.getNumGeoms() - 1)
            if not node.getNumGeoms() and ("near", i, j) not in tiles.meshes:
                continue  # a tile of puddles only
            if (i // 4, j // 4) not in groups:
                groups[(i // 4, j // 4)] = self.root.attachNewNode(f"semantic-group-{i // 4}-{j // 4}")
            tile = groups[(i // 4, j // 4)].attachNewNode(node)
            if ("near", i, j) in tiles.meshes:
                self._add_lod(tile, tiles, i, j, size, states["static"])
        self._actors = r._actors_root.instanceTo(self.root)  # the same pool nodes, placed once for both cameras
        self._add_far_ground()
        self._lamp_state = {lid: "off" for lid in self._lamp_rows}
        self._closed = False

    def _add_lod(self, parent: Any, tiles: Tiles, i: int, j: int, size: float, state: Any) -> None:
        """The renderer's LOD switch of a tile's buildings, so that both cameras see the same triangles."""
        from panda3d.core import GeomNode, LODNode, Point3

        lod = LODNode(f"semantic-buildings-{i}-{j}")
        lod.setCenter(Point3((i + 0.5) * size, (j + 0.5) * size, 0.0) if size > 0 else Point3(0, 0, 0))
        for layer, near, far in (("near", self.config.lod_distance, 0.0), ("far", 1e6, self.config.lod_distance)):
            node = GeomNode(f"semantic-{layer}-{i}-{j}")
            node.addGeom(tiles.meshes[(layer, i, j)].geom(layer), state)
            lod.addChild(node)
            lod.addSwitch(near, far)
        parent.attachNewNode(lod)

    def _add_far_ground(self) -> None:
        """Terrain where the RGB sky card shows the far ground: below the horizon, past the draw distance."""
        dist, half_w, _, bottom = sky_card_extent(self.config)
        mesh = Mesh()
        q = np.array([[-half_w, dist, bottom], [half_w, dist, bottom], [half_w, dist, 0.0], [-half_w, dist, 0.0]])
        mesh.poly(q, encode(sem.TERRAIN), (0, -1, 0), sem.TERRAIN)
        card = self._cam.attachNewNode(mesh.geom_node("semantic-far-ground"))
        card.setBin("background", 0)
        card.setDepthWrite(False)
        card.setDepthTest(False)

    def render(self, cam: tuple[float, float, float, float], light_states: Mapping[int, str]) -> np.ndarray:
        """(height, width) uint8 class ids from camera pose `cam` (x, y, z, yaw); actors are already placed."""
        self._set_lamps(light_states)
        self._cam.setPosHpr(cam[0], cam[1], cam[2], math.degrees(cam[3]) - 90.0, 0.0, 0.0)
        self._buf.setActive(True)
        try:
            render_frame()
        finally:
            self._buf.setActive(False)
        raw = np.frombuffer(self._tex.getRamImage(), np.uint8)
        comps = raw.size // (self.config.width * self.config.height)
        return decode(raw.reshape(self.config.height, self.config.width, comps)[::-1, :, 2])  # BGR(A), bottom-up

    def _set_lamps(self, light_states: Mapping[int, str]) -> None:
        """Each head's face in its state's class (a light not listed is off), as the renderer does its lamps."""
        for lid, st in changed_lights(self._lamp_state, light_states):
            tile, row = self._lamp_rows[lid]
            node, gi = self._lamp_geoms[tile]
            vdata = node.modifyGeom(gi).modifyVertexData()
            arr = np.frombuffer(memoryview(vdata.modifyArray(0)).cast("B"), np.float32).reshape(-1, 10)
            arr[row: row + 12, 6:10] = encode(sem.LIGHT_CLASS[st])
            self._lamp_state[lid] = st

    def close(self) -> None:
        """Free the buffer and the semantic scene (the shared actor nodes stay with the renderer)."""
        if self._closed:
            return
        self._closed = True
        self._actors.detachNode()
        _engine().removeWindow(self._buf)
        self.root.removeNode()
        self._buf = None
        self._tex = None
