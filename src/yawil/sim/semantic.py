"""The semantic classes of the camera's pixels, shared by every backend: one table, id = index.

`Observation.semantic` (with `Scenario(semantic=True)`) is an (88, 200) uint8 array of these ids,
pixel-aligned with `Observation.image`. The embedded renderer draws them (docs/rendering.md, "Semantic
camera"); the CARLA backend maps CARLA's own tags to them (`yawil.sim.carla.convert.semantic_lut`). The table
follows what the embedded towns contain, named after CityScapes/CARLA where one exists, so that attention can
be measured by class (issue 42) and models trained here can use CARLA's labels as auxiliary targets.

No torch, no Panda3D: the explanation tools read this module too.
"""

from __future__ import annotations

import numpy as np

CLASSES: tuple[str, ...] = (
    "unlabeled",  # nothing of the list below (CARLA's "None", "Other"); the embedded world draws none
    "sky",  # what no geometry covers above the horizon
    "road",  # roads and junctions, wet or dry, with their puddles
    "lane_marking",  # centre and edge lines, stop lines
    "crosswalk",  # the stripes of a pedestrian crossing
    "sidewalk",  # raised walkways with their curbs
    "terrain",  # the ground beside the roads (grass), and the far ground beyond the draw distance
    "building",
    "pole",  # poles, and the posts of traffic lights
    "vegetation",  # trees, trunk and crown
    "static",  # other props: hydrants, boxes, markers
    "traffic_light",  # a light head's housing, and its face when the light is off (or its state unknown)
    "light_red",  # the face of a head (its three lamps) showing red
    "light_yellow",
    "light_green",
    "vehicle",
    "pedestrian",
)
CLASS_ID: dict[str, int] = {name: i for i, name in enumerate(CLASSES)}

(UNLABELED, SKY, ROAD, LANE_MARKING, CROSSWALK, SIDEWALK, TERRAIN, BUILDING, POLE, VEGETATION, STATIC, TRAFFIC_LIGHT,
 LIGHT_RED, LIGHT_YELLOW, LIGHT_GREEN, VEHICLE, PEDESTRIAN) = range(len(CLASSES))

# The class of a light head's face by the light's state (the states of yawil.sim.town.render.renderer).
LIGHT_CLASS: dict[str, int] = {"red": LIGHT_RED, "yellow": LIGHT_YELLOW, "green": LIGHT_GREEN, "off": TRAFFIC_LIGHT}

# Drawing colours (RGB), CityScapes' where the class is one of its own, CARLA's for lane markings and static.
PALETTE: np.ndarray = np.array([
    (0, 0, 0),  # unlabeled
    (70, 130, 180),  # sky
    (128, 64, 128),  # road
    (157, 234, 50),  # lane_marking
    (255, 255, 255),  # crosswalk
    (244, 35, 232),  # sidewalk
    (152, 251, 152),  # terrain
    (70, 70, 70),  # building
    (153, 153, 153),  # pole
    (107, 142, 35),  # vegetation
    (110, 190, 160),  # static
    (250, 170, 30),  # traffic_light
    (255, 0, 0),  # light_red
    (255, 220, 0),  # light_yellow
    (0, 200, 0),  # light_green
    (0, 0, 142),  # vehicle
    (220, 20, 60),  # pedestrian
], dtype=np.uint8)


def colorize(ids: np.ndarray) -> np.ndarray:
    """An (..., 3) uint8 RGB picture of class ids, in `PALETTE`'s colours (for views and figures)."""
    arr = np.asarray(ids)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"colorize needs integer class ids, got dtype {arr.dtype}")
    if arr.size and (int(arr.min()) < 0 or int(arr.max()) >= len(CLASSES)):
        raise ValueError(f"class ids must lie in [0, {len(CLASSES)}), got [{int(arr.min())}, {int(arr.max())}]")
    return PALETTE[arr]
