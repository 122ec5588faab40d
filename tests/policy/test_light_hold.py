"""The light hold (`light_hold`): a standing car does not start while the aux head's light output fires, for at
most that long a stand; a moving car is left to the head. Checked and recorded like the other drive settings."""

from __future__ import annotations

import numpy as np
import pytest

from yawil.policy.drive import DriveSettings, LightHold


def test_a_stand_is_held_while_the_light_fires_and_at_most_the_limit() -> None:
    h = LightHold(limit=0.3, dt=0.1)
    assert [h(0.0, True) for _ in range(5)] == [True, True, True, False, False]  # the limit: then the head drives
    assert h(0.0, False) is False
    assert h(1.0, True) is False and h.held == 0  # moving: no hold, and a new stand starts a new count
    assert h(0.0, True) is True
    assert LightHold(limit=0.3, dt=0.1)(0.0, False) is False  # no light: no hold


def test_only_a_stand_the_head_made_is_held() -> None:
    """A stand the lead-stop class made (the head would drive throughout) is not held: it may be 30 m short of
    the line; once the head has said stop in a stand, the stand is held though the head rises again."""
    h = LightHold(limit=10.0, dt=0.1)
    assert [h(0.0, True, False) for _ in range(3)] == [False] * 3
    assert h(0.0, True, True) is True and h(0.0, True, False) is True  # the head stopped it, then anticipates
    assert h(2.0, True, False) is False and h(0.0, True, False) is False  # a new stand: not armed again


def _aux(light_logit: float) -> np.ndarray:
    """An aux row: target 5 (normalised as given), lead distance 1 (far), lead speed 0, the light's logit."""
    return np.array([5.0, 1.0, 0.0, light_logit], dtype=np.float32)


@pytest.mark.parametrize("logit, speed, held", [(4.0, 0.0, True), (-4.0, 0.0, False), (4.0, 3.0, False)])
def test_decide_keeps_a_standing_car_at_a_light_it_sees(logit: float, speed: float, held: bool) -> None:
    s = DriveSettings(speed_control="target", light_hold=40.0)
    state = s.episode(0)
    stopped = _aux(logit)
    stopped[0] = 0.0  # the head stops the car first
    s.decide(np.zeros(3, np.float32), stopped, float, state, speed)
    d = s.decide(np.zeros(3, np.float32), _aux(logit), float, state, speed)  # then its target rises
    assert (d.target_speed == 0.0) is held and d.head_target_speed == 5.0
    assert d.light == pytest.approx(1.0 / (1.0 + np.exp(-logit)))
    off = DriveSettings(speed_control="target")  # without the setting the light output changes nothing
    assert off.decide(np.zeros(3, np.float32), _aux(logit), float, off.episode(0), speed).target_speed == 5.0


def test_the_light_hold_is_checked_and_recorded_where_set() -> None:
    s = DriveSettings(speed_control="stop", stop_release=10.0, light_hold=40.0)
    assert s.as_dict() == {"speed_control": "stop", "stop_release": 10.0, "light_hold": 40.0}
    with pytest.raises(ValueError, match="light_hold"):
        DriveSettings(light_hold=40.0)  # no speed control reads the aux head
    with pytest.raises(ValueError, match="light_hold"):
        DriveSettings(speed_control="target", light_hold=-1.0)
    from yawil.bench.runner import AgentSpec

    spec = AgentSpec("expert")
    assert "light_hold" not in spec.options()  # records of earlier runs still match
    learned = AgentSpec("x.pt", speed_control="target", light_hold=40.0)
    assert learned.options()["light_hold"] == 40.0 and learned.drive()["light_hold"] == 40.0
