"""Errors of the CARLA backend, kept apart from the agent's failures.

`SimulatorError` means the simulator, not the agent, ended the episode (lost connection, crashed server,
time-out of the client): a benchmark runner records the episode as "simulator error", calls
`CarlaWorld.reconnect()` and goes on. `CarlaSetupError` means the backend cannot start at all (no server,
client and server versions differ, a town the server does not have): retrying does not help.
"""

from __future__ import annotations

from yawil.sim.types import SimulatorError  # backend-neutral: the runner catches it without importing carla

__all__ = ["CarlaSetupError", "SimulatorError", "START_HINT"]


class CarlaSetupError(RuntimeError):
    """The CARLA backend cannot run with this server (absent, wrong version, missing map)."""


START_HINT = (
    "start a CARLA server first, e.g. `./CarlaUE4.sh -RenderOffScreen -carla-rpc-port=2000` "
    "(or `docker run --rm --gpus all --net=host carlasim/carla:0.9.16 ./CarlaUE4.sh -RenderOffScreen`), "
    "with the same version as the `carla` client package"
)
