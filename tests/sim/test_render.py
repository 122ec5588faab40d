"""Camera renderer: shape, determinism, projection, actors, lights, weather, several towns per process;
and its numpy parts alone: camera pose, cell clipping, haze and rain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.sim.town.map.geometry import ActorView, Box, LightPost, Marking, Style, TownGeometry
from yawil.sim.town.render.camera import CameraConfig, camera_pose, reference_projection
from yawil.sim.town.render.renderer import CameraRenderer
from yawil.sim.town.render.scene_mesh import clip_to_cells
from yawil.sim.town.render.weather_fx import haze_map, post_effects, rain_layers
from yawil.sim.types import Pose
from yawil.sim.weather import TEST_WEATHERS, TRAIN_WEATHERS, get_weather

W = 3.5  # lane width
ARM = 70.0  # arm length from the centre


def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def crossing_town(name: str = "crossing", style: Style | None = None) -> TownGeometry:
    """A four-way crossing at the origin: two-lane roads, sidewalks, markings, buildings, props, lights."""
    r, s = W * 2 / 2, 3.0  # road half width, sidewalk width
    roads = [rect(-r, -r, r, r), rect(r, -r, ARM, r), rect(-ARM, -r, -r, r), rect(-r, r, r, ARM), rect(-r, -ARM, r, -r)]
    walks = []
    for sx in (1, -1):
        for sy in (1, -1):
            (xa, xb), (ya, yb) = sorted((sx * r, sx * ARM)), sorted((sy * r, sy * (r + s)))
            walks.append(rect(xa, ya, xb, yb))  # along the x arms
            (xa, xb), (ya, yb) = sorted((sx * r, sx * (r + s))), sorted((sy * (r + s), sy * ARM))
            walks.append(rect(xa, ya, xb, yb))  # along the y arms
    yellow, white = (0.9, 0.75, 0.1), (0.95, 0.95, 0.95)
    marks = []
    for d in (np.array([1.0, 0.0]), np.array([-1.0, 0.0]), np.array([0.0, 1.0]), np.array([0.0, -1.0])):
        n = np.array([-d[1], d[0]])
        a, b = d * (r + 4), d * ARM
        marks.append(Marking(np.array([a, b]), yellow, 0.15, dashed=True, kind="center"))
        for side in (1, -1):
            marks.append(Marking(np.array([a + side * n * (r - 0.2), b + side * n * (r - 0.2)]), white, 0.15, kind="edge"))
        # incoming lane is on the left of d (traffic drives toward the centre, keeps right)
        marks.append(Marking(np.array([d * (r + 4.5), d * (r + 4.5) + n * r]), white, 0.4, kind="stop"))
        for lat in np.arange(-r + 0.5, r - 0.4, 1.0):  # one Marking per stripe, as the map builder does
            marks.append(Marking(np.array([d * (r + 0.5) + n * lat, d * (r + 3.5) + n * lat]), white, 0.5, kind="crosswalk"))
    rng = np.random.default_rng(0)
    st = style or Style()
    buildings = []
    for sx in (1, -1):
        for sy in (1, -1):
            for k in range(4):
                x = sx * (r + s + 8 + k * 14)
                y = sy * (r + s + 7)
                buildings.append(Box(x, y, 0.0, 12.0, 10.0, float(rng.uniform(6, 18)), st.building_palette[k % 3]))
                buildings.append(Box(y, x, 0.0, 10.0, 12.0, float(rng.uniform(6, 18)), st.building_palette[(k + 1) % 3]))
    props = [Box(20.0, r + 1.0, 0.0, 0.3, 0.3, 5.0, (0.3, 0.3, 0.3), kind="pole"),
             Box(-15.0, -r - 1.0, 0.0, 0.4, 0.4, 0.7, (0.8, 0.1, 0.1), kind="hydrant"),
             Box(30.0, -r - 1.5, 0.0, 2.0, 2.0, 5.0, (0.2, 0.5, 0.2), kind="tree")]
    lights = [LightPost(0, -(r + 4.5), -(r + 1.0), 0.0),  # governs eastbound traffic (coming from the west)
              LightPost(1, r + 4.5, r + 1.0, math.pi),
              LightPost(2, r + 1.0, -(r + 4.5), math.pi / 2),
              LightPost(3, -(r + 1.0), r + 4.5, -math.pi / 2)]
    return TownGeometry(name, (-ARM, -ARM, ARM, ARM), roads, walks, marks, buildings, props, lights, st)


EGO = Pose(-18.0, -W / 2, 0.0)  # eastbound lane, 12 m before the stop line


@pytest.fixture(scope="module")
def renderer():
    r = CameraRenderer(crossing_town())
    yield r
    r.close()


def test_shape_dtype_and_determinism(renderer: CameraRenderer) -> None:
    a = renderer.render(EGO, (), {0: "red"}, "HardRainNoon", 7)
    b = renderer.render(Pose(5.0, 1.0, 2.0), (), {}, "ClearNoon", 3)  # something else in between
    c = renderer.render(EGO, (), {0: "red"}, "HardRainNoon", 7)
    assert a.shape == (88, 200, 3) and a.dtype == np.uint8
    assert np.array_equal(a, c)
    assert not np.array_equal(a, b)
    d = renderer.render(EGO, (), {0: "red"}, "HardRainNoon", 8)  # rain streaks move with the frame
    assert not np.array_equal(a, d)


def test_lens_matches_protocol_projection(renderer: CameraRenderer) -> None:
    """Panda3D's off-centre lens puts points where 800x600 + crop + resize would."""
    from panda3d.core import Point2, Point3

    cfg = renderer.config
    pts = np.array([[10.0, 0.0, 1.4], [20.0, 5.0, 0.0], [8.0, -4.0, 4.0], [30.0, 10.0, 9.0], [6.0, 2.0, 0.0]])
    ego = Pose(0.0, 0.0, 0.0)
    ref = reference_projection(ego, pts)
    renderer.render(ego, (), {}, "ClearNoon", 0)  # places the camera
    cam = renderer._cam
    for p, (col, row) in zip(pts, ref, strict=True):
        local = cam.getRelativePoint(renderer.root, Point3(*p))
        film = Point2()
        assert renderer._lens.project(local, film)
        pc = (film[0] + 1) / 2 * cfg.width
        pr = (1 - film[1]) / 2 * cfg.height
        assert abs(pc - col) < 1e-3 and abs(pr - row) < 1e-3, (p, (pc, pr), (col, row))
    # by hand: a point 8 m ahead of the camera at its height sits on the horizon row
    f = 400 / math.tan(math.radians(50))
    horizon_row = (300 - 115) * 88 / 395
    assert np.allclose(ref[0], [100.0, horizon_row])
    assert np.allclose(ref[1], [(400 - f * 5 / 18) / 4, (300 + f * 1.4 / 18 - 115) * 88 / 395])


