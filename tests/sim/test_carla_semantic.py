"""CARLA's semantic camera as yawil's class ids: the tag table of both CARLA generations, the crop and resize,
and the sensor made only when a scenario asks for it (against `FakeCarlaServer`; no server runs here)."""

from __future__ import annotations

import carla
import numpy as np
import pytest

from carla_fakes import FakeCarlaServer, FakeImage, semantic_frame
from yawil.sim import make_world
from yawil.sim import semantic as sem
from yawil.sim.carla import convert
from yawil.sim.types import Control, Scenario

# The tags of CARLA 0.9.11-0.9.13 (LibCarla's rpc/ObjectLabel.h before the CityScapes order of 0.9.14).
LEGACY_TAGS = ("NONE", "Buildings", "Fences", "Other", "Pedestrians", "Poles", "RoadLines", "Roads", "Sidewalks",
               "Vegetation", "Vehicles", "Walls", "TrafficSigns", "Sky", "Ground", "Bridge", "RailTrack", "GuardRail",
               "TrafficLight", "Static", "Dynamic", "Water", "Terrain")


def test_every_tag_of_the_installed_client_has_a_class() -> None:
    tags = convert.carla_tag_values()
    assert set(tags) <= set(convert.CARLA_LABEL_CLASSES), set(tags) - set(convert.CARLA_LABEL_CLASSES)
    assert set(convert.CARLA_LABEL_CLASSES.values()) <= set(sem.CLASSES)
    lut = convert.semantic_lut(tags)
    assert lut.shape == (256,) and lut.dtype == np.uint8
    label = carla.CityObjectLabel
    expect = {label.Roads: "road", label.RoadLines: "lane_marking", label.Sidewalks: "sidewalk", label.Sky: "sky",
              label.Car: "vehicle", label.Truck: "vehicle", label.Pedestrians: "pedestrian", label.Poles: "pole",
              label.TrafficLight: "traffic_light", label.Buildings: "building", label.Vegetation: "vegetation",
              label.Terrain: "terrain", label.NONE: "unlabeled"}
    for tag, name in expect.items():
        assert sem.CLASSES[lut[int(tag)]] == name, tag
    if int(label.Roads) == 1:  # the CityScapes order of 0.9.14 and later
        assert (lut[1], lut[14], lut[24]) == (sem.ROAD, sem.VEHICLE, sem.LANE_MARKING)


def test_legacy_tags_map_to_the_same_classes() -> None:
    lut = convert.semantic_lut({name: value for value, name in enumerate(LEGACY_TAGS)})
    assert (lut[7], lut[6], lut[8], lut[10], lut[4], lut[13], lut[18], lut[1]) == (
        sem.ROAD, sem.LANE_MARKING, sem.SIDEWALK, sem.VEHICLE, sem.PEDESTRIAN, sem.SKY, sem.TRAFFIC_LIGHT, sem.BUILDING)
    assert lut[200] == sem.UNLABELED  # no such tag
    assert convert.semantic_lut({"SomethingNew": 40})[40] == sem.UNLABELED
    with pytest.raises(ValueError, match="one byte"):
        convert.semantic_lut({"Roads": 300})


def test_semantic_image_crop_and_nearest_resize() -> None:
    lut = convert.semantic_lut(convert.carla_tag_values())
    ids = convert.observation_semantic(FakeImage(3, semantic_frame().tobytes()), lut)
    assert ids.shape == (88, 200) and ids.dtype == np.uint8
    # output row r samples full-image row 115 + (r + 0.5) * 395 / 88: the horizon (row 300) falls in row 41
    assert np.all(ids[:41, 30:] == sem.SKY) and np.all(ids[41:, :20] == sem.ROAD)
    car_rows = [r for r in range(88) if 320 <= 115 + int((r + 0.5) * 395 / 88) < 400]
    assert np.all(ids[car_rows][:, 75:125] == sem.VEHICLE) and not np.any(ids[:, :75] == sem.VEHICLE)
    assert np.all(ids[10:70, 24] == sem.POLE) and not np.any(ids[:, 23] == sem.POLE)  # columns 96..103 -> 24 only
    with pytest.raises(ValueError, match="BGRA"):
        convert.observation_semantic(FakeImage(3, b"\0" * 10), lut)


def test_semantic_sensor_only_when_asked() -> None:
    server = FakeCarlaServer(town="Town02")
    world = make_world("carla", host="fake", port=2000, timeout=2.0, client=server)
    try:
        obs = world.reset(Scenario(town="town02"), seed=1)
        assert obs.semantic is None
        assert not any(a.type_id == "sensor.camera.semantic_segmentation" for a in server.actors.values())
        obs = world.reset(Scenario(town="town02", semantic=True), seed=1)
        cams = [a for a in server.actors.values() if a.type_id.startswith("sensor.camera.")]
        assert sorted(a.type_id for a in cams) == ["sensor.camera.rgb", "sensor.camera.semantic_segmentation"]
        sem_cam = next(a for a in cams if a.type_id.endswith("semantic_segmentation"))
        assert sem_cam.parent is server.ego and sem_cam.transform.location.x == 2.0
        assert obs.image is not None and obs.semantic is not None and obs.semantic.shape == (88, 200)
        assert np.all(obs.semantic[:41, 30:] == sem.SKY) and sem.VEHICLE in obs.semantic
        assert world.step(Control()).semantic is not None
    finally:
        world.close()
