"""What CARLA's sensors and map queries become for yawil's criteria (plain data in, plain data out).

The criteria themselves are `yawil.sim.criteria`'s, composed by `yawil.sim.judge.EpisodeJudge` as for the
embedded world. CARLA reports contacts through its collision sensor instead of boxes: `SensorContacts` turns
one step's reports into what the one `CollisionCriterion` reads (one event per contact onset with an actor).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from yawil.sim.carla.topology import StopLine

LIGHT_STATES = {"red": "red", "yellow": "yellow", "green": "green", "off": "green", "unknown": "green"}


def collision_kind(type_id: str) -> str:
    """'vehicle' | 'pedestrian' | 'static' from a CARLA blueprint id ('vehicle.*', 'walker.*', others)."""
    if type_id.startswith("vehicle."):
        return "vehicle"
    if type_id.startswith("walker."):
        return "pedestrian"
    return "static"


@dataclass(frozen=True)
class SensorContacts:
    """One step's collision-sensor reports: (other actor id, its type_id) each (a `criteria.Contacts`)."""

    hits: Sequence[tuple[int, str]]

    def touching(self) -> set[tuple[str, int]]:
        return {(collision_kind(type_id), int(oid)) for oid, type_id in self.hits}


def classify_region(on_road: bool, is_junction: bool, road_id: int, lane_id: int, lane_yaw: float, ego_yaw: float,
                    route_road: int, route_lane: int) -> str:
    """The region of LaneInvasionCriterion from the driving-lane waypoint under the ego.

    Off road when there is none (map.get_waypoint(project_to_road=False) is None); no direction inside a
    junction; on the route's road, the opposite lane is a lane_id of the other sign (OpenDRIVE: lanes right
    of the reference line are negative); on another road, a lane heading against the ego.
    """
    if not on_road:
        return "off_road"
    if is_junction:
        return "junction"
    if road_id == route_road:
        return "lane" if (lane_id > 0) == (route_lane > 0) else "opposite_lane"
    return "lane" if math.cos(ego_yaw - lane_yaw) >= 0.0 else "opposite_lane"


def light_state_name(state: object) -> str:
    """A carla.TrafficLightState (Red, Yellow, Green, Off, Unknown) as yawil's state name; off counts as green."""
    name = str(state).rsplit(".", 1)[-1].lower()
    if name not in LIGHT_STATES:
        raise ValueError(f"unknown traffic light state {state!r}; expected Red, Yellow, Green, Off or Unknown")
    return LIGHT_STATES[name]


def stop_line_arrays(stops: Sequence[StopLine]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ids, one end, other end, yaw) of stop lines, as RedLightCriterion takes them."""
    ends = [s.ends() for s in stops]
    return (np.array([s.light_id for s in stops], dtype=np.int64), np.array([e[0] for e in ends]).reshape(-1, 2),
            np.array([e[1] for e in ends]).reshape(-1, 2), np.array([s.yaw for s in stops], dtype=np.float64))
