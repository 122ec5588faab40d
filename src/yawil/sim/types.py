"""Backend-neutral types of the simulator interface.

Every backend (the embedded one under `yawil.sim.town`, CARLA under `yawil.sim.carla`) speaks these
types and nothing else, so that the expert, the data collector, the agent and the benchmark runner never
know which simulator they drive. Plain dataclasses and numpy arrays only: no torch here.

Conventions (fixed for all backends, see docs/simulator.md):
- Map frame is right-handed: x east, y north, z up, metres. Yaw in radians, counter-clockwise from +x,
  wrapped to (-pi, pi]. (CARLA's frame is left-handed; its backend converts y -> -y, yaw -> -yaw.)
- Control follows CARLA: steer in [-1, 1] with positive = turn right, throttle and brake in [0, 1].
- Time step 0.1 s. Speed in m/s.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum, IntEnum
from typing import Protocol, overload, runtime_checkable

import numpy as np

from yawil.sim.weather import get_weather

DT = 0.1  # seconds per step, for every backend
# Shared by every backend, so that the agent and expert see the same observation whichever world made it:
COMMAND_LOOKAHEAD = 3  # waypoints ahead of the ego's projection whose road option is the command
PRIVILEGED_RADIUS = 50.0  # metres: the actors listed in the privileged observation


class RoadOption(IntEnum):
    """High-level command of a route waypoint, with CARLA's planner values."""

    VOID = -1
    LEFT = 1
    RIGHT = 2
    STRAIGHT = 3
    LANEFOLLOW = 4


# Branch order of the conditional models (CIL, CILRS): index i drives branch i.
COMMANDS: tuple[RoadOption, ...] = (
    RoadOption.LANEFOLLOW,
    RoadOption.LEFT,
    RoadOption.RIGHT,
    RoadOption.STRAIGHT,
)


def command_index(option: int) -> int:
    """Branch index of a road option; VOID counts as LANEFOLLOW (as CARLA's agents do)."""
    opt = RoadOption(int(option))
    if opt is RoadOption.VOID:
        return 0
    return COMMANDS.index(opt)


_TWO_PI = 2.0 * math.pi


@overload
def wrap_angle(a: float) -> float: ...


@overload
def wrap_angle(a: np.ndarray | Sequence[float]) -> np.ndarray: ...


def wrap_angle(a: float | np.ndarray | Sequence[float]) -> float | np.ndarray:
    """Wrap angles to (-pi, pi]: the one angle wrap of yawil, for a scalar and elementwise for an array.

    A real scalar (float, int, numpy scalar) gives a float, by `math.remainder` (exact); anything else (an
    array, a list) a float64 array, by `np.remainder(a + pi, 2 pi) - pi`. The two are the arithmetic the
    scalar wrap of the simulator and the array wrap of guidance and the expert always used (they can differ
    in the last bit), kept each where it was so that collected data and records stay bit-identical.
    """
    if isinstance(a, numbers.Real):
        w = math.remainder(a, _TWO_PI)
        return math.pi if w == -math.pi else w
    arr = np.asarray(a, dtype=np.float64)
    v = np.remainder(arr + math.pi, _TWO_PI) - math.pi  # [-pi, pi)
    out: np.ndarray = np.where(v <= -math.pi, v + _TWO_PI, v)
    return out


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    yaw: float  # radians, CCW from +x

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw], dtype=np.float64)


@dataclass(frozen=True)
class Control:
    """One step's actuation. Out-of-range or NaN values are an error, never silently clipped."""

    steer: float = 0.0
    throttle: float = 0.0
    brake: float = 0.0

    def validate(self) -> Control:
        for name, value, lo in (("steer", self.steer, -1.0), ("throttle", self.throttle, 0.0), ("brake", self.brake, 0.0)):
            if not isinstance(value, (int, float, np.floating, np.integer)) or not math.isfinite(float(value)):
                raise ValueError(f"Control.{name} must be a finite number, got {value!r}")
            if not lo <= float(value) <= 1.0:
                raise ValueError(f"Control.{name}={value!r} is out of range [{lo}, 1]")
        return self


@dataclass(frozen=True)
class Scenario:
    """What an episode is: where, when, with whom.

    `town` is a built-in name (town01, town02, square) or a path to a layout JSON file. `start` and `goal`
    are poses snapped by the backend to the nearest lane of matching direction; None draws them at random
    from the seed. `timeout_s` None means NoCrash's formula from the route length. `semantic` adds the
    semantic camera: `Observation.semantic`, class ids of `yawil.sim.semantic` pixel-aligned with the image.
    """

    town: str = "town01"
    start: Pose | None = None
    goal: Pose | None = None
    weather: str = "ClearNoon"
    vehicles: int = 0
    pedestrians: int = 0
    timeout_s: float | None = None
    camera: bool = True
    min_route_length: float = 0.0  # for random routes: draw until at least this long (metres)
    semantic: bool = False


