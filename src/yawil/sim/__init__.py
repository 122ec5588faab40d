"""The simulator interface: backend-neutral types and `make_world`.

`make_world("embedded")` gives the built-in simulator (yawil.sim.town); `make_world("carla", ...)` the CARLA
backend when it is installed. The Gymnasium environments (`yawil/Town01-v0`, `yawil/Town02-v0`,
`yawil/Square-v0`) live above the simulator, in `yawil.gym_env` (they add guidance and the expert's action);
`import yawil` registers them, and the environment module loads on `gymnasium.make`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from yawil.sim.types import (
    COMMANDS,
    DT,
    AgentState,
    Control,
    Event,
    EventKind,
    LightState,
    Observation,
    Pose,
    Privileged,
    RoadOption,
    Route,
    Scenario,
    SimulatorError,
    World,
    command_index,
    wrap_angle,
)

BACKENDS: tuple[str, ...] = ("embedded", "carla")


def make_world(backend: str = "embedded", **kwargs: Any) -> World:
    """A simulator backend by name; keyword arguments go to its constructor."""
    if backend == "embedded":
        from yawil.sim.town.world import EmbeddedWorld

        return EmbeddedWorld(**kwargs)
    if backend == "carla":
        try:
            from yawil.sim.carla.world import CarlaWorld  # type: ignore[import-not-found]
        except ModuleNotFoundError as err:
            raise ValueError(f"backend 'carla' is not available ({err}); install the carla client package") from None
        return CarlaWorld(**kwargs)  # type: ignore[no-any-return]
    raise ValueError(f"unknown simulator backend {backend!r}; choose one of {', '.join(BACKENDS)}")


def world_factory(backend: str = "embedded", **kwargs: Any) -> Callable[[], World]:
    """A picklable no-argument maker of worlds, for worker processes (each builds its own world)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown simulator backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    return functools.partial(make_world, backend, **kwargs)


__all__ = [
    "BACKENDS", "COMMANDS", "DT", "AgentState", "Control", "Event", "EventKind", "LightState", "Observation", "Pose",
    "Privileged", "RoadOption", "Route", "Scenario", "SimulatorError", "World", "command_index", "make_world", "world_factory",
    "wrap_angle",
]
