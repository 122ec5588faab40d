"""The ego car: a kinematic bicycle model with actuator limits, integrated at 0.1 s.

Steering follows CARLA: steer > 0 turns right, i.e. a negative (clockwise) wheel angle in our CCW frame.
The wheel angle chases steer * max_steer at a bounded rate; throttle and brake map to accelerations through
a power-limited engine curve, and drag plus rolling resistance slow the car when coasting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from yawil.sim.types import DT, Control, Pose, wrap_angle


@dataclass(frozen=True)
class VehicleParams:
    wheelbase: float = 2.9
    rear_to_cg: float = 1.45  # the pose is the car's centre; slip angle from this split
    length: float = 4.6
    width: float = 1.9
    height: float = 1.5
    max_steer: float = math.radians(35.0)  # wheel angle at |steer| = 1
    steer_rate: float = math.radians(120.0)  # rad/s of wheel angle
    max_accel: float = 3.5  # m/s^2 at standstill, full throttle
    max_decel: float = 8.0  # m/s^2 at full brake
    max_speed: float = 25.0  # m/s; the engine gives nothing beyond
    drag: float = 0.0008  # 1/m: aerodynamic deceleration = drag * v^2
    rolling: float = 0.15  # m/s^2 when moving


@dataclass
class EgoState:
    x: float
    y: float
    yaw: float
    speed: float = 0.0
    wheel: float = 0.0  # current wheel angle, rad, CCW positive

    @property
    def pose(self) -> Pose:
        return Pose(self.x, self.y, self.yaw)


def longitudinal_accel(params: VehicleParams, speed: float, throttle: float, brake: float) -> float:
    """Net acceleration from throttle and brake at a speed (m/s^2)."""
    engine = throttle * params.max_accel * max(0.0, 1.0 - speed / params.max_speed)
    resist = params.drag * speed * speed + (params.rolling if speed > 0.0 else 0.0)
    return engine - brake * params.max_decel - resist


def step_bicycle(state: EgoState, control: Control, params: VehicleParams, dt: float = DT) -> EgoState:
    """One integration step; the control must already be validated."""
    target = -float(control.steer) * params.max_steer
    dmax = params.steer_rate * dt
    wheel = state.wheel + max(-dmax, min(dmax, target - state.wheel))
    accel = longitudinal_accel(params, state.speed, float(control.throttle), float(control.brake))
    v_new = max(0.0, state.speed + accel * dt)
    v_mid = 0.5 * (state.speed + v_new)
    beta = math.atan(params.rear_to_cg / params.wheelbase * math.tan(wheel))
    yaw_rate = v_mid * math.cos(beta) * math.tan(wheel) / params.wheelbase
    heading = state.yaw + 0.5 * yaw_rate * dt  # midpoint heading for the position update
    x = state.x + v_mid * math.cos(heading + beta) * dt
    y = state.y + v_mid * math.sin(heading + beta) * dt
    return EgoState(x, y, wrap_angle(state.yaw + yaw_rate * dt), v_new, wheel)
