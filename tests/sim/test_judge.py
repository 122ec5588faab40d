"""The episode judge (`yawil.sim.judge`): every criterion composed once, one update per step, for both worlds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.sim import Control, Event, EventKind, Pose, Route, Scenario
from yawil.sim.criteria import BoxContacts, Criterion, StepState, nocrash_timeout
from yawil.sim.judge import NO_CONTACTS, EpisodeJudge, episode_timeout
from yawil.sim.town.world import EmbeddedWorld
from yawil.sim.types import validate_scenario

XY = np.stack([np.arange(0.0, 51.0), np.zeros(51)], axis=1)  # 50 m east along y = 0
ROUTE = Route(xy=XY, options=np.full(51, 4, np.int8), lane_yaw=np.zeros(51))
# one stop line across the route at x = 49.5 (light 7, stopping eastbound traffic)
LINE = (np.array([7]), np.array([[49.5, 1.0]]), np.array([[49.5, -1.0]]), np.array([0.0]))
NO_LINES = (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))


def _lane(_index: int) -> str:
    return "lane"


def test_timeout_is_the_scenarios_or_nocrash() -> None:
    assert episode_timeout(Scenario(timeout_s=12), 500.0) == 12.0
    assert episode_timeout(Scenario(), 500.0) == nocrash_timeout(500.0)
    assert EpisodeJudge(ROUTE, NO_LINES, Scenario()).timeout_s == pytest.approx(nocrash_timeout(50.0))


def test_driving_the_route_measures_and_reaches_the_goal_once() -> None:
    judge = EpisodeJudge(ROUTE, NO_LINES, Scenario(timeout_s=100.0))
    judge.start(0.0, 0.0, 0.0, "lane")
    prev, events = (0.0, 0.0), []
    for k in range(1, 51):
        x = float(k)
        events += judge.update(0.1 * k, x, 0.0, 0.0, prev, NO_CONTACTS, _lane, ())
        prev = (x, 0.0)
    assert [e.kind for e in events] == [EventKind.GOAL_REACHED] and events[0].time == pytest.approx(4.8)
    assert judge.done and judge.goal.reached and not judge.timeout.expired
    assert judge.progress.index == 50 and judge.progress.progress == pytest.approx(50.0)
    assert judge.distance.total == pytest.approx(50.0)
    judge.start(0.0, 0.0, 0.0, "lane")  # a new episode forgets the last
    assert not judge.done and not judge.goal.reached and judge.progress.index == 0 and judge.distance.total == 0.0


def test_one_step_gives_every_event_in_the_fixed_order() -> None:
    judge = EpisodeJudge(ROUTE, LINE, Scenario(timeout_s=0.1))
    judge.start(49.0, 0.0, 0.0, "lane")
    touching = BoxContacts((50.0, 0.0, 0.0, 4.0, 2.0), np.array([[52.0, 0.0, 0.0, 4.0, 2.0], [50.0, 1.2, 0.0, 0.6, 0.6]]),
                           np.array([3, 11]), ["vehicle", "pedestrian"])
    seen: list[int] = []

    def region(index: int) -> str:
        seen.append(index)
        return "opposite_lane"

    events = judge.update(0.1, 50.0, 0.0, 0.0, (49.0, 0.0), touching, region, ["red"])
    assert [(e.kind, e.other_id, e.other_type, e.detail) for e in events] == [
        (EventKind.COLLISION, 11, "pedestrian", ""), (EventKind.COLLISION, 3, "vehicle", ""),
        (EventKind.LANE_INVASION, None, None, "opposite_lane"), (EventKind.LIGHT_PASSED, 7, None, "red"),
        (EventKind.RED_LIGHT, 7, None, "red"), (EventKind.GOAL_REACHED, None, None, ""), (EventKind.TIMEOUT, None, None, ""),
    ]
    assert seen == [judge.progress.index] == [40]  # this step's projection (searched 40 waypoints ahead at most)
    assert judge.done
    # onsets only: the same contacts and region the next step give nothing new (but the light is behind)
    assert judge.update(0.2, 50.0, 0.0, 0.0, (50.0, 0.0), touching, region, ["red"]) == []


def test_start_region_counts_as_the_last_one() -> None:
    judge = EpisodeJudge(ROUTE, NO_LINES, Scenario(timeout_s=100.0))
    judge.start(0.0, 0.0, 0.0, "off_road")
    assert judge.update(0.1, 1.0, 0.0, 0.0, (0.0, 0.0), NO_CONTACTS, lambda _i: "off_road", ()) == []
    ev = judge.update(0.2, 2.0, 0.0, 0.0, (1.0, 0.0), NO_CONTACTS, lambda _i: "opposite_lane", ())
    assert [e.detail for e in ev] == ["opposite_lane"]


class _Honk(Criterion):
    """A criterion of a test: an event whenever the ego is faster than 5 m per step."""

    def __init__(self) -> None:
        self.started = 0

    def start(self, first: StepState) -> None:
        self.started += 1

    def judge(self, state: StepState) -> list[Event]:
        fast = math.hypot(state.x - state.prev_xy[0], state.y - state.prev_xy[1]) > 5.0
        return [Event(EventKind.COLLISION, state.time, state.x, state.y, detail="honk")] if fast else []


def test_a_new_criterion_is_one_entry_in_the_judge() -> None:
    judge = EpisodeJudge(ROUTE, NO_LINES, Scenario(timeout_s=100.0))
    honk = _Honk()
    judge.criteria += (honk,)
    judge.start(0.0, 0.0, 0.0, "lane")
    assert honk.started == 1
    assert judge.update(0.1, 1.0, 0.0, 0.0, (0.0, 0.0), NO_CONTACTS, _lane, ()) == []
    assert [e.detail for e in judge.update(0.2, 9.0, 0.0, 0.0, (1.0, 0.0), NO_CONTACTS, _lane, ())] == ["honk"]
    with pytest.raises(TypeError, match="abstract method.*judge"):  # a rule without `judge` cannot be made
        Criterion()  # type: ignore[abstract]


def test_the_embedded_world_reports_what_its_judge_says() -> None:
    w = EmbeddedWorld()
    obs = w.reset(Scenario(town="square", start=Pose(1.75, -40.0, math.pi / 2), goal=Pose(1.75, -10.0, math.pi / 2),
                           timeout_s=60.0, camera=False), seed=0)
    assert isinstance(w.judge, EpisodeJudge) and w.timeout_s == 60.0 and not obs.done
    w.ego.speed = 6.0
    events: list[Event] = []
    while not obs.done:
        obs = w.step(Control(throttle=0.3))
        events += obs.events
        assert obs.route_index == w.judge.progress.index and obs.distance_driven == w.judge.distance.total
    assert events[-1].kind is EventKind.GOAL_REACHED and w.judge.goal.reached


@pytest.mark.parametrize(("field", "value"), [
    ("weather", "Snow"), ("vehicles", -1), ("pedestrians", True), ("timeout_s", 0.0), ("timeout_s", True),
    ("timeout_s", math.inf), ("min_route_length", -1.0), ("start", Pose(0.0, math.nan, 0.0)), ("goal", (1, 2, 3)),
])
def test_one_scenario_check_names_the_field(field: str, value: object) -> None:
    bad = Scenario(**{field: value})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="Snow" if field == "weather" else f"Scenario.{field}"):
        validate_scenario(bad)
    with pytest.raises(ValueError, match="Snow" if field == "weather" else f"Scenario.{field}"):
        EmbeddedWorld().reset(bad, 0)


def test_scenario_check_refuses_other_things_and_passes_good_ones() -> None:
    with pytest.raises(ValueError, match="needs a Scenario"):
        validate_scenario("town01")
    good = Scenario(town="town02", vehicles=3, timeout_s=30, min_route_length=100.0, start=Pose(1.0, 2.0, 0.5))
    assert validate_scenario(good) is good


def test_the_carla_world_checks_scenarios_the_same_way() -> None:
    from yawil.sim.carla.world import check_scenario

    assert check_scenario(Scenario(town="town02")) == "Town02"
    for bad in (Scenario(timeout_s=True), Scenario(min_route_length=-1.0), Scenario(vehicles=-2)):  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="Scenario."):
            check_scenario(bad)
