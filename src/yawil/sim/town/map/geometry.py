"""What a town looks like: the static geometry handed from the map builder to the renderers.

The map builder (`yawil.sim.town.map.layout`) turns a layout file into a lane graph and one `TownGeometry`;
the camera renderer (`yawil.sim.town.render.renderer`) and the bird's-eye view (`yawil.sim.town.render.birdseye`) draw
only from this, plus the per-frame `ActorView`s and light states. Map frame: x east, y north, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

RGB = tuple[float, float, float]  # each in [0, 1]


@dataclass(frozen=True)
class Box:
    """An oriented box standing on the ground (z is its bottom)."""

    x: float
    y: float
    yaw: float
    length: float  # along yaw
    width: float
    height: float
    color: RGB
    z: float = 0.0
    kind: str = "building"  # "building" | "pole" | "hydrant" | "tree" | ...


@dataclass(frozen=True)
class Marking:
    """A painted line on the road."""

    points: np.ndarray  # (N, 2) polyline
    color: RGB
    width: float = 0.15
    dashed: bool = False
    kind: str = "center"  # "center" | "edge" | "stop" | "crosswalk"


@dataclass(frozen=True)
class LightPost:
    """A traffic-light head on a pole, facing the traffic it governs (its lamps face -yaw direction)."""

    id: int
    x: float
    y: float
    yaw: float  # heading of the traffic it governs


@dataclass(frozen=True)
class Style:
    """The look of a town, so that a new town is a real visual change."""

    ground: RGB = (0.35, 0.45, 0.30)
    road: RGB = (0.30, 0.30, 0.32)
    sidewalk: RGB = (0.62, 0.60, 0.56)
    building_palette: tuple[RGB, ...] = ((0.7, 0.55, 0.45), (0.8, 0.78, 0.7), (0.55, 0.5, 0.6))


@dataclass
class TownGeometry:
    name: str
    bounds: tuple[float, float, float, float]  # (xmin, ymin, xmax, ymax)
    road_polygons: list[np.ndarray] = field(default_factory=list)  # convex (M, 2) polygons, CCW
    sidewalk_polygons: list[np.ndarray] = field(default_factory=list)  # convex, raised 0.15 m
    markings: list[Marking] = field(default_factory=list)
    buildings: list[Box] = field(default_factory=list)
    props: list[Box] = field(default_factory=list)
    light_posts: list[LightPost] = field(default_factory=list)
    style: Style = field(default_factory=Style)


@dataclass(frozen=True)
class ActorView:
    """A moving thing as the renderers see it, one per frame."""

    id: int
    kind: str  # "vehicle" | "pedestrian"
    x: float
    y: float
    yaw: float
    length: float
    width: float
    height: float
    color: RGB
