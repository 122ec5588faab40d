"""The semantic camera: the class table, rendered ids where the objects are, the same ids in every weather, the
RGB image untouched, the worlds' `Observation.semantic`, and CARLA's tags mapped to the same ids."""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_render import EGO, W, crossing_town

import yawil.sim.cli as sim_cli
from yawil.sim import semantic as sem
from yawil.sim.town.map.geometry import ActorView, Box
from yawil.sim.town.render.camera import reference_projection
from yawil.sim.town.render.renderer import CameraRenderer
from yawil.sim.town.render.semantic import decode, encode
from yawil.sim.town.world import EmbeddedWorld
from yawil.sim.types import Pose, Scenario, validate_scenario
from yawil.sim.weather import WEATHERS

ROAD_AHEAD = Pose(-60.0, -W / 2, 0.0)  # eastbound lane of the west arm, 50 m before the crossing
CAR = ActorView(1, "vehicle", EGO.x + 12.0, EGO.y, 0.0, 4.5, 1.9, 1.5, (0.8, 0.1, 0.1))
PED = ActorView(2, "pedestrian", EGO.x + 8.0, EGO.y + 1.0, 1.0, 0.4, 0.5, 1.75, (0.1, 0.2, 0.8))


@pytest.fixture(scope="module")
def renderer() -> Iterator[CameraRenderer]:
    r = CameraRenderer(crossing_town())
    yield r
    r.close()


def pixel(ego: Pose, point: tuple[float, float, float]) -> tuple[int, int]:
    """(row, column) of the pixel a world point projects into."""
    col, row = reference_projection(ego, np.array([point]))[0]
    return int(row), int(col)


# ------------------------------------------------------------------------------------------- the table
def test_class_table_palette_and_colorize() -> None:
    assert len(set(sem.CLASSES)) == len(sem.CLASSES) and sem.CLASSES[0] == "unlabeled"
    assert all(sem.CLASS_ID[n] == i for i, n in enumerate(sem.CLASSES))
    assert (sem.SKY, sem.ROAD, sem.VEHICLE, sem.PEDESTRIAN) == tuple(sem.CLASS_ID[n] for n in ("sky", "road", "vehicle",
                                                                                               "pedestrian"))
    assert sem.PALETTE.shape == (len(sem.CLASSES), 3) and sem.PALETTE.dtype == np.uint8
    assert len({tuple(c) for c in sem.PALETTE.tolist()}) == len(sem.CLASSES)  # one colour each
    assert set(sem.LIGHT_CLASS) == {"red", "yellow", "green", "off"}
    ids = np.arange(len(sem.CLASSES), dtype=np.uint8).reshape(1, -1)
    assert np.array_equal(sem.colorize(ids)[0], sem.PALETTE)
    with pytest.raises(ValueError, match="class ids"):
        sem.colorize(np.array([len(sem.CLASSES)]))
    with pytest.raises(ValueError, match="integer"):
        sem.colorize(np.zeros(3))


def test_encoding_decodes_exactly_with_room_for_rounding() -> None:
    for k in range(len(sem.CLASSES)):
        red = round(float(encode(k)[0]) * 255)
        assert red == 8 * k + 4
        assert all(decode(np.array([red + d], np.uint8))[0] == k for d in range(-3, 4))
    assert decode(np.array([255], np.uint8))[0] == sem.UNLABELED  # a value no class is drawn with


# ----------------------------------------------------------------------------------- the rendered ids
def test_open_road_ahead(renderer: CameraRenderer) -> None:
    ids = renderer.render_semantic(ROAD_AHEAD, (), {})
    assert ids.shape == (88, 200) and ids.dtype == np.uint8
    assert np.all(ids[80:, 85:115] == sem.ROAD)  # the lane under the bonnet
    assert np.all(ids[:4, 90:110] == sem.SKY)  # up the street
    # the dashed centre line (0.15 m wide at y = 0, dashes over x in [-10.5 - 6k, -7.5 - 6k]) and the right edge
    # line: lines about a pixel wide, so the pixel of the projection or one beside it
    for x in (-51.0, -45.0):
        r, c = pixel(ROAD_AHEAD, (x, 0.0, 0.02))
        assert sem.LANE_MARKING in ids[r, c - 1: c + 2], (x, r, c)
    r, c = pixel(ROAD_AHEAD, (-48.0, 0.0, 0.02))  # a gap between dashes
    assert np.all(ids[r, c - 1: c + 2] == sem.ROAD)
    r, c = pixel(ROAD_AHEAD, (-50.0, -W + 0.2, 0.02))
    assert sem.LANE_MARKING in ids[r, c - 1: c + 2]
    r, c = pixel(ROAD_AHEAD, (-45.0, -W - 1.5, 0.15))  # the sidewalk on the right, buildings beyond it
    assert ids[r, c] == sem.SIDEWALK
    r, c = pixel(ROAD_AHEAD, (-40.0, -(W + 3 + 7 - 5), 5.0))
    assert ids[r, c] == sem.BUILDING
    counts = np.bincount(ids.ravel(), minlength=len(sem.CLASSES))
    assert counts[sem.VEHICLE] == counts[sem.PEDESTRIAN] == counts[sem.UNLABELED] == 0


