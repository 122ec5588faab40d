"""The "stop" class's hold (`stop_hold`): the stop outlasts the class by its seconds, and is checked and recorded
like the release."""

from __future__ import annotations

import pytest

from yawil.policy.drive import DriveSettings, StopHold


def test_the_stop_outlasts_the_class_by_its_hold() -> None:
    h = StopHold(hold=0.3, dt=0.1)
    assert [h(f) for f in (False, True, False, False, False, False)] == [False, True, True, True, True, False]
    assert [h(f) for f in (True, False, True, False)] == [True, True, True, True]  # a new firing restarts it
    h.reset()
    assert h(False) is False


def test_the_hold_is_a_stop_mode_setting_recorded_where_set() -> None:
    s = DriveSettings(speed_control="stop", stop_release=10.0, stop_hold=1.0)
    assert s.as_dict() == {"speed_control": "stop", "stop_release": 10.0, "stop_hold": 1.0}
    assert s.episode(0).stop_hold is not None and DriveSettings(speed_control="stop").episode(0).stop_hold is None
    with pytest.raises(ValueError, match="stop_hold"):
        DriveSettings(speed_control="target", stop_hold=1.0)
    with pytest.raises(ValueError, match="stop_hold"):
        DriveSettings(speed_control="stop", stop_hold=-1.0)


def test_bench_records_the_hold_only_when_set() -> None:
    from yawil.bench.runner import AgentSpec

    assert "stop_hold" not in AgentSpec("expert").options()
    spec = AgentSpec("zoo:yilratt-dagger-dense2", speed_control="stop", stop_release=10.0, stop_hold=1.0,
                     engine="torch")
    assert spec.options()["stop_hold"] == 1.0 and spec.drive()["stop_hold"] == 1.0
    with pytest.raises(ValueError, match="stop_hold"):
        AgentSpec("zoo:yilratt-dagger-dense2", speed_control="target", stop_hold=1.0).validate(build=False)


def test_dagger_drives_its_learner_with_the_hold(monkeypatch: pytest.MonkeyPatch) -> None:
    """`yawil dagger --stop-hold` is a setting of the run (dagger.json), checked like the release, and reaches the
    learner's agent; an older run folder without it reads as 0 (no hold)."""
    from yawil.agent import Agent
    from yawil.pipelines.dagger import DaggerConfig, load_learner

    aux = {"model_args": {"aux": True, "lead_stop": True}, "aux_weight": 0.5}
    cfg = DaggerConfig(model="yilratt", speed_control="stop", stop_release=10.0, stop_hold=1.0, train_args=aux)
    assert cfg.to_dict()["stop_hold"] == 1.0 and DaggerConfig().to_dict()["stop_hold"] == 0.0
    with pytest.raises(ValueError, match="stop_hold"):
        DaggerConfig(model="yilratt", speed_control="target", stop_hold=1.0, train_args=aux)
    seen: dict = {}
    monkeypatch.setattr(Agent, "from_checkpoint", classmethod(lambda cls, path, **kw: seen.update(kw)))
    load_learner("x.pt", 1, "stop", stop_release=10.0, stop_hold=1.0)
    assert seen["stop_hold"] == 1.0 and seen["speed_control"] == "stop"
