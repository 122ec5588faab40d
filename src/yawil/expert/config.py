"""The expert's settings (`ExpertConfig`, docs/expert.md), changeable from the command line with
`--expert-arg KEY=VALUE`."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields


@dataclass(frozen=True)
class ExpertConfig:
    """Every tunable of the expert, with the reason for its default in docs/expert.md."""

    # vehicle (matches the embedded backend's ego; the pose is the centre of the car)
    wheelbase: float = 2.9
    max_steer_deg: float = 35.0  # wheel angle at |steer| = 1
    length: float = 4.6
    width: float = 1.9
    # lateral: pure pursuit
    lookahead_min: float = 2.5
    lookahead_gain: float = 0.4  # seconds: look-ahead = min + gain * speed, from the rear axle
    lookahead_max: float = 10.0
    # speeds
    cruise_speed: float = 20.0 / 3.6  # m/s
    max_lateral_accel: float = 1.6  # m/s^2, limits the speed in curves
    min_curve_speed: float = 2.5  # m/s, never plan slower than this for curvature alone
    comfort_decel: float = 2.5  # m/s^2, braking profile towards stop points
    max_decel: float = 8.0  # m/s^2, what full braking achieves (the embedded ego's brake)
    plan_accel: float = 1.5  # m/s^2, assumed when predicting when the ego reaches a point
    # lights
    stop_line_margin: float = 1.0  # m between the front bumper and the stop line when stopped
    yellow_decel: float = 3.0  # stop for yellow only if this deceleration suffices
    # hazards
    corridor_margin: float = 0.45  # m added to the ego's half width on each side
    pedestrian_margin: float = 0.2  # extra lateral margin for pedestrians (kerb walkers stay outside)
    stop_gap: float = 3.0  # m kept between the front bumper and a pedestrian or crossing point when stopped
    vehicle_gap: float = 2.0  # m kept behind a standing vehicle (a queue on a 20 m block must fit a car)
    time_gap: float = 1.0  # s of headway behind a moving lead vehicle
    vehicle_horizon: float = 6.0  # s of constant-velocity prediction of vehicles
    pedestrian_horizon: float = 4.0  # s for pedestrians
    prediction_step: float = 0.4  # s between predicted positions
    time_buffer_before: float = 1.0  # s: the agent reaching a point this long before the ego still conflicts
    time_buffer_after: float = 1.5  # s: and this long after the ego left it
    head_on_deg: float = 160.0  # predicted crossings at a larger angle are oncoming traffic on a curve
    traffic_yellow_decel: float = 3.0  # other vehicles stop for a yellow light if this deceleration suffices
    junction_watch: float = 4.0  # m around the junction path where a crossing vehicle blocks entry
    crosswalk_after_exit: float = 4.0  # m after a junction's exit kept clear (its crosswalk)
    crosswalk_watch: float = 2.5  # m beyond the corridor where a pedestrian at a crosswalk may step in
    pedestrian_max_speed: float = 1.6  # m/s a standing pedestrian is assumed able to walk at
    preview_min: float = 30.0  # m of route examined ahead (at least)
    restart_hold: float = 1.0  # s an agent outside the lane must stay clear before the ego starts from a stop
    restart_hold_speed: float = 0.5  # m/s below which the ego counts as standing for that rule
    # goal
    goal_overshoot: float = 0.5  # m past the route's end where the centre is planned to stop
    # PID on speed (throttle positive, brake negative)
    kp: float = 0.6
    ki: float = 0.15
    kd: float = 0.0
    integral_limit: float = 2.0
    max_throttle: float = 0.75
    brake_gain: float = 0.6  # brake per unit of negative PID output
    brake_deadband: float = 0.1
    hold_brake: float = 1.0  # brake while stopped at a stop point

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not isinstance(value, (int, float)) or not math.isfinite(float(value)):
                raise ValueError(f"ExpertConfig.{name} must be a finite number, got {value!r}")
            if value < 0:
                raise ValueError(f"ExpertConfig.{name} must be >= 0, got {value!r}")
        for name in ("wheelbase", "max_steer_deg", "cruise_speed", "comfort_decel", "max_decel", "plan_accel",
                     "prediction_step", "lookahead_min"):
            if getattr(self, name) <= 0:
                raise ValueError(f"ExpertConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if self.lookahead_max < self.lookahead_min:
            raise ValueError(f"ExpertConfig.lookahead_max ({self.lookahead_max}) must be >= lookahead_min ({self.lookahead_min})")

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def parse_items(cls, items: Sequence[str], option: str = "--expert-arg") -> dict[str, float]:
        """`["comfort_decel=1.5", ...]` (command-line KEY=VALUE items) -> {setting: number}, keys checked."""
        known = {f.name for f in fields(cls)}
        values: dict[str, float] = {}
        for item in items:
            key, sep, text = item.partition("=")
            if not sep or not key:
                raise ValueError(f"{option}: expected KEY=VALUE, got {item!r}")
            if key not in known:
                raise ValueError(f"{option} {item!r}: unknown expert setting {key!r}; known: {', '.join(sorted(known))}")
            try:
                values[key] = float(text)
            except ValueError:
                raise ValueError(f"{option} {item!r}: expected a number after '='") from None
        return values

    @classmethod
    def from_items(cls, items: Sequence[str], option: str = "--expert-arg") -> ExpertConfig:
        """A config from command-line KEY=VALUE items; the rest keep their defaults."""
        return cls(**cls.parse_items(items, option))

    @classmethod
    def from_settings(cls, values: Mapping[str, float], option: str = "expert_args") -> ExpertConfig:
        """A config from stored {setting: number} (a run's settings); an unknown key names itself."""
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"{option}: unknown expert setting {unknown[0]!r}; known: "
                             f"{', '.join(sorted(f.name for f in fields(cls)))}")
        return cls(**values)

    def changes(self) -> dict[str, float]:
        """The settings that differ from the defaults (what a record or a run's settings need to say)."""
        base = ExpertConfig().to_dict()
        return {k: v for k, v in self.to_dict().items() if v != base[k]}
