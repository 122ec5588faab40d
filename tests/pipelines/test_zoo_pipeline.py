"""`yawil reproduce --profile zoo` at a tiny scale: collect, train, benchmark, pack; the packed model passes its
probe check and its card holds the figures the stages measured; a rerun resumes without work."""

from __future__ import annotations

from pathlib import Path

import pytest

from yawil.pipelines import zoo as zp


@pytest.mark.slow
def test_zoo_pipeline_makes_a_checked_model_with_its_card(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from yawil.bench.suites import episodes
    from yawil.cli import main
    from yawil.zoo import read_card
    from yawil.zoo.pack import check_zoo_model

    tiny = zp.ZooRecipe("tiny", "a tiny net", "yaw-guided", 3, drive={"speed_control": "target"},
                        train_args={"ema": 0.9, "model_args": {"aux": True}, "aux_weight": 0.5, "threads": 1})
    monkeypatch.setattr(zp, "RECIPES", (tiny,))
    monkeypatch.setattr(zp, "EXPERT_FRAMES", 150)
    monkeypatch.setattr(zp, "EVAL_WORKERS", 1)
    one = episodes("all", ["new-town-weather"], ["straight"], routes="0:1", seeds=1, weather_rule="cycle")
    monkeypatch.setattr(zp, "episode_set", lambda which: one)
    out = tmp_path / "zoo_run"
    assert main(["reproduce", "--profile", "zoo", "--out", str(out)]) == 0
    card = read_card("tiny", out / "zoo")
    assert card["eval100"]["episodes"] == 1 and card["demo"]["episodes"] == 1 and card["step"] == 3
    assert card["drive"] == {"speed_control": "target"} and card["commands"][1].startswith("yawil train --model yaw-guided")
    assert card["data"]["frames"] == 150 and "cores" in card["machine"] and card["validation"]
    assert check_zoo_model("tiny", out / "zoo") <= 1e-3
    assert main(["reproduce", "--profile", "zoo", "--out", str(out)]) == 0  # every stage done: nothing runs again
    assert main(["reproduce", "--profile", "zoo", "--out", str(out), "--zoo-models", "nope"]) == 2
