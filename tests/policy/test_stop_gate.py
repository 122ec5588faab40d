"""The stop release's gate (`stop_gate`): a stand counts toward the release only while the aux head's predicted
lead distance is at least that far; checked and recorded like the other release settings."""

from __future__ import annotations

import numpy as np
import pytest

from yawil.data.schema import LEAD_RANGE
from yawil.policy.drive import DriveSettings, StopRelease


def test_a_stand_that_is_not_clear_neither_counts_nor_resets() -> None:
    r = StopRelease(patience=0.3, dt=0.1)
    assert [r.released(0.0, True, c) for c in (True, False, True, False, False)] == [False] * 5
    assert r.released(0.0, True, True) is True  # the third clear step of standing: the creep starts
    r = StopRelease(patience=0.3, dt=0.1)
    assert [r.released(0.0, True) for _ in range(3)] == [False, False, True]  # no gate: as before
    r = StopRelease(patience=0.3, dt=0.1)
    r.released(0.0, True), r.released(0.0, True)
    assert r.released(1.0, True) is False and r.stood == 0  # moving resets the count, clear or not


def _aux(lead_m: float, stop_logit: float = 4.0) -> np.ndarray:
    """An aux row: target 5 (normalised as given), lead distance (/ LEAD_RANGE), lead speed 0, light 0, stop."""
    return np.array([5.0, lead_m / LEAD_RANGE, 0.0, -5.0, stop_logit], dtype=np.float32)


@pytest.mark.parametrize("lead_m, released", [(10.0, False), (40.0, True)])
def test_decide_releases_only_when_the_regression_sees_no_car_close(lead_m: float, released: bool) -> None:
    s = DriveSettings(speed_control="stop", stop_release=0.3, stop_gate=25.0)
    state = s.episode(0)
    targets = [s.decide(np.zeros(3, np.float32), _aux(lead_m), float, state, 0.0).target_speed for _ in range(5)]
    assert (max(targets) > 0) is released  # the class fires throughout: only a release lets the car drive


def test_the_gate_is_a_release_setting_recorded_where_set() -> None:
    s = DriveSettings(speed_control="stop", stop_release=10.0, stop_gate=25.0)
    assert s.as_dict() == {"speed_control": "stop", "stop_release": 10.0, "stop_gate": 25.0}
    with pytest.raises(ValueError, match="stop_gate"):
        DriveSettings(speed_control="stop", stop_gate=25.0)  # no release to gate
    with pytest.raises(ValueError, match="stop_gate"):
        DriveSettings(speed_control="stop", stop_release=10.0, stop_gate=float("nan"))
    from yawil.bench.runner import AgentSpec

    assert "stop_gate" not in AgentSpec("expert").options()
    spec = AgentSpec("zoo:yilratt-dagger-dense3", speed_control="stop", stop_release=10.0, stop_gate=25.0,
                     engine="torch")
    assert spec.options()["stop_gate"] == 25.0 and spec.drive()["stop_gate"] == 25.0
    with pytest.raises(ValueError, match="stop_gate"):
        AgentSpec("zoo:yilratt-dagger-dense3", speed_control="stop", stop_gate=25.0).validate(build=False)


def test_dagger_and_select_take_the_gate() -> None:
    import argparse

    from yawil.pipelines.dagger import DaggerConfig
    from yawil.policy.speed import add_speed_control_arguments, given_drive

    aux = {"model_args": {"aux": True, "lead_stop": True}, "aux_weight": 0.5}
    cfg = DaggerConfig(model="yilratt", speed_control="stop", stop_release=10.0, stop_gate=25.0, train_args=aux)
    assert cfg.to_dict()["stop_gate"] == 25.0 and DaggerConfig().to_dict()["stop_gate"] == 0.0
    with pytest.raises(ValueError, match="stop_gate"):
        DaggerConfig(model="yilratt", speed_control="stop", stop_gate=25.0, train_args=aux)
    p = argparse.ArgumentParser()
    add_speed_control_arguments(p)
    args = p.parse_args(["--speed-control", "stop", "--stop-release", "10", "--stop-gate", "25"])
    assert given_drive(args)["stop_gate"] == 25.0
