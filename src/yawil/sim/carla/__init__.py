"""The CARLA backend of yawil's simulator interface (needs the `carla` client package and a server).

`yawil.sim.make_world("carla", host=..., port=..., timeout=...)` gives a `CarlaWorld` (world.py). The
parts that need no server are separate and import `carla` only when called: frame and type conversions and
the camera pipeline (convert.py), weather mapping (weather.py), route planning on the map topology with
networkx (topology.py), infraction rules (infractions.py) and errors (errors.py). The benchmark's CARLA
route files and their generator live with the benchmark, in `yawil.bench.carla_routes`. Nothing here is
imported by the rest of yawil but `yawil.sim.make_world` and the benchmark.
"""

from __future__ import annotations

from yawil.sim.carla.errors import CarlaSetupError, SimulatorError

__all__ = ["CarlaSetupError", "SimulatorError"]