def test_actors_where_they_are_placed(renderer: CameraRenderer) -> None:
    empty = renderer.render_semantic(EGO, (), {})
    ids = renderer.render_semantic(EGO, [CAR, PED], {})
    r, c = pixel(EGO, (CAR.x - CAR.length / 2, CAR.y, 0.5))  # the middle of the car's rear
    assert ids[r, c] == sem.VEHICLE and empty[r, c] == sem.CROSSWALK  # the car stands before the crossing
    r, c = pixel(EGO, (PED.x, PED.y, 1.0))
    assert ids[r, c] == sem.PEDESTRIAN
    # pixel-aligned with the RGB image: the car's class covers what the car changes in the picture, no more
    rgb_empty = renderer.render(EGO, (), {}, "ClearNoon", 0)
    rgb_car = renderer.render(EGO, [CAR], {}, "ClearNoon", 0)
    changed = np.any(rgb_car != rgb_empty, axis=2)
    car_ids = renderer.render_semantic(EGO, [CAR], {}) == sem.VEHICLE
    assert car_ids.sum() > 100
    assert np.array_equal(changed, car_ids), (changed ^ car_ids).sum()
    # the same actor id becoming a pedestrian (a pool slot changes shape) is drawn as a pedestrian
    swapped = renderer.render_semantic(EGO, [ActorView(1, "pedestrian", PED.x, PED.y, PED.yaw, 0.4, 0.5, 1.75,
                                                       (0.1, 0.2, 0.8))], {})
    assert not np.any(swapped == sem.VEHICLE) and np.any(swapped == sem.PEDESTRIAN)
    assert np.array_equal(renderer.render_semantic(EGO, (), {}), empty)  # pool nodes hide again


def test_a_prop_lands_where_the_rgb_shows_it() -> None:
    """A magenta box: the RGB's magenta pixels are all `static` in the semantic image."""
    town = crossing_town("marker")
    town.props.append(Box(15.0, 3.0, 0.0, 0.6, 0.6, 0.6, (1.0, 0.0, 1.0), z=1.0, kind="marker"))
    with CameraRenderer(town) as r:
        img = r.render(Pose(0.0, 0.0, 0.0), (), {}, "ClearNoon", 0).astype(int)
        ids = r.render_semantic(Pose(0.0, 0.0, 0.0), (), {})
    magenta = (img[..., 0] > 100) & (img[..., 1] < 60) & (img[..., 2] > 100)
    assert magenta.sum() >= 4 and np.all(ids[magenta] == sem.STATIC)
    assert (ids == sem.STATIC).sum() == magenta.sum()


def test_traffic_light_by_state(renderer: CameraRenderer) -> None:
    lp = renderer.geometry.light_posts[0]  # governs EGO's lane, 12 m ahead
    face = pixel(EGO, (lp.x - 0.35, lp.y, 2.6 + 0.55))  # the middle of the head's face
    pole = pixel(EGO, (lp.x, lp.y, 1.5))
    by_state = {st: renderer.render_semantic(EGO, (), {0: st}) for st in ("red", "yellow", "green")}
    for st, ids in by_state.items():
        assert ids[face] == sem.LIGHT_CLASS[st], st
        lit = {sem.LIGHT_RED, sem.LIGHT_YELLOW, sem.LIGHT_GREEN} & set(np.unique(ids).tolist())
        assert lit == {sem.LIGHT_CLASS[st]}  # only light 0 faces the camera
        assert ids[pole] == sem.POLE
    off = renderer.render_semantic(EGO, (), {})
    assert off[face] == sem.TRAFFIC_LIGHT
    face_px = by_state["red"] == sem.LIGHT_RED
    assert face_px.sum() >= 6 and np.all(off[face_px] == sem.TRAFFIC_LIGHT)  # the same pixels, unlit
    with pytest.raises(ValueError, match="state 'blue'"):
        renderer.render_semantic(EGO, (), {0: "blue"})


