"""Post-training int8 quantization of a driving network for OpenVINO (NNCF), calibrated on expert frames.

    graph = int8_graph(graph, calibration, graph_key(graph, about))   # an OpenVINO model, int8 convolutions

Why: the forward pass is about two thirds of an evaluation step on a CPU (docs/performance.md); with int8
convolutions (AVX512-VNNI, AMX) OpenVINO runs YILRatt's forward in 7 ms against 12.5 ms in bf16 on the 2-core
EPYC. Only the convolutions are quantized: the attention, the guidance and speed MLPs and the heads stay in the
float precision hint. Quantizing every operation moved the zoo YILRatt's steer by 0.05 on average (p99 0.55) on
town01 frames; the convolutions alone by 0.0016 (p99 0.014), bf16 by 0.0002 (docs/decisions.md).

Calibration (`expert_calibration`): CALIBRATION_FRAMES frames evenly spaced over the first episode(s) that the
expert drives in town01 with the training weathers and traffic, `yawil.data.collect` with seed 0 and the model's
own guidance config: the training distribution, made by the package itself (no data to ship or download), the
same frames on every machine. NNCF's statistics and bias correction are deterministic, so the quantized graph is
a function of the weights, the frames and the library versions: it is cached under `cache_dir()` by a key of
those (written atomically), which lets a benchmark's workers load what its parent's validation made.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from yawil.fileio import write_atomic

CALIBRATION_FRAMES = 300
CALIBRATION_SEED = 0
IGNORED_TYPES = ("MatMul", "Softmax", "Multiply", "Add")  # all but the convolutions stay in float


def cache_dir() -> Path:
    """Where quantized graphs are kept: $XDG_CACHE_HOME/yawil/int8 (default ~/.cache/yawil/int8)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "yawil" / "int8"


def require_nncf() -> None:
    """A clear line where the quantizer is missing (it is opt-in, like OpenVINO)."""
    import importlib.util

    for package in ("openvino", "nncf"):
        if importlib.util.find_spec(package) is None:
            raise ValueError(f"engine 'openvino-int8' needs the {package} package: pip install openvino nncf")


def graph_digest(graph: Any) -> str:
    """SHA-256 of an OpenVINO model as saved (float weights, and the structure without the node names, which the
    converter numbers per process): what is quantized, exactly. A model's state dict is not: it may hold layers
    the graph never runs (an unused, randomly initialised layer4)."""
    import openvino as ov

    h = hashlib.sha256()
    with tempfile.TemporaryDirectory(prefix="yawil-graph-") as tmp:
        ov.save_model(graph, str(Path(tmp) / "g.xml"), compress_to_fp16=False)
        h.update(re.sub(rb' name="[^"]*"', b"", (Path(tmp) / "g.xml").read_bytes()))
        h.update((Path(tmp) / "g.bin").read_bytes())
    return h.hexdigest()


def graph_key(graph: Any, calibration: dict[str, Any]) -> str:
    """The cache key of a quantized graph: the float graph, the calibration and the library versions."""
    import nncf
    import openvino as ov

    blob = json.dumps({"graph": graph_digest(graph), "calibration": calibration,
                       "openvino": ov.get_version(), "nncf": nncf.__version__, "ignored": IGNORED_TYPES},
                      sort_keys=True, default=float)
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


def int8_graph(graph: Any, calibration: Callable[[], list[list[np.ndarray]]], key: str,
               cache: Path | None = None) -> Any:
    """`graph` (an OpenVINO model of batch 1) with int8 convolutions: loaded from the cache when `key` is there,
    else quantized on `calibration()` (a list of input lists, one frame each) and saved."""
    import nncf
    import openvino as ov

    folder = cache or cache_dir()
    xml, weights = folder / f"{key}.xml", folder / f"{key}.bin"
    core = ov.Core()
    if xml.is_file() and weights.is_file():
        return core.read_model(str(xml), str(weights))
    frames = calibration()
    nncf.set_log_level(logging.WARNING)  # its INFO lines list every operation left in float: noise to a bench user
    quantized = nncf.quantize(graph, nncf.Dataset(frames), subset_size=len(frames), model_type=None,
                              fast_bias_correction=True, ignored_scope=nncf.IgnoredScope(types=list(IGNORED_TYPES), validate=False))
    with tempfile.TemporaryDirectory() as tmp:  # OpenVINO writes a pair of files: each is renamed in, .xml last
        ov.save_model(quantized, str(Path(tmp) / "q.xml"), compress_to_fp16=False)
        write_atomic(weights, (Path(tmp) / "q.bin").read_bytes())
        write_atomic(xml, (Path(tmp) / "q.xml").read_bytes())
    return core.read_model(str(xml), str(weights))


def expert_calibration(spec: Any, guidance: Any, frames: int = CALIBRATION_FRAMES,
                       seed: int = CALIBRATION_SEED) -> list[list[np.ndarray]]:
    """`frames` network inputs (image, speed, guidance/command as the model takes them; batch 1 each) of frames
    the expert drives in town01 (see the module's docstring). `spec`: the agent's `InputSpec`; `guidance`: its
    `GuidanceConfig`, so the guidance field is the one the model was trained on."""
    import torch

    from yawil.data.collect import collect
    from yawil.data.dataset import DrivingDataset

    with tempfile.TemporaryDirectory(prefix="yawil-int8-") as tmp:
        collect(Path(tmp) / "calibration", town="town01", weathers="train", frames=frames, workers=1, seed=seed,
                guidance=guidance, progress=False)
        data = DrivingDataset(Path(tmp) / "calibration")
        picks = np.linspace(0, len(data) - 1, frames).round().astype(int)
        out = []
        for i in picks:
            x = spec.from_batch(torch.utils.data.default_collate([data[int(i)]]))
            out.append([np.ascontiguousarray(t.detach().cpu().numpy()) for t in x.named().values()])  # as run() feeds
        return out
