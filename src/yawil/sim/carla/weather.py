"""yawil's weather presets as CARLA's WeatherParameters.

The presets carry CARLA's names (ClearNoon, WetNoon, HardRainNoon, ClearSunset, WetCloudyNoon,
SoftRainSunset), so the mapping is by name to the `carla.WeatherParameters` attribute of the same name.
"""

from __future__ import annotations

from typing import Any

from yawil.sim.weather import WEATHERS, get_weather

# yawil preset -> carla.WeatherParameters attribute (identity today; kept explicit so a rename stays local)
CARLA_PRESETS: dict[str, str] = {name: name for name in WEATHERS}


def carla_weather(name: str) -> Any:
    """The carla.WeatherParameters of a yawil weather preset; ValueError for unknown names."""
    import carla

    get_weather(name)
    attr = CARLA_PRESETS[name]
    params = getattr(carla.WeatherParameters, attr, None)
    if params is None:
        raise ValueError(f"weather {name!r}: this carla client has no WeatherParameters.{attr}")
    return params
