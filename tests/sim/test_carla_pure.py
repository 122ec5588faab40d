"""CARLA backend parts that need no server, against the real `carla` client package.

Conversions, weather mapping, camera crop/resize, route planning on a hand-written map description
(tests/fixtures/carla/synthetic_town.json: a four-way junction and a T-junction in CARLA's frame) and on a
real carla.Map built offline from OpenDRIVE (grid.xodr, converted from grid.osm with
carla.Osm2Odr), infraction rules on recorded event sequences.
"""

from __future__ import annotations

import math
from pathlib import Path

import carla
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from yawil.sim.carla import convert
from yawil.sim.carla.infractions import (
    SensorContacts,
    classify_region,
    collision_kind,
    light_state_name,
    stop_line_arrays,
)
from yawil.sim.carla.topology import (
    CarlaTopology,
    StopLine,
    waypoint_path,
    waypoint_tuple,
    write_map_description,
)
from yawil.sim.carla.weather import CARLA_PRESETS, carla_weather
from yawil.sim.criteria import CollisionCriterion, LaneInvasionCriterion, RedLightCriterion
from yawil.sim.types import Control, EventKind, Pose, RoadOption
from yawil.sim.weather import WEATHERS

FIX = Path(__file__).parents[1] / "fixtures" / "carla"
L, R, S, F = RoadOption.LEFT, RoadOption.RIGHT, RoadOption.STRAIGHT, RoadOption.LANEFOLLOW


# ------------------------------------------------------------------------------------------- conversions
@given(st.floats(-500, 500), st.floats(-500, 500), st.floats(-math.pi + 1e-6, math.pi))
@settings(max_examples=60, deadline=None)
def test_pose_round_trip_through_carla_transform(x: float, y: float, yaw: float) -> None:
    tf = convert.pose_to_transform(Pose(x, y, yaw), z=0.3)
    assert isinstance(tf, carla.Transform)
    back = convert.pose_from_transform(tf)
    assert back.x == pytest.approx(x, abs=1e-3) and back.y == pytest.approx(y, abs=1e-3)
    assert math.cos(back.yaw - yaw) == pytest.approx(1.0, abs=1e-9)


def test_carla_frame_is_left_handed_and_flipped() -> None:
    # CARLA yaw 90 deg points along +y of CARLA = south in yawil (y north): yawil yaw -pi/2
    tf = carla.Transform(carla.Location(x=10.0, y=20.0, z=0.0), carla.Rotation(yaw=90.0))
    pose = convert.pose_from_transform(tf)
    assert (pose.x, pose.y) == (10.0, -20.0)
    assert pose.yaw == pytest.approx(-math.pi / 2)
    fwd = tf.get_forward_vector()  # the real client's own forward vector agrees with the converted yaw
    assert (fwd.x, -fwd.y) == pytest.approx((math.cos(pose.yaw), math.sin(pose.yaw)), abs=1e-6)
    assert convert.yaw_to_carla(math.pi / 2) == pytest.approx(-90.0)
    assert convert.speed_of(carla.Vector3D(3.0, -4.0, 0.0)) == 5.0


def test_vehicle_control_same_conventions_and_validated() -> None:
    vc = convert.vehicle_control(Control(steer=0.25, throttle=0.5, brake=0.0))
    assert isinstance(vc, carla.VehicleControl)
    assert (vc.steer, vc.throttle, vc.brake, vc.reverse, vc.hand_brake) == pytest.approx((0.25, 0.5, 0.0, False, False))
    with pytest.raises(ValueError, match="steer"):
        convert.vehicle_control(Control(steer=1.5))
    with pytest.raises(ValueError, match="throttle"):
        convert.vehicle_control(Control(throttle=float("nan")))


def test_camera_mount_is_the_protocols() -> None:
    tf = convert.camera_transform()
    assert (tf.location.x, tf.location.y, tf.location.z) == pytest.approx((2.0, 0.0, 1.4))
    assert (convert.CAMERA_WIDTH, convert.CAMERA_HEIGHT, convert.CAMERA_FOV) == (800, 600, 100.0)