def test_same_ids_in_every_weather_and_rgb_untouched(renderer: CameraRenderer) -> None:
    """Ids do not see the weather, and drawing them leaves the RGB image bit-identical."""
    scenes = [(EGO, [CAR, PED], {0: "red"}), (ROAD_AHEAD, [], {0: "green"}), (Pose(5.0, 1.0, 2.0), [CAR], {})]
    with CameraRenderer(crossing_town()) as plain:  # never asked for classes
        for pose, actors, lights in scenes:
            first = renderer.render_semantic(pose, actors, lights)
            for k, w in enumerate(WEATHERS):
                rgb = renderer.render(pose, actors, lights, w, k)
                assert np.array_equal(renderer.render_semantic(pose, actors, lights), first), w
                assert np.array_equal(rgb, plain.render(pose, actors, lights, w, k)), w
                assert np.array_equal(renderer.render(pose, actors, lights, w, k), rgb), w


def test_opengl_semantic_is_aligned_with_its_own_rgb() -> None:
    """EGL/OpenGL, when the machine has it: its classes cover what its own RGB image shows (the two backends'
    raster rules differ, so each is compared with itself)."""
    try:
        gl = CameraRenderer(crossing_town("gl"), backend="opengl")
    except RuntimeError as e:  # reported by -ra, never silent
        pytest.skip(f"no headless OpenGL here: {e}")
    with gl:
        changed = np.any(gl.render(EGO, [CAR], {}, "WetNoon", 0) != gl.render(EGO, (), {}, "WetNoon", 0), axis=2)
        ids = gl.render_semantic(EGO, [CAR], {0: "red"})
    assert changed.sum() > 100 and np.array_equal(changed, ids == sem.VEHICLE)
    assert sem.LIGHT_RED in ids and sem.ROAD in ids and sem.SKY in ids


def test_same_inputs_same_ids_across_renderers() -> None:
    with CameraRenderer(crossing_town()) as a:
        ia = a.render_semantic(EGO, [CAR, PED], {0: "red"})
    with CameraRenderer(crossing_town()) as b:
        b.render_semantic(ROAD_AHEAD, [PED], {1: "green"})  # something else first
        assert np.array_equal(b.render_semantic(EGO, [CAR, PED], {0: "red"}), ia)
        b.close()
        with pytest.raises(RuntimeError, match="close"):
            b.render_semantic(EGO, (), {})
    with CameraRenderer(crossing_town()) as c, pytest.raises(ValueError, match="finite"):
        c.render_semantic(Pose(math.nan, 0.0, 0.0), (), {})


# ------------------------------------------------------------------------------------------ the world
def test_scenario_semantic_is_validated() -> None:
    assert Scenario().semantic is False
    validate_scenario(Scenario(semantic=True))
    for bad in ("yes", 1, None):
        with pytest.raises(ValueError, match="Scenario.semantic"):
            validate_scenario(Scenario(semantic=bad))  # type: ignore[arg-type]


def test_world_observation_semantic() -> None:
    """Same scenario and seed, same ids (twice in one world, whatever came between); None unless asked;
    without the RGB camera too."""
    sc = Scenario(town="town01", vehicles=15, pedestrians=10, semantic=True)
    w = EmbeddedWorld()
    try:
        runs = []
        for _ in range(2):
            obs = [w.reset(sc, 5)]
            for _ in range(5):
                obs.append(w.step(sim_cli.follow_route(obs[-1])))
            runs.append(obs)
        for a, b in zip(*runs, strict=True):
            assert a.semantic is not None and a.semantic.shape == (88, 200) and a.semantic.dtype == np.uint8
            assert a.image is not None and np.array_equal(a.semantic, b.semantic)
            assert np.mean(a.semantic[70:] == sem.ROAD) > 0.5
        assert w.reset(Scenario(town="town01"), 5).semantic is None
        only = w.reset(Scenario(town="town01", vehicles=15, pedestrians=10, camera=False, semantic=True), 5)
        assert only.image is None and np.array_equal(only.semantic, runs[0][0].semantic)
    finally:
        w.close()


def test_sim_view_writes_the_semantic_frames(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser(prog="yawil")
    sim_cli.add_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "view"
    args = parser.parse_args(["sim", "view", "--town", "square", "--steps", "2", "--frames", "2", "--vehicles", "2",
                              "--pedestrians", "2", "--semantic", "--out", str(out)])
    assert sim_cli.run(args) == 0
    names = sorted(p.name for p in out.iterdir() if p.suffix == ".png")
    assert names == ["birdseye.png", "camera_0000.png", "camera_0002.png", "semantic_0000.png", "semantic_0002.png"]
    pic = np.asarray(Image.open(out / "semantic_0002.png").convert("RGB"))
    assert pic.shape == (88, 200, 3)
    assert {tuple(c) for c in pic.reshape(-1, 3).tolist()} <= {tuple(c) for c in sem.PALETTE.tolist()}