def test_rendered_marker_lands_on_projection() -> None:
    """A small bright box seen in the image where the reference projection says."""
    town = crossing_town("marker")
    town.props.append(Box(15.0, 3.0, 0.0, 0.3, 0.3, 0.3, (1.0, 0.0, 1.0), z=1.0, kind="marker"))
    with CameraRenderer(town) as r:
        img = r.render(Pose(0.0, 0.0, 0.0), (), {}, "ClearNoon", 0).astype(int)
    mask = (img[..., 0] > 100) & (img[..., 1] < 60) & (img[..., 2] > 100)  # the magenta box
    assert mask.sum() >= 1
    rows, cols = np.nonzero(mask)
    col, row = reference_projection(Pose(0.0, 0.0, 0.0), np.array([[15.0, 3.0, 1.15]]))[0]
    assert abs(cols.mean() + 0.5 - col) < 1.0 and abs(rows.mean() + 0.5 - row) < 1.0


def test_vehicle_ahead_changes_centre(renderer: CameraRenderer) -> None:
    empty = renderer.render(EGO, (), {}, "ClearNoon", 0)
    car = ActorView(1, "vehicle", EGO.x + 12.0, EGO.y, 0.0, 4.5, 1.9, 1.5, (0.8, 0.1, 0.1))
    full = renderer.render(EGO, [car], {}, "ClearNoon", 0)
    centre = (slice(30, 60), slice(85, 115))
    diff = np.abs(full[centre].astype(int) - empty[centre].astype(int)).mean()
    assert diff > 20.0
    ped = ActorView(2, "pedestrian", EGO.x + 8.0, EGO.y + 1.0, 1.0, 0.4, 0.5, 1.75, (0.1, 0.2, 0.8))
    with_ped = renderer.render(EGO, [ped], {}, "ClearNoon", 0)
    assert np.abs(with_ped.astype(int) - empty.astype(int)).sum() > 0
    assert np.array_equal(renderer.render(EGO, (), {}, "ClearNoon", 0), empty)  # pool nodes hide again