# ------------------------------------------------------------------------------------------- image
def test_bgra_to_rgb_and_crop_resize_take_rows_115_to_509() -> None:
    h, w = 600, 800
    bgra = np.zeros((h, w, 4), dtype=np.uint8)
    bgra[:, :, 0] = 10  # blue
    bgra[:, :, 1] = 20  # green
    bgra[:, :, 2] = np.arange(h, dtype=np.int64)[:, None] % 256  # red encodes the row
    bgra[:, :, 3] = 255
    rgb = convert.bgra_to_rgb(bgra.tobytes())
    assert rgb.shape == (600, 800, 3) and rgb[7, 3].tolist() == [7, 20, 10]
    bgra[:115, :, 2] = 255  # rows outside the crop are white-red: they must not leak in
    bgra[510:, :, 2] = 255
    out = convert.crop_resize(convert.bgra_to_rgb(bgra.tobytes()))
    assert out.shape == (88, 200, 3) and out.dtype == np.uint8
    assert out[0, 0, 0] < 125 and out[-1, 0, 0] < 255  # top row ~ row 117, bottom ~ row 508 (mod 256)
    assert abs(int(out[44, 100, 0]) - (115 + 44.5 * 395 / 88) % 256) <= 3
    assert np.all(out[:, :, 1] == 20) and np.all(out[:, :, 2] == 10)


def test_image_errors_name_the_shape() -> None:
    with pytest.raises(ValueError, match="800x600x4"):
        convert.bgra_to_rgb(b"\x00" * 100)
    with pytest.raises(ValueError, match="uint8 RGB"):
        convert.crop_resize(np.zeros((88, 200, 3), dtype=np.uint8))


# ------------------------------------------------------------------------------------------- weather
def test_every_yawil_preset_maps_to_carla_weather_parameters() -> None:
    assert set(CARLA_PRESETS) == set(WEATHERS)
    for name in WEATHERS:
        params = carla_weather(name)
        assert isinstance(params, carla.WeatherParameters)
        assert params == getattr(carla.WeatherParameters, name)
    assert carla_weather("HardRainNoon").precipitation > carla_weather("ClearNoon").precipitation
    with pytest.raises(ValueError, match="unknown weather 'Foggy'"):
        carla_weather("Foggy")


# ------------------------------------------------------------------------------------------- topology
@pytest.fixture(scope="module")
def town() -> CarlaTopology:
    return CarlaTopology.from_json(FIX / "synthetic_town.json")


def runs(options: np.ndarray) -> list[RoadOption]:
    out: list[RoadOption] = []
    for o in options.tolist():
        if not out or out[-1] != o:
            out.append(RoadOption(o))
    return out


