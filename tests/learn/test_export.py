"""ONNX export: named inputs, dynamic batch, metadata, and agreement with torch through onnxruntime."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from yawil.cli import main
from yawil.learn.export import check_onnx, export_onnx

torch.set_num_threads(2)
GC = {"spacing": 2.0, "count": 4, "reference": "route"}


def _checkpoint(tiny_checkpoint: Any, name: str, **cfg: Any) -> Path:
    return tiny_checkpoint(name, guidance=GC, speed=(2.0, 1.0), train_config={}, **cfg).path


def test_cil_export_agrees_with_torch(tmp_path: Path, tiny_checkpoint: Any, capsys: pytest.CaptureFixture[str]) -> None:
    ckpt = _checkpoint(tiny_checkpoint, "cil")
    out = tmp_path / "cil.onnx"
    assert main(["export", str(ckpt), "--onnx", str(out), "--check"]) == 0
    printed = capsys.readouterr().out
    assert "max abs difference" in printed and "FAIL" not in printed
    proto = onnx.load(str(out))
    assert [i.name for i in proto.graph.input] == ["image", "speed", "command"]
    assert [o.name for o in proto.graph.output] == ["actions", "pred_speed", "branches"]  # every branch, for a consumer
    assert max(op.version for op in proto.opset_import if op.domain in ("", "ai.onnx")) >= 17
    meta = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(meta["yawil.norm"])["speed_mean"] == 2.0
    agreement = check_onnx(ckpt, out, batch=3, seed=7)  # another batch size: the batch is dynamic
    assert [a.output for a in agreement] == ["actions", "pred_speed", "branches"]
    assert all(a.max_abs_diff <= 1e-4 for a in agreement)
    # the branch is chosen by the command input inside the graph
    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    x = {"image": np.random.default_rng(0).random((2, 3, 88, 200), dtype=np.float32),
         "speed": np.zeros((2, 1), np.float32)}  # fmt: skip
    a0 = sess.run(["actions"], {**x, "command": np.array([0, 0])})[0]
    a1 = sess.run(["actions"], {**x, "command": np.array([1, 1])})[0]
    assert not np.allclose(a0, a1)


def test_guided_export_has_guidance_input(tmp_path: Path, tiny_checkpoint: Any) -> None:
    ckpt = _checkpoint(tiny_checkpoint, "yaw-guided", guidance_dim=4)
    out = export_onnx(ckpt, tmp_path / "g.onnx")
    assert [i.name for i in onnx.load(str(out)).graph.input] == ["image", "speed", "guidance"]
    assert all(a.max_abs_diff <= 1e-4 for a in check_onnx(ckpt, out))


def test_export_errors(tmp_path: Path, tiny_checkpoint: Any, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(tmp_path / "none.pt"), "--onnx", str(tmp_path / "x.onnx")]) == 2
    assert "none.pt" in capsys.readouterr().err
    with pytest.raises(ValueError, match="opset"):
        export_onnx(_checkpoint(tiny_checkpoint, "cil"), tmp_path / "x.onnx", opset=13)
    assert not (tmp_path / "x.onnx").exists()
    assert main(["export", str(_checkpoint(tiny_checkpoint, "cil")), "--onnx", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err


def test_a_failed_check_writes_no_model(tmp_path: Path, tiny_checkpoint: Any, capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    from yawil.learn.export import Agreement

    monkeypatch.setattr(Agreement, "ok", lambda self, tolerance, attention_tolerance: False)  # a check that fails
    ckpt = _checkpoint(tiny_checkpoint, "cil")
    out = tmp_path / "cil.onnx"
    assert main(["export", str(ckpt), "--onnx", str(out), "--check"]) == 1
    printed = capsys.readouterr().out
    assert "FAIL" in printed and "not written" in printed and not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_yilratt_export_with_attention_outputs(tmp_path: Path, tiny_checkpoint: Any) -> None:
    ckpt = _checkpoint(tiny_checkpoint, "yilratt", guidance_dim=4)
    out = export_onnx(ckpt, tmp_path / "y.onnx")
    names = [o.name for o in onnx.load(str(out)).graph.output]
    assert names[:2] == ["actions", "pred_speed"] and len(names) > 2 and names[2] == "attention_0"
    agreement = check_onnx(ckpt, out, batch=2)
    assert all(a.ok(1e-4, 1e-3) for a in agreement) and agreement[0].max_abs_diff <= 1e-4


def test_check_on_dataset_frames_and_non_finite_outputs_fail(tmp_path: Path, tiny_checkpoint: Any,
                                                            tiny_dataset: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """--check compares on real frames too (--data, or a zoo model's probe), and an output that is inf or NaN in
    both engines (a damaged model agrees with itself perfectly) fails the check."""
    from yawil.policy.checkpoint import load_checkpoint, save_checkpoint

    ckpt = tiny_checkpoint("yaw-guided", guidance_dim=15).path
    data = tiny_dataset(episodes=2, frames=5, k=15)
    out = tmp_path / "g.onnx"
    assert main(["export", str(ckpt), "--onnx", str(out), "--check", "--data", str(data), "--batch", "3"]) == 0
    printed = capsys.readouterr().out
    assert "real:actions" in printed and "FAIL" not in printed
    broken = load_checkpoint(ckpt)
    name = next(k for k, v in broken["state_dict"].items() if k.endswith("weight") and v.is_floating_point())
    broken["state_dict"][name].fill_(float("inf"))
    save_checkpoint(broken, tmp_path / "broken.pt")
    assert main(["export", str(tmp_path / "broken.pt"), "--onnx", str(tmp_path / "b.onnx"), "--check"]) == 1
    assert "FAIL" in capsys.readouterr().out and not (tmp_path / "b.onnx").exists()
    assert main(["export", str(ckpt), "--onnx", str(tmp_path / "c.onnx"), "--batch", "0"]) == 2
    assert "--batch 0: expected a batch size from 1 to 256" in capsys.readouterr().err