def test_light_state_visible_where_the_head_projects(renderer: CameraRenderer) -> None:
    red = renderer.render(EGO, (), {0: "red"}, "ClearNoon", 0).astype(int)
    green = renderer.render(EGO, (), {0: "green"}, "ClearNoon", 0).astype(int)
    lp = renderer.geometry.light_posts[0]
    lamp_x = lp.x - 0.35
    (rc, rr), (gc, gr) = reference_projection(EGO, np.array([[lamp_x, lp.y, 2.6 + 1.1 * 5 / 6], [lamp_x, lp.y, 2.6 + 1.1 / 6]]))
    r_px, g_px = red[int(rr), int(rc)], green[int(gr), int(gc)]
    assert r_px[0] > 180 and r_px[1] < 100, r_px  # lit red lamp
    assert g_px[1] > 180 and g_px[0] < 120, g_px  # lit green lamp
    assert green[int(rr), int(rc)][0] < 100  # the red lamp is dark when green
    assert np.abs(red - green).sum() > 0
    with pytest.raises(ValueError, match="state 'blue'"):
        renderer.render(EGO, (), {0: "blue"}, "ClearNoon", 0)


def test_each_test_weather_differs_from_each_train_weather(renderer: CameraRenderer) -> None:
    imgs = {w: renderer.render(EGO, (), {0: "green"}, w, 1).astype(float) for w in TRAIN_WEATHERS + TEST_WEATHERS}
    for t in TEST_WEATHERS:
        for tr in TRAIN_WEATHERS:
            assert np.abs(imgs[t] - imgs[tr]).mean() > 8.0, (t, tr)


def test_bad_input(renderer: CameraRenderer) -> None:
    with pytest.raises(ValueError, match="unknown weather"):
        renderer.render(EGO, (), {}, "Snow", 0)
    with pytest.raises(ValueError, match="finite"):
        renderer.render(Pose(float("nan"), 0.0, 0.0), (), {}, "ClearNoon", 0)
    with pytest.raises(ValueError, match="kind"):
        renderer.render(EGO, [ActorView(1, "bike", 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, (1, 1, 1))], {}, "ClearNoon", 0)
    with pytest.raises(ValueError, match="backend"):
        CameraRenderer(crossing_town(), backend="vulkan")
    with pytest.raises(ValueError, match="crop"):
        CameraConfig(crop_top=400, crop_bottom=300)
    bad = crossing_town("bad")
    bad.road_polygons.append(np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"road_polygons\[5\]"):
        CameraRenderer(bad)


def test_two_towns_in_one_process() -> None:
    a = CameraRenderer(crossing_town("town-a"))
    b = CameraRenderer(crossing_town("town-b", Style(ground=(0.5, 0.4, 0.3), road=(0.45, 0.42, 0.4))))
    ia = a.render(EGO, (), {}, "ClearNoon", 0)
    ib = b.render(EGO, (), {}, "ClearNoon", 0)
    assert np.abs(ia.astype(int) - ib.astype(int)).mean() > 3.0
    a.close()
    assert np.array_equal(b.render(EGO, (), {}, "ClearNoon", 0), ib)
    with pytest.raises(RuntimeError, match="close"):
        a.render(EGO, (), {}, "ClearNoon", 0)
    b.close()
    c = CameraRenderer(crossing_town("town-a"))
    assert np.array_equal(c.render(EGO, (), {}, "ClearNoon", 0), ia)
    c.close()


def test_opengl_backend_sees_the_same_scene() -> None:
    """EGL/OpenGL, when the machine has it, draws the same scene (raster details differ a little)."""
    try:
        gl = CameraRenderer(crossing_town("gl"), backend="opengl")
    except RuntimeError as e:  # reported by -ra, never silent
        pytest.skip(f"no headless OpenGL here: {e}")
    car = ActorView(1, "vehicle", EGO.x + 12.0, EGO.y, 0.0, 4.5, 1.9, 1.5, (0.8, 0.1, 0.1))
    a = gl.render(EGO, [car], {0: "red"}, "WetNoon", 0)
    gl.close()
    with CameraRenderer(crossing_town("gl")) as sw:
        b = sw.render(EGO, [car], {0: "red"}, "WetNoon", 0)
    assert a.shape == b.shape == (88, 200, 3)
    assert np.abs(a.astype(int) - b.astype(int)).mean() < 12.0


