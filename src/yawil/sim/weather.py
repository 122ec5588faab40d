"""Weather presets, named as CARLA's, shared by every backend.

The embedded renderer reads the look parameters; the CARLA backend maps the name to
`carla.WeatherParameters`. Training and test sets follow the paper (and CoRL2017/NoCrash).
"""

from __future__ import annotations

from dataclasses import dataclass

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Weather:
    name: str
    sun_azimuth_deg: float  # compass direction the light comes from, CCW from +x
    sun_elevation_deg: float
    sun_color: RGB
    ambient: RGB
    sky_top: RGB
    sky_horizon: RGB
    cloudiness: float  # 0..1
    wetness: float  # 0..1: darker road, reflections
    puddles: float  # 0..1
    rain: float  # 0..1: density of rain streaks
    haze: float  # 0..1: distance fog


WEATHERS: dict[str, Weather] = {
    w.name: w
    for w in (
        Weather("ClearNoon", 45.0, 70.0, (1.0, 0.98, 0.92), (0.45, 0.45, 0.48), (0.35, 0.55, 0.9), (0.7, 0.8, 0.95), 0.1, 0.0, 0.0, 0.0, 0.05),
        Weather("WetNoon", 45.0, 70.0, (0.95, 0.95, 0.92), (0.45, 0.45, 0.48), (0.4, 0.55, 0.85), (0.72, 0.78, 0.88), 0.2, 0.8, 0.4, 0.0, 0.1),
        Weather("HardRainNoon", 45.0, 60.0, (0.55, 0.57, 0.6), (0.4, 0.42, 0.45), (0.35, 0.37, 0.4), (0.5, 0.52, 0.55), 0.95, 1.0, 0.8, 1.0, 0.5),
        Weather("ClearSunset", 200.0, 8.0, (1.0, 0.6, 0.35), (0.35, 0.3, 0.3), (0.3, 0.35, 0.6), (1.0, 0.65, 0.4), 0.15, 0.0, 0.0, 0.0, 0.15),
        Weather("WetCloudyNoon", 45.0, 65.0, (0.75, 0.75, 0.75), (0.48, 0.48, 0.5), (0.5, 0.52, 0.56), (0.68, 0.7, 0.72), 0.8, 0.7, 0.3, 0.0, 0.25),
        Weather("SoftRainSunset", 200.0, 10.0, (0.9, 0.55, 0.4), (0.32, 0.3, 0.32), (0.32, 0.32, 0.45), (0.8, 0.55, 0.45), 0.7, 0.6, 0.3, 0.4, 0.3),
    )
}

TRAIN_WEATHERS: tuple[str, ...] = ("ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset")
TEST_WEATHERS: tuple[str, ...] = ("WetCloudyNoon", "SoftRainSunset")
WEATHER_SETS: dict[str, tuple[str, ...]] = {"train": TRAIN_WEATHERS, "test": TEST_WEATHERS, "all": tuple(WEATHERS)}


def get_weather(name: str) -> Weather:
    try:
        return WEATHERS[name]
    except KeyError:
        raise ValueError(f"unknown weather {name!r}; choose one of {', '.join(WEATHERS)}") from None


def weather_set(spec: str) -> tuple[str, ...]:
    """'train', 'test', 'all' or a comma-separated list of names."""
    if spec in WEATHER_SETS:
        return WEATHER_SETS[spec]
    names = tuple(s.strip() for s in spec.split(",") if s.strip())
    for n in names:
        get_weather(n)
    return names