# Poses in yawil's frame: X = four-way junction at (0, 0), T = T-junction at (100, 0), lanes on the right.
WEST_EASTBOUND = Pose(-80.0, -1.75, 0.0)
CASES = {
    "X left": (WEST_EASTBOUND, Pose(1.75, 60.0, math.pi / 2), [F, L, F]),
    "X right": (WEST_EASTBOUND, Pose(-1.75, -60.0, -math.pi / 2), [F, R, F]),
    "X straight": (WEST_EASTBOUND, Pose(60.0, -1.75, 0.0), [F, S, F]),
    "X straight then T left": (WEST_EASTBOUND, Pose(101.75, 60.0, math.pi / 2), [F, S, F, L, F]),
    "X straight then T right": (WEST_EASTBOUND, Pose(98.25, -60.0, -math.pi / 2), [F, S, F, R, F]),
    "T through then X": (Pose(98.25, 60.0, -math.pi / 2), Pose(-60.0, 1.75, math.pi), [F, R, F, S, F]),
    "T straight on the through road": (Pose(98.25, 60.0, -math.pi / 2), Pose(98.25, -60.0, -math.pi / 2), [F, S, F]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_road_options_as_global_route_planner(town: CarlaTopology, name: str) -> None:
    start, goal, expected = CASES[name]
    planned = town.plan(start, goal)
    r = planned.route
    assert runs(r.options) == expected
    steps = np.hypot(*np.diff(r.xy, axis=0).T)
    assert np.allclose(steps[:-1], 1.0, atol=0.05) and steps[-1] <= 1.0 + 1e-9  # dense: one waypoint per metre
    assert np.hypot(*(r.xy[0] - [start.x, start.y])) < 0.01 and np.hypot(*(r.xy[-1] - [goal.x, goal.y])) < 0.01
    # lane_yaw is the map's own heading ("simulator yaw"): on straight lanes it equals the direction of travel
    heading = np.arctan2(np.diff(r.xy[:, 1]), np.diff(r.xy[:, 0]))
    assert np.all(np.cos(heading - r.lane_yaw[:-1]) > 0.9)
    assert r.lane_yaw[0] == pytest.approx(start.yaw, abs=1e-6)
    # the option is announced 5 m before the junction, as the embedded planner does
    first = int(np.flatnonzero(r.options != int(F))[0])
    assert planned.junction[first + 5] and not planned.junction[first + 4]


def test_route_lights_are_stop_lines_before_junctions(town: CarlaTopology) -> None:
    r = town.plan(*CASES["X straight then T left"][:2]).route
    assert [lid for _, lid in r.lights] == [101, 201]
    for idx, lid in r.lights:
        stop = next(s for s in town.stops if s.light_id == lid)
        assert math.hypot(r.xy[idx, 0] - stop.x, r.xy[idx, 1] - stop.y) <= 0.6
    # a route that ends well before the junction passes no light...
    short = town.plan(WEST_EASTBOUND, Pose(-25.0, -1.75, 0.0)).route
    assert short.lights == () and runs(short.options) == [F]
    # ...but one ending 3 m before the stop line does: the car stopping at its goal reaches over the line
    near = town.plan(WEST_EASTBOUND, Pose(-15.0, -1.75, 0.0)).route
    assert near.lights == ((len(near.xy) - 1, 101),)


def test_snap_respects_direction_and_unreachable_goals_fail(town: CarlaTopology) -> None:
    seg, s, d = town.snap(Pose(-50.0, 0.3, math.pi))  # nearer the eastbound lane, but heading west
    assert town.segments[seg].yaw[0] == pytest.approx(math.pi) and d == pytest.approx(1.45, abs=1e-6)
    with pytest.raises(ValueError, match="unreachable"):  # the arms end in dead ends: leaving X, nothing comes back
        town.plan(Pose(-50.0, 1.75, math.pi), Pose(60.0, -1.75, 0.0))


def test_random_routes_are_seeded_and_long_enough(town: CarlaTopology) -> None:
    a = town.random_route(np.random.default_rng(3), min_length=150.0)
    b = town.random_route(np.random.default_rng(3), min_length=150.0)
    assert np.array_equal(a.route.xy, b.route.xy) and a.route.length >= 150.0
    with pytest.raises(ValueError, match="no route of at least 5000"):
        town.random_route(np.random.default_rng(0), min_length=5000.0, max_tries=50)


def test_map_description_errors_name_the_place(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "yawil-carla-map/1", "segments": [[[0, 0, 0, 0, 1, 0, false], [5, 0, 0, 0, 1, -1, false]]]}')
    with pytest.raises(ValueError, match=r"segment 0\[0\]: lane_id 0"):
        CarlaTopology.from_json(bad)
    bad.write_text('{"format": "other"}')
    with pytest.raises(ValueError, match="'format' must be"):
        CarlaTopology.from_json(bad)
    with pytest.raises(ValueError, match="cannot read"):
        CarlaTopology.from_json(tmp_path / "missing.json")


@pytest.fixture(scope="module")
def real_map() -> carla.Map:
    return carla.Map("grid", (FIX / "grid.xodr").read_text(encoding="utf-8"))


def test_adapter_on_a_real_carla_map(real_map: carla.Map, tmp_path: Path) -> None:
    """The carla.Waypoint adapter and the planner on a map the client library itself parsed (a 3x3 grid)."""
    topo = CarlaTopology.from_carla_map(real_map)
    assert len(topo.segments) == len(real_map.get_topology())
    seen, checked = set(), 0
    for a, b in real_map.get_topology():
        entry = convert.xy_from_carla(a.transform.location.x, a.transform.location.y)
        if not a.is_junction or not any(np.hypot(*(s.xy[-1] - entry)) < 0.5 for s in topo.segments if not s.junction):
            continue  # Osm2Odr lets some through lanes pass a T-junction without ending: no approach to plan from
        checked += 1
        start = convert.pose_from_transform(a.previous(20.0)[0].transform)
        goal = convert.pose_from_transform(b.next(15.0)[0].transform)
        turn = math.remainder(goal.yaw - start.yaw, 2 * math.pi)
        expected = S if abs(turn) < math.radians(35) else (L if turn > 0 or abs(turn) > math.radians(150) else R)
        r = topo.plan(start, goal).route
        assert runs(r.options) == [F, expected, F], (a.road_id, b.road_id, math.degrees(turn))
        assert r.length == pytest.approx(35.0 + a.transform.location.distance(b.transform.location), abs=25.0)
        seen.add(expected)
    assert seen == {L, R, S} and checked >= 20
    # record the real map's description and plan on the recording: the same route
    write_map_description([waypoint_path(a, b) for a, b in real_map.get_topology()], [], tmp_path / "m.json", "rec")
    again = CarlaTopology.from_json(tmp_path / "m.json")
    start, goal = Pose(10.0, 1.0, 0.0), Pose(290.0, 290.0, math.pi / 2)
    a, b = again.plan(start, goal).route, topo.plan(start, goal).route
    assert len(a) == len(b) and np.allclose(a.xy, b.xy, atol=1e-3) and np.array_equal(a.options, b.options)
    assert waypoint_tuple(real_map.get_topology()[0][0])[4:] == (real_map.get_topology()[0][0].road_id, real_map.get_topology()[0][0].lane_id, real_map.get_topology()[0][0].is_junction)


def test_real_map_off_road_and_junction_queries(real_map: carla.Map) -> None:
    """What CarlaWorld asks the map each step, answered by the real client library."""
    drive = carla.LaneType.Driving
    assert real_map.get_waypoint(carla.Location(x=-50.0, y=-50.0), project_to_road=False, lane_type=drive) is None
    wp = next(a for a, _ in real_map.get_topology() if not a.is_junction).next(10.0)[0]
    on = real_map.get_waypoint(wp.transform.location, project_to_road=False, lane_type=drive)
    assert on is not None and on.road_id == wp.road_id and not on.is_junction
    j = next(a for a, _ in real_map.get_topology() if a.is_junction).next(3.0)[0]
    assert real_map.get_waypoint(j.transform.location, project_to_road=False, lane_type=drive).is_junction


# ------------------------------------------------------------------------------------------- infractions
def test_collision_sensor_events_counted_once_per_contact() -> None:
    c = CollisionCriterion()
    seq = [[(7, "vehicle.tesla.model3")], [(7, "vehicle.tesla.model3")] * 3, [], [(7, "vehicle.tesla.model3"), (9, "walker.pedestrian.0001")],
           [(0, "static.pole")]]
    got = [[(e.other_type, e.other_id) for e in c.update(0.1 * i, 0.0, 0.0, SensorContacts(hits))] for i, hits in enumerate(seq)]
    assert got == [[("vehicle", 7)], [], [], [("pedestrian", 9), ("vehicle", 7)], [("static", None)]]
    assert collision_kind("traffic.traffic_light") == "static"


def test_lane_regions_from_lane_id_sign_and_heading() -> None:
    assert classify_region(False, False, 0, 0, 0.0, 0.0, 5, -1) == "off_road"
    assert classify_region(True, True, 9, -1, 0.0, 0.0, 5, -1) == "junction"
    assert classify_region(True, False, 5, -1, 0.0, 3.0, 5, -1) == "lane"  # same road, same sign
    assert classify_region(True, False, 5, 1, math.pi, 0.0, 5, -1) == "opposite_lane"
    assert classify_region(True, False, 6, 1, math.pi, 0.0, 5, -1) == "opposite_lane"  # other road: heading
    assert classify_region(True, False, 6, 1, 0.1, 0.0, 5, -1) == "lane"
    # a recorded drift over the centre line and back, then off the road: two invasions
    crit = LaneInvasionCriterion()
    regions = [classify_region(*a) for a in [(True, False, 5, -1, 0.0, 0.0, 5, -1), (True, False, 5, 1, math.pi, 0.0, 5, -1),
                                            (True, False, 5, 1, math.pi, 0.0, 5, -1), (True, False, 5, -1, 0.0, 0.0, 5, -1),
                                            (False, False, 0, 0, 0.0, 0.0, 5, -1)]]
    events = [e for i, r in enumerate(regions) for e in crit.update(0.1 * i, 0.0, 0.0, r)]
    assert [e.detail for e in events] == ["opposite_lane", "off_road"]


def test_light_states_and_stop_lines_feed_the_red_light_criterion() -> None:
    assert [light_state_name(s) for s in (carla.TrafficLightState.Red, carla.TrafficLightState.Yellow,
                                          carla.TrafficLightState.Green, carla.TrafficLightState.Off)] == ["red", "yellow", "green", "green"]
    with pytest.raises(ValueError, match="unknown traffic light state"):
        light_state_name("Blue")
    stop = StopLine(42, 10.0, -1.75, 0.0, 3.5)  # eastbound lane, line across it at x = 10
    crit = RedLightCriterion(*stop_line_arrays([stop]))
    assert crit.update(0.0, (9.0, -1.75), (9.5, -1.75), 0.0, ["red"]) == []
    ev = crit.update(0.1, (9.5, -1.75), (10.2, -1.75), 0.0, ["red"])
    assert [e.kind for e in ev] == [EventKind.LIGHT_PASSED, EventKind.RED_LIGHT] and ev[0].other_id == 42
    assert crit.update(0.2, (9.5, 1.75), (10.2, 1.75), 0.0, ["red"]) == []  # the other lane: not this line
