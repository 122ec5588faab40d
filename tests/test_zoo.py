"""The model zoo: compact packing (bf16, unused modules left out), `zoo:NAME` wherever a checkpoint is taken,
the probe that catches a silent change of preprocessing, and every shipped model against its card."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import yawil.zoo as zoo
from yawil.zoo.pack import check_zoo_model, pack

torch.set_num_threads(1)


@pytest.fixture
def packed(tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A YILRatt with the lead-stop head packed into a zoo of its own (the real zoo untouched)."""
    ckpt = tiny_checkpoint("yilratt", aux=True, lead_stop=True, spread=True).path
    root = tmp_path / "zoo"
    card = {"summary": "an untrained net", "drive": {"speed_control": "stop", "stop_release": 10.0}}
    pack(ckpt, "tiny", tiny_dataset(episodes=2, frames=5, k=15), card, root=root, count=3)
    monkeypatch.setattr(zoo, "ZOO_DIR", root)
    return ckpt


def test_pack_stores_bf16_without_unused_modules_and_loads_float32(packed: Path) -> None:
    from yawil.policy.checkpoint import load_checkpoint, model_from_checkpoint

    stored = torch.load(zoo.ZOO_DIR / "tiny" / zoo.WEIGHTS, weights_only=False)
    assert stored["omitted"] == ["backbone.layer4"]  # no output depends on it (compute_global=False)
    assert not any(k.startswith("backbone.layer4.") for k in stored["state_dict"])
    assert all(v.dtype == torch.bfloat16 for v in stored["state_dict"].values() if v.is_floating_point())
    assert "optimizer" not in stored and (zoo.ZOO_DIR / "tiny" / zoo.WEIGHTS).stat().st_size < packed.stat().st_size / 2
    model = model_from_checkpoint(load_checkpoint("zoo:tiny"))
    assert all(p.dtype == torch.float32 for p in model.parameters())
    full = model_from_checkpoint(load_checkpoint(packed)).state_dict()
    for k, v in model.state_dict().items():
        if not k.startswith("backbone.layer4.") and v.is_floating_point():
            assert torch.equal(v, full[k].to(torch.bfloat16).float()), k
    card = zoo.read_card("tiny")
    assert card["model_name"] == "yilratt" and card["probe"]["bf16_max_diff_from_fp32"] < 0.05
    assert len(card["probe"]["actions"]) == 3 and len(card["probe"]["aux"][0]) == 5


def test_probe_check_passes_and_catches_a_preprocessing_change(packed: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from yawil.policy.inputs import InputSpec

    assert check_zoo_model("tiny") < 1e-5
    original = InputSpec.image
    monkeypatch.setattr(InputSpec, "image", lambda self, image: original(self, image) * (255.0 / 256.0))
    with pytest.raises(ValueError, match="preprocessing"):
        check_zoo_model("tiny")


def test_zoo_names_resolve_everywhere_a_checkpoint_is_taken(packed: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.agent import Agent
    from yawil.bench.runner import AgentSpec, drive_options
    from yawil.cli import main

    assert Agent.from_checkpoint("zoo:tiny").name == "yilratt"
    spec = AgentSpec("zoo:tiny", speed_control="stop", stop_release=10.0).validate()
    assert spec.identity() == str((zoo.ZOO_DIR / "tiny" / zoo.WEIGHTS).resolve()) and spec.content_hash()
    args = type("A", (), {"agent": "zoo:tiny", "speed_control": False, "stop_release": 0.0})()
    assert drive_options(args) == ("stop", 10.0)  # the card's way of driving when none is given
    args.speed_control = "target"
    assert drive_options(args) == ("target", 0.0)
    assert main(["models", "--zoo"]) == 0 and "tiny" in capsys.readouterr().out
    assert main(["zoo", "check"]) == 0 and "zoo:tiny" in capsys.readouterr().out
    with pytest.raises(SystemExit, match=r"no such zoo model \(the zoo has: tiny\)"):
        main(["bench", "--agent", "zoo:nope", "--out", "x"])


def test_pack_refuses_bad_input(tmp_path: Path, tiny_checkpoint: Any, capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.cli import main

    ckpt = tiny_checkpoint("yaw-guided", guidance_dim=15).path
    card = tmp_path / "card.json"
    card.write_text("[1, 2]")
    assert main(["zoo", "pack", str(ckpt), "--name", "x", "--data", str(tmp_path), "--card", str(card)]) == 2
    assert "expected a JSON object" in capsys.readouterr().err
    card.write_text(json.dumps({}))
    assert main(["zoo", "pack", str(ckpt), "--name", "x", "--data", str(tmp_path / "none"), "--card", str(card)]) == 2
    assert "no episode files" in capsys.readouterr().err
    assert main(["zoo", "pack", str(ckpt), "--name", "../x", "--data", str(tmp_path), "--card", str(card)]) == 2


@pytest.mark.parametrize("name", zoo.zoo_names())
def test_every_shipped_model_gives_its_cards_outputs(name: str) -> None:
    """A shipped model's outputs on its probe frames equal its card's (to 1e-3): preprocessing and the model's
    code are what they were when the card was written."""
    assert check_zoo_model(name) <= 1e-3
    card = zoo.read_card(name)
    for field in ("commands", "commit", "data", "machine", "wall_s", "eval100", "drive"):
        assert field in card, f"zoo:{name}: its card lacks {field!r}"
    assert np.isfinite(card["probe"]["bf16_max_diff_from_fp32"])
