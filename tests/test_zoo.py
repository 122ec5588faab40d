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
    assert spec.identity() == "zoo:tiny"  # records name it the same on every machine, its hash beside it
    assert spec.content_hash() == zoo.read_card("tiny")["weights_sha256"]
    args = type("A", (), {"agent": "zoo:tiny", "speed_control": False, "stop_release": 0.0})()
    assert drive_options(args) == {"speed_control": "stop", "stop_release": 10.0, "stop_creep": 0.0,
                                   "stop_hold": 0.0, "stop_gate": 0.0, "light_hold": 0.0}  # the card's
    args.speed_control = "target"
    assert drive_options(args) == {"speed_control": "target", "stop_release": 0.0, "stop_creep": 0.0, "stop_hold": 0.0,
                                   "stop_gate": 0.0, "light_hold": 0.0}
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
    assert "fails yawil data check" in capsys.readouterr().err
    assert main(["zoo", "pack", str(ckpt), "--name", "../x", "--data", str(tmp_path), "--card", str(card)]) == 2


def test_pack_refuses_before_the_work_what_it_cannot_pack(tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """More --frames than the dataset has (it sampled on and on), a `stop` drive for a model without the aux head
    (accepted, then failing wherever it was driven), an --out under a file (the error named pack's temporary
    folder, after the work), and pack-only options given to `zoo check` (ignored): one line each, nothing made."""
    from yawil.cli import main

    data = tiny_dataset(episodes=2, frames=5, k=15)
    card = tmp_path / "card.json"
    card.write_text(json.dumps({"drive": {"speed_control": "stop"}}))
    (tmp_path / "afile").write_text("not a checkpoint")  # refused before the checkpoint is read

    def pack_with(ckpt: Path, *extra: str) -> tuple[int, str]:
        rc = main(["zoo", "pack", str(ckpt), "--name", "m", "--data", str(data), "--card", str(card), *extra])
        return rc, capsys.readouterr().err

    rc, err = pack_with(tmp_path / "afile", "--frames", "1000", "--out", str(tmp_path / "z"))
    assert rc == 2 and f"--frames 1000: {data} has " in err and "at most" in err, err
    for out in (tmp_path / "afile", tmp_path / "afile" / "z"):
        rc, err = pack_with(tmp_path / "afile", "--out", str(out))
        assert rc == 2 and f"its parent {tmp_path / 'afile'} is a file" in err and "packing" not in err, err
    rc, err = pack_with(tiny_checkpoint("yaw-guided", guidance_dim=15).path, "--frames", "2", "--out",
                        str(tmp_path / "z"))
    assert rc == 2 and "--card: drive" in err and "needs a model with an aux head" in err, err
    assert not (tmp_path / "z").exists()
    assert main(["zoo", "check", "--out", str(tmp_path / "z"), "--force"]) == 2
    assert "--out, --force apply to zoo pack only" in capsys.readouterr().err


def test_pack_checks_everything_first_and_replaces_only_with_force(tmp_path: Path, tiny_checkpoint: Any,
                                                                   tiny_dataset: Any, monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.cli import main

    ckpt = str(tiny_checkpoint("yaw-guided", guidance_dim=15).path)
    data = tiny_dataset(episodes=2, frames=5, k=15)
    card = tmp_path / "card.json"
    monkeypatch.chdir(tmp_path)

    def pack_with(fields: dict[str, Any], *extra: str) -> tuple[int, str]:
        card.write_text(json.dumps(fields))
        rc = main(["zoo", "pack", ckpt, "--name", "m", "--data", str(data), "--card", str(card), "--frames", "2",
                   *extra])
        return rc, capsys.readouterr().err

    for fields, text in [({"sumary": "typo"}, "unknown field(s) sumary"), ({"probe": {}}, "written by yawil zoo pack"),
                         ({"drive": {"speed_control": "fast"}}, "drive: speed_control='fast'"),
                         ({"drive": {"stop_release": 5}}, "applies to --speed-control stop"),
                         ({"training_seeds": {"one": {}}}, "training_seeds must map a training seed")]:
        rc, err = pack_with(fields)
        assert rc == 2 and text in err, err
    assert not (tmp_path / "zoo").exists()
    assert pack_with({"summary": "first"})[0] == 0  # the default --out is ./zoo, not the installed package
    first = (tmp_path / "zoo" / "m" / zoo.CARD).read_text()
    rc, err = pack_with({"summary": "second"})
    assert rc == 2 and "give --force" in err and (tmp_path / "zoo" / "m" / zoo.CARD).read_text() == first
    assert pack_with({"summary": "second"}, "--force")[0] == 0
    assert json.loads((tmp_path / "zoo" / "m" / zoo.CARD).read_text())["summary"] == "second"
    assert sorted(p.name for p in (tmp_path / "zoo").iterdir()) == ["m"]  # no temporary folder left
    import shutil

    data = Path(shutil.copytree(data, tmp_path / "data"))  # the fixture's dataset is shared: damage a copy
    next(iter(sorted(data.glob("**/*.h5")))).unlink()  # a dataset with a missing episode file
    rc, err = pack_with({"summary": "third"}, "--force", "--out", str(tmp_path / "z2"))
    assert rc == 2 and "fails yawil data check" in err and not (tmp_path / "z2").exists()


def test_damaged_weights_are_named_not_driven(packed: Path, tmp_path: Path) -> None:
    """A zoo model whose weights differ from its card's SHA-256, and a checkpoint whose weights differ from the
    digest stored in it, are refused in one line naming the file (flipped bytes otherwise load and drive)."""
    from yawil.policy.checkpoint import load_checkpoint, save_checkpoint

    ckpt = load_checkpoint(packed)
    damaged = tmp_path / "damaged.pt"
    save_checkpoint(ckpt, damaged)
    stored = torch.load(damaged, weights_only=False)
    name = next(k for k, v in stored["state_dict"].items() if v.is_floating_point() and v.numel() > 8)
    stored["state_dict"][name].view(-1)[3] += 1e26
    torch.save(stored, damaged)
    with pytest.raises(ValueError, match="damaged.pt: its weights do not match the SHA-256"):
        load_checkpoint(damaged)
    weights = zoo.ZOO_DIR / "tiny" / zoo.WEIGHTS
    raw = bytearray(weights.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    weights.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="differs from its card's weights_sha256"):
        load_checkpoint("zoo:tiny")


@pytest.mark.parametrize("name", zoo.zoo_names())
def test_every_shipped_model_gives_its_cards_outputs(name: str) -> None:
    """A shipped model's outputs on its probe frames equal its card's (to 1e-3): preprocessing and the model's
    code are what they were when the card was written."""
    assert check_zoo_model(name) <= 1e-3
    card = zoo.read_card(name)
    for field in ("commands", "commit", "data", "machine", "wall_s", "drive"):
        assert field in card, f"zoo:{name}: its card lacks {field!r}"
    assert "eval100" in card or "results" in card, f"zoo:{name}: its card holds no benchmark figure"
    assert np.isfinite(card["probe"]["bf16_max_diff_from_fp32"])


def test_the_onnx_example_drives_as_the_torch_agent_on_recorded_frames(packed: Path, tmp_path: Path) -> None:
    """examples/onnx_drive.py (ONNX Runtime, preprocessing from the metadata alone, the card's drive settings from
    the metadata) gives the torch agent's controls on the probe frames, frame after frame of one episode."""
    import importlib.util

    from yawil.agent import Agent
    from yawil.learn.export import export_onnx
    from yawil.policy.probe import read_probe

    spec = importlib.util.spec_from_file_location("onnx_drive", Path(__file__).parents[1] / "examples" / "onnx_drive.py")
    assert spec is not None and spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    onnx_path = export_onnx("zoo:tiny", tmp_path / "tiny.onnx")
    driver = example.OnnxDriver(str(onnx_path))
    assert (driver.drive.speed_control, driver.drive.stop_release) == ("stop", 10.0)  # from the card, via metadata
    agent = Agent.from_checkpoint("zoo:tiny", precision="fp32", channels_last="off", engine="torch")
    probe = read_probe(zoo.ZOO_DIR / "tiny")
    for i in range(len(probe["speed"])):
        speed = float(probe["speed"][i])
        x = agent.spec.from_frame(probe["image"][i], speed, probe["guidance"][i], int(probe["command"][i]))
        out = agent.engine.run(x)
        d = agent.drive.decide(out.actions[0], out.aux[0], agent._speed_of, agent.states[0], max(speed, 0.0))
        want = agent.drive.post(d.actions, speed)
        got = driver.step(probe["image"][i], speed, probe["guidance"][i], int(probe["command"][i]))
        assert np.allclose([got.steer, got.throttle, got.brake], [want.steer, want.throttle, want.brake], atol=1e-4)


def test_damaged_resume_state_is_named_and_pack_force_replaces_only_a_zoo_model(
        tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any) -> None:
    """A flipped byte in the optimiser state (weights intact) is refused on load, since --resume would train on it;
    `zoo pack --force` never replaces a folder that is not a zoo model (a dataset, a run, a user file)."""
    from yawil.policy.checkpoint import load_checkpoint, save_checkpoint

    ckpt = load_checkpoint(tiny_checkpoint("yaw-guided", guidance_dim=15).path)
    ckpt["optimizer"] = {"state": {0: {"exp_avg": torch.ones(8)}}, "param_groups": [{"lr": 1e-3}]}
    save_checkpoint(ckpt, tmp_path / "last.pt")
    assert load_checkpoint(tmp_path / "last.pt")["optimizer"]["param_groups"][0]["lr"] == 1e-3
    stored = torch.load(tmp_path / "last.pt", weights_only=False)
    stored["optimizer"]["state"][0]["exp_avg"][3] = 4.7e8
    torch.save(stored, tmp_path / "last.pt")
    with pytest.raises(ValueError, match="optimiser or resume state does not match"):
        load_checkpoint(tmp_path / "last.pt")
    data = tiny_dataset(episodes=2, frames=5, k=15)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "best.pt").write_bytes(b"weights")
    (tmp_path / "mine.txt").write_text("a user's file")
    for name in ("run", "mine.txt"):
        with pytest.raises(ValueError, match="is not a zoo model"):
            pack(tiny_checkpoint("yaw-guided", guidance_dim=15).path, name, data, {"summary": "x"}, root=tmp_path,
                 count=2, force=True)
    assert (tmp_path / "run" / "best.pt").read_bytes() == b"weights" and (tmp_path / "mine.txt").is_file()


def test_a_training_checkpoint_with_resume_state_packs(tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any) -> None:
    """A checkpoint `train` writes carries its optimiser and the digest of it; the pack drops both (it kept the
    digest, so every training checkpoint was refused as damaged)."""
    from yawil.policy.checkpoint import load_checkpoint, save_checkpoint

    ckpt = load_checkpoint(tiny_checkpoint("yilratt", aux=True).path)
    trained = tmp_path / "last.pt"
    save_checkpoint({**ckpt, "optimizer": {"state": {}, "param_groups": [{"lr": 1e-3}]}}, trained)
    assert "resume_sha256" in torch.load(trained, weights_only=False)
    pack(trained, "trained", tiny_dataset(episodes=2, frames=5, k=15), {"summary": "x"}, root=tmp_path / "zoo", count=2)
    packed = load_checkpoint(tmp_path / "zoo" / "trained" / "model.pt")
    assert "optimizer" not in packed and "resume_sha256" not in packed
