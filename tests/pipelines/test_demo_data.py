"""The demo collects with the zoo model's guidance reference, and refuses data of another left by an earlier demo."""

from __future__ import annotations

from pathlib import Path

import pytest

from yawil.pipelines.demo import DemoBudget, _mark, demo_guidance, run_demo
from yawil.zoo import read_card


def test_the_demo_collects_with_the_reference_its_zoo_model_learned() -> None:
    card = read_card(DemoBudget.zoo_model)
    assert demo_guidance(card).reference == card["data"]["guidance_reference"] == "ego"
    assert demo_guidance({"data": {"town": "town01"}}).reference == "route"  # a card naming none: the paper's


def test_data_of_an_earlier_demo_with_another_reference_is_refused_before_any_stage(tmp_path: Path) -> None:
    _mark(tmp_path, "collect", {"seconds": 1.0, "frames": 10})  # an earlier demo's marker: no reference (route)
    with pytest.raises(ValueError, match=r"'route' yaw reference, but zoo:yilratt-dagger-dense3 needs 'ego'; remove"):
        run_demo(tmp_path, DemoBudget())
    assert not (tmp_path / "stages" / "train_baseline.json").exists()
