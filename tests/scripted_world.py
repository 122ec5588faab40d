"""A small scripted world for the collector's tests: a straight road then a gentle curve, the real ego
dynamics, a synthetic image, an optional collision at a frame; and a small collection config for it.
Used by tests/data/test_collect.py and tests/pipelines/test_dagger.py."""

from __future__ import annotations

import math

import numpy as np

from yawil.data.collect import CollectConfig
from yawil.sim.town.dynamics import EgoState, VehicleParams, step_bicycle
from yawil.sim.types import (
    DT,
    Control,
    Event,
    EventKind,
    Observation,
    Privileged,
    RoadOption,
    Route,
    Scenario,
)


class LineWorld:
    """A 120 m straight road then a gentle curve; optional collision at a frame. Records applied controls."""

    collision_at: int | None = None

    def __init__(self) -> None:
        self.applied: list[Control] = []

    def reset(self, scenario: Scenario, seed: int) -> Observation:
        straight = np.stack([np.arange(0.0, 121.0), np.zeros(121)], axis=1)
        a = np.linspace(0.0, math.pi / 2, 40)[1:]
        arc = np.stack([120.0 + 25.0 * np.sin(a), 25.0 - 25.0 * np.cos(a)], axis=1)
        xy = np.concatenate([straight, arc])
        d = np.diff(xy, axis=0)
        yaw = np.concatenate([np.arctan2(d[:, 1], d[:, 0]), [math.pi / 2]])
        self.route = Route(xy=xy, options=np.full(len(xy), int(RoadOption.LANEFOLLOW), np.int8), lane_yaw=yaw)
        self.state = EgoState(0.0, 0.0, 0.0, 0.0)
        self.frame, self.seed, self.weather, self.camera = 0, seed, scenario.weather, scenario.camera
        self.applied = []
        return self._obs(())

    def _obs(self, events: tuple[Event, ...]) -> Observation:
        st = self.state
        idx = int(np.argmin(np.linalg.norm(self.route.xy - np.array([st.x, st.y]), axis=1)))
        done = idx >= len(self.route) - 2
        img = None
        if self.camera:
            img = np.full((88, 200, 3), (self.frame * 7 + self.seed) % 256, dtype=np.uint8)
        if done:
            events = (*events, Event(EventKind.GOAL_REACHED, self.frame * DT, st.x, st.y))
        return Observation(
            image=img, speed=st.speed, pose=st.pose, route=self.route, route_index=idx,
            command=RoadOption.LANEFOLLOW, events=events, time=self.frame * DT, frame=self.frame, done=done,
            distance_driven=0.0, town="line", bounds=(-10.0, -10.0, 160.0, 160.0), weather=self.weather,
            privileged=Privileged(),
        )

    def step(self, control: Control) -> Observation:
        self.applied.append(control.validate())
        self.state = step_bicycle(self.state, control, VehicleParams())
        self.frame += 1
        events: tuple[Event, ...] = ()
        if self.collision_at is not None and self.frame == self.collision_at:
            events = (Event(EventKind.COLLISION, self.frame * DT, self.state.x, self.state.y, 5, "vehicle"),)
        return self._obs(events)

    def close(self) -> None:
        pass


def line_world() -> LineWorld:
    return LineWorld()


def crash_world() -> LineWorld:
    w = LineWorld()
    w.collision_at = 150
    return w


def small_cfg(**kw: object) -> CollectConfig:
    base: dict[str, object] = dict(town="line", weathers=("ClearNoon", "WetNoon"), vehicles=(0, 0), pedestrians=(0, 0),
                                   noise_fraction=0.3, straight_keep=1.0)
    base.update(kw)
    return CollectConfig(**base)  # type: ignore[arg-type]