def validate_scenario(sc: object) -> Scenario:
    """Every backend's check of a scenario before its reset: a clear ValueError naming the bad field.

    The town name is the backend's to check (the embedded one takes layouts, CARLA only its own maps), as is
    whether the route can be as long as `min_route_length` asks.
    """
    if not isinstance(sc, Scenario):
        raise ValueError(f"reset needs a Scenario, got {type(sc).__name__}")
    get_weather(sc.weather)
    for name in ("vehicles", "pedestrians"):
        n = getattr(sc, name)
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"Scenario.{name} must be a non-negative integer, got {n!r}")
    if sc.timeout_s is not None and (isinstance(sc.timeout_s, bool) or not isinstance(sc.timeout_s, (int, float))
                                     or not math.isfinite(sc.timeout_s) or sc.timeout_s <= 0):
        raise ValueError(f"Scenario.timeout_s must be a positive number of seconds or None, got {sc.timeout_s!r}")
    if not isinstance(sc.semantic, (bool, np.bool_)):
        raise ValueError(f"Scenario.semantic must be True or False, got {sc.semantic!r}")
    if not isinstance(sc.min_route_length, (int, float)) or not 0 <= sc.min_route_length < 1e5:
        raise ValueError(f"Scenario.min_route_length must be a non-negative number of metres, got {sc.min_route_length!r}")
    for name in ("start", "goal"):
        p = getattr(sc, name)
        if p is not None and not (isinstance(p, Pose) and all(math.isfinite(v) for v in (p.x, p.y, p.yaw))):
            raise ValueError(f"Scenario.{name} must be a Pose with finite values or None, got {p!r}")
    return sc


@dataclass(frozen=True)
class Route:
    """The planned route, dense (about one waypoint per metre), fixed for the episode.

    `lane_yaw` is the heading the map itself reports for the lane at each waypoint (the "simulator yaw"
    of the paper's Carla-yaw baseline), as opposed to the heading one computes from the coordinates.
    `lights` lists (waypoint index of the stop line, light id) for each signalised junction the route
    enters, in route order.
    """

    xy: np.ndarray  # (N, 2) float64
    options: np.ndarray  # (N,) int8, RoadOption values
    lane_yaw: np.ndarray  # (N,) float64
    lights: tuple[tuple[int, int], ...] = ()

    @property
    def length(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.xy, axis=0), axis=1)))

    def __len__(self) -> int:
        return int(self.xy.shape[0])


class EventKind(str, Enum):
    COLLISION = "collision"
    LANE_INVASION = "lane_invasion"  # detail: "opposite_lane" | "off_road"
    RED_LIGHT = "red_light"  # crossed a stop line on red
    LIGHT_PASSED = "light_passed"  # crossed a signalised stop line (any state)
    GOAL_REACHED = "goal_reached"
    TIMEOUT = "timeout"


@dataclass(frozen=True)
class Event:
    kind: EventKind
    time: float
    x: float
    y: float
    other_id: int | None = None  # collision: the other actor's id (None for static objects)
    other_type: str | None = None  # collision: "vehicle" | "pedestrian" | "static"
    detail: str = ""


@dataclass(frozen=True)
class LightState:
    id: int
    state: str  # "red" | "yellow" | "green"
    x: float  # centre of the stop line it governs
    y: float
    yaw: float  # heading of the traffic it governs


@dataclass(frozen=True)
class AgentState:
    id: int
    kind: str  # "vehicle" | "pedestrian"
    x: float
    y: float
    yaw: float
    speed: float
    length: float
    width: float


@dataclass(frozen=True)
class Privileged:
    """Ground truth for the expert only. A learned agent must never read it."""

    lights: tuple[LightState, ...] = ()
    agents: tuple[AgentState, ...] = ()
    ego_lane_yaw: float = 0.0  # heading of the lane under the ego


@dataclass(frozen=True)
class Observation:
    image: np.ndarray | None  # (88, 200, 3) uint8 RGB, None when the scenario has no camera
    speed: float  # m/s
    pose: Pose
    route: Route
    route_index: int  # index of the ego's projection on the route
    command: RoadOption  # the road option the planner gives now (what CIL is told)
    events: tuple[Event, ...]  # what happened during the last step
    time: float  # seconds since reset
    frame: int
    done: bool  # goal reached or timeout (a collision does not end the episode by itself)
    distance_driven: float  # metres since reset
    town: str
    bounds: tuple[float, float, float, float]  # (xmin, ymin, xmax, ymax) of the map, for XY guidance
    weather: str
    privileged: Privileged = field(default_factory=Privileged)
    semantic: np.ndarray | None = None  # (88, 200) uint8 class ids (yawil.sim.semantic), with Scenario.semantic


class SimulatorError(RuntimeError):
    """The simulator, not the agent, ended an episode (lost connection, crashed server, client time-out).

    A runner retries such an episode on a fresh connection instead of counting it against the agent.
    """


@runtime_checkable
class World(Protocol):
    """A simulator backend. One episode at a time; deterministic given (scenario, seed)."""

    def reset(self, scenario: Scenario, seed: int) -> Observation: ...

    def step(self, control: Control) -> Observation: ...

    def close(self) -> None: ...
