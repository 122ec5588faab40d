"""The drive-time engines: each row of a batch is bit-identical whatever the batch (the benchmark's determinism),
and the engines agree with the torch model within their precision."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from yawil import models
from yawil.policy.checkpoint import Norm
from yawil.policy.engine import make_engine, resolve_engine
from yawil.policy.inputs import InputSpec
from yawil.policy.runtime import resolve_runtime


def _batch(spec: InputSpec, n: int) -> list:  # type: ignore[type-arg]
    rng = np.random.default_rng(0)
    return [spec.from_frames([rng.integers(0, 256, (88, 200, 3), dtype=np.uint8) for _ in range(b)],
                             list(rng.random(b) * 8), [rng.standard_normal(15).astype(np.float32) for _ in range(b)],
                             [None] * b) for b in (n,)]


@pytest.mark.parametrize("engine, precision", [("onnxruntime", "fp32")])
def test_rows_do_not_depend_on_the_batch(engine: str, precision: str) -> None:
    model = models.create("yaw-guided", seed=0, dropout=0.0, aux=True, lead_stop=True).eval()
    runtime = resolve_runtime("cpu", precision, "auto")
    eng = make_engine(model, runtime, engine)
    spec = InputSpec.of(model, Norm(2.5, 1.5, [0.0] * 15, [1.0] * 15), runtime)
    x = _batch(spec, 5)[0]
    whole = eng.run(x)
    for i in range(5):
        row = eng.run(type(x)(x.image[i:i + 1], x.speed[i:i + 1], x.guidance[i:i + 1]))  # type: ignore[index]
        assert np.array_equal(row.actions[0], whole.actions[i]) and np.array_equal(row.aux[0], whole.aux[i])  # type: ignore[index]
    if engine == "onnxruntime":  # fp32 against the torch model itself
        with torch.no_grad():
            ref = x.forward(model)
        np.testing.assert_allclose(whole.actions, ref.actions.numpy(), atol=1e-5)


def test_engine_names_are_checked() -> None:
    runtime = resolve_runtime("cpu", "fp32", "auto")
    assert resolve_engine("auto", runtime) == ("onnxruntime", "fp32")
    assert resolve_engine("auto", resolve_runtime("cpu", "bf16", "auto")) == ("torch", "bf16")
    with pytest.raises(ValueError, match="engine 'tensorrt'"):
        resolve_engine("tensorrt", runtime)


_SETUP = """
import numpy as np, torch
from yawil import models
from yawil.guidance import GuidanceConfig
from yawil.policy.checkpoint import Norm
from yawil.policy.engine import make_engine
from yawil.policy.inputs import InputSpec
from yawil.policy.quantize import cache_dir, expert_calibration
from yawil.policy.runtime import resolve_runtime
model = models.create("yaw-guided", seed=0, dropout=0.0, aux=True).eval()
runtime = resolve_runtime("cpu", "fp32", "auto")
spec = InputSpec.of(model, Norm(2.5, 1.5, [0.0] * 15, [1.0] * 15), runtime)
rng = np.random.default_rng(0)
x = spec.from_frames([rng.integers(0, 256, (88, 200, 3), dtype=np.uint8) for _ in range(3)], [1.0, 2.0, 3.0],
                     [rng.standard_normal(15).astype(np.float32) for _ in range(3)], [None] * 3)
with torch.no_grad():
    ref = x.forward(model)

def check(eng, tolerance):
    whole = eng.run(x)
    one = eng.run(type(x)(x.image[1:2], x.speed[1:2], x.guidance[1:2]))
    assert np.array_equal(one.actions[0], whole.actions[1]), "rows depend on the batch"
    assert np.abs(whole.actions - ref.actions.numpy()).max() < tolerance
    return whole
"""


def _run(code: str, env: dict[str, str] | None = None) -> None:
    """`code` after the shared set-up, in a subprocess (a process that ran OpenVINO crashed at a later fork in this
    suite)."""
    pytest.importorskip("openvino")
    done = subprocess.run([sys.executable, "-c", _SETUP + textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-2000:]


def test_openvino_in_its_own_process() -> None:
    """The opt-in OpenVINO engine: rows independent of the batch, and within bf16's reach of the torch model."""
    _run("""
        check(make_engine(model, runtime, "openvino"), 1e-4)
    """)


def test_openvino_int8_in_its_own_process(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The int8 engine (NNCF, calibrated on expert frames): rows independent of the batch, close to the float
    model, and its graph cached by weights and calibration: a second engine loads it and drives the same."""
    pytest.importorskip("nncf")
    _run("""
        frames = expert_calibration(spec, GuidanceConfig(), frames=12)
        assert len(frames) == 12 and [f.shape for f in frames[0]] == [(1, 3, 88, 200), (1, 1), (1, 15)], frames[0]
        eng = make_engine(model, runtime, "openvino-int8", (lambda: frames, {"test": 1}))
        assert eng.label == "openvino-int8" and eng.option == "openvino-int8"
        assert len(list(cache_dir().glob("*.xml"))) == 1
        whole = check(eng, 0.1)
        def no_frames():
            raise AssertionError("the cached graph should have been loaded")
        again = make_engine(model, runtime, "openvino-int8", (no_frames, {"test": 1}))
        assert np.array_equal(again.run(x).actions, whole.actions)
    """, env={**os.environ, "XDG_CACHE_HOME": str(tmp_path)})


def test_int8_engine_names_its_missing_parts() -> None:
    runtime = resolve_runtime("cpu", "fp32", "auto")
    with pytest.raises(ValueError, match="runs on the CPU"):
        resolve_engine("openvino-int8", resolve_runtime("cpu", "fp32", "auto").__class__(torch.device("cuda"), "fp16", True))
    model = models.create("yaw-guided", seed=0, dropout=0.0).eval()
    pytest.importorskip("nncf")
    assert resolve_engine("openvino-int8", runtime) == ("openvino", "int8")
    with pytest.raises(ValueError, match="needs calibration frames"):
        make_engine(model, runtime, "openvino-int8")