def test_camera_pose_follows_the_mount() -> None:
    x, y, z, yaw = camera_pose(Pose(1.0, 2.0, math.pi / 2))  # mount (2, 0, 1.4): 2 m ahead, facing +y
    assert np.allclose((x, y, z, yaw), (1.0, 4.0, 1.4, math.pi / 2))


def polygon_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@pytest.mark.parametrize("poly", [
    rect(-3.0, 4.0, 27.0, 9.5),
    np.array([[0.0, 0.0], [23.0, 4.0], [5.0, 31.0]]),
    np.array([[12.0, -8.0], [30.0, 10.0], [12.0, 28.0], [-6.0, 10.0]]),  # a diamond across many cells
])
def test_clip_to_cells_keeps_area_and_stays_in_one_cell(poly: np.ndarray) -> None:
    pieces = clip_to_cells(poly, 10.0)
    assert len(pieces) > 1
    assert math.isclose(sum(polygon_area(p) for p in pieces), polygon_area(poly), rel_tol=1e-9)
    for p in pieces:
        lo, hi = p.min(0), p.max(0)
        cell = np.floor((lo + hi) / 2 / 10.0)
        assert np.all(lo >= cell * 10.0 - 1e-9) and np.all(hi <= (cell + 1) * 10.0 + 1e-9), p


def test_haze_map_is_strongest_at_the_horizon_and_off_without_haze() -> None:
    cfg = CameraConfig()
    clear = haze_map(get_weather("ClearNoon"), cfg)
    rain = haze_map(get_weather("HardRainNoon"), cfg)
    assert clear.shape == rain.shape == (cfg.height, 1, 1)
    assert np.all(rain >= clear) and np.all((rain >= 0) & (rain <= 1))
    horizon = int((cfg.full_height / 2 - cfg.crop_top) * cfg.height / (cfg.crop_bottom - cfg.crop_top))
    w = get_weather("HardRainNoon")  # depth capped at haze_max_depth: the horizon rows share the maximum
    top = min(1.0, 0.6 + 0.4 * w.haze) * (1.0 - math.exp(-cfg.haze_max_depth * w.haze / 60.0))
    assert math.isclose(float(rain[horizon, 0, 0]), top, rel_tol=1e-6) and math.isclose(float(rain.max()), top, rel_tol=1e-6)
    assert rain[0, 0, 0] < top / 2 and rain[-1, 0, 0] < top / 2
    below = rain[horizon + 1:, 0, 0]
    assert np.all(np.diff(below) <= 0)  # nearer ground toward the bottom: less haze
    w = get_weather("ClearNoon")
    none = haze_map(type(w)(**{**w.__dict__, "haze": 0.0}), cfg)
    assert not none.any()


def test_rain_layers_and_post_effects() -> None:
    assert rain_layers(0.0, 88, 200) == []
    a, b = rain_layers(0.4, 88, 200), rain_layers(0.4, 88, 200)
    assert len(a) == 8
    for (ra, ca), (rb, cb) in zip(a, b, strict=True):
        assert np.array_equal(ra, rb) and np.array_equal(ca, cb)
        assert ra.min() >= 0 and ra.max() < 88 and ca.min() >= 0 and ca.max() < 200
        assert len(set(zip(ra.tolist(), ca.tolist(), strict=True))) == ra.size  # each pixel once
    img = np.full((88, 200, 3), 40, np.uint8)
    no_haze = np.zeros((88, 1, 1), np.float32)
    assert np.array_equal(post_effects(img, no_haze, np.zeros(3, np.float32), [], 5), img)
    out0 = post_effects(img, no_haze, np.zeros(3, np.float32), a, 0)
    changed = np.nonzero(np.any(out0 != img, axis=2))
    order = np.lexsort((a[0][1], a[0][0]))
    assert np.array_equal(changed[0], a[0][0][order]) and np.array_equal(changed[1], a[0][1][order])  # layer 0 only
    out8 = post_effects(img, no_haze, np.zeros(3, np.float32), a, 8)  # layer 0 again, 53 px to the side
    assert np.array_equal(np.roll(out0, 53, axis=1), out8)
    hazy = post_effects(img, np.full((88, 1, 1), 0.5, np.float32), np.full(3, 240.0, np.float32), [], 0)
    assert np.all(hazy == 140)
