"""`yawil export CHECKPOINT --onnx out.onnx [--check]`: a trained model as an ONNX graph.

Inputs (dynamic batch), those of the model-input contract (`yawil.policy.inputs.ModelInputs`, the agent's and the
trainer's): `image` float32 [B, 3, H, W] in [0, 1]; `speed` float32 [B, 1] normalised; then `guidance` float32
[B, D] normalised (guided models) or `command` int64 [B] branch index (CIL, CILRS).
Outputs (`yawil.policy.engine.graph_outputs`, the graph the drive-time engines run): `actions` [B, 3], `pred_speed`
[B, 1] (normalised; ONNX forbids reusing the input name), `aux` [B, n] for models built with aux heads (target
speed, lead vehicle, light, lead-stop logit: `yawil.models.base.AUX_NAMES`), `branches` [B, 4, 3] for CIL and
CILRS, and `attention_i` [B, h, w] for YILRatt.
The checkpoint's normalisation and guidance config are stored in the model's metadata (`yawil.norm`,
`yawil.guidance_config`, `yawil.model`) so that a consumer can reproduce the agent's preprocessing.

Export uses torch's TorchScript-based exporter (`dynamo=False`): the torch.export one needs the
`onnxscript` package, which the project does not depend on. Only argparse is imported at module level.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

OPSET = 17


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "export", help="export a checkpoint to ONNX", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("checkpoint", help="a yawil checkpoint (best.pt / last.pt) or zoo:NAME")
    p.add_argument("--onnx", required=True, metavar="OUT", help="ONNX file to write")
    p.add_argument("--force", action="store_true", help="replace an existing output file (never one inside a dataset, run, results or zoo folder)")
    p.add_argument("--opset", type=int, default=OPSET, help=f"ONNX opset (17 to the exporter's newest, 20 with today's torch; default {OPSET})")
    p.add_argument("--check", action="store_true", help="compare onnxruntime with torch on a random batch and on "
                   "real frames (a zoo model's probe frames, or --data's); a non-finite output fails the check")
    p.add_argument("--data", default=None, metavar="DIR", help="--check: a dataset to draw the real frames from "
                   "(default: the zoo model's probe frames; none for other checkpoints)")
    p.add_argument("--batch", type=int, default=4, help="batch size of the --check comparison (default 4)")
    p.add_argument(
        "--tolerance", type=float, default=1e-4,
        help="max abs difference --check accepts on actions and speed (1e-4, times |value| when above 1)",
    )  # fmt: skip
    p.add_argument(
        "--attention-tolerance", type=float, default=1e-3, help="max abs difference on attention maps (1e-3)"
    )
    return p


def input_names(model: Any) -> list[str]:
    """The graph's inputs in order (`yawil.policy.inputs.input_names`)."""
    from yawil.policy.inputs import input_names as names_of

    return names_of(model)


def export_onnx(checkpoint: str | Path, onnx_path: str | Path, opset: int = OPSET) -> Path:
    """Write the ONNX file atomically (temporary file, then rename) and return its path."""
    import json
    import warnings

    import onnx
    import torch

    from yawil.fileio import atomic_path
    from yawil.policy.checkpoint import load_checkpoint, model_from_checkpoint
    from yawil.policy.engine import graph_module, graph_outputs, image_size

    try:  # the TorchScript exporter's newest opset (dynamo=False below); a larger one ended in a traceback
        from torch.onnx._constants import ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET as newest
    except ImportError:
        newest = 20
    if not 17 <= opset <= newest:
        raise ValueError(f"--opset {opset}: expected 17 to {newest}")
    ckpt = load_checkpoint(checkpoint)
    model = model_from_checkpoint(ckpt).eval()
    names = input_names(model)
    from yawil.policy.inputs import example_inputs

    example = example_inputs(model, 2, image_size=image_size(model))
    outputs = graph_outputs(model, image_size(model))
    dynamic = {name: {0: "batch"} for name in names + outputs}
    path = Path(onnx_path)
    with atomic_path(path) as tmp_path:
        tmp = str(tmp_path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter is deprecated, not gone
            warnings.simplefilter("ignore", torch.jit.TracerWarning)  # shape checks traced as constants: intended
            torch.onnx.export(
                graph_module(model), tuple(example[n] for n in names), tmp,
                input_names=names, output_names=outputs, dynamic_axes=dynamic, opset_version=opset, dynamo=False,
            )  # fmt: skip
        proto = onnx.load(tmp)
        meta = {
            "yawil.model": json.dumps({"name": ckpt["model_name"], "config": ckpt["model_config"]}, default=str),
            "yawil.norm": json.dumps(ckpt["norm"]),
            "yawil.guidance_config": json.dumps(ckpt["guidance_config"]),
            "yawil.guidance_kind": json.dumps(ckpt["guidance_kind"]),
            "yawil.drive": json.dumps(_drive(str(checkpoint))),
        }
        for key, value in meta.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.checker.check_model(proto)
        onnx.save(proto, tmp)
    return path


def _drive(checkpoint: str) -> dict[str, Any]:
    """How the agent drives this model (`yawil.policy.drive.DriveSettings`): a zoo model's card settings, else the
    defaults, with the post-processing rules, so that an ONNX consumer can drive it as `yawil bench` does."""
    from dataclasses import asdict

    from yawil.policy.drive import DriveSettings
    from yawil.zoo import PREFIX, card_drive

    settings = DriveSettings()
    if checkpoint.startswith(PREFIX):
        settings = DriveSettings.from_options(card_drive(checkpoint))
    return {**asdict(settings), "reference": "yawil.policy.drive (decide, PostProcess); docs/training.md"}


@dataclass(frozen=True)
class Agreement:
    """Largest absolute difference of one output, and the largest |value| torch gave for it."""

    output: str
    max_abs_diff: float
    max_abs_ref: float
    finite: bool = True  # every value of both finite (a damaged model gives inf or NaN that agree perfectly)

    @property
    def is_attention(self) -> bool:
        """An attention map (`attention_i`, or `real:attention_i` on real frames)."""
        return self.output.split(":")[-1].startswith("attention")

    def ok(self, tolerance: float, attention_tolerance: float) -> bool:
        """Driving outputs: `tolerance` scaled by the output's magnitude when it exceeds 1 (predicted speed
        is in normalised units, float32 keeps ~7 digits). Attention maps: `attention_tolerance`, since a
        sharp softmax turns 1e-5 differences of the logits of a 34-layer network into ~1e-4 of the map."""
        if not self.finite:
            return False
        if self.is_attention:
            return self.max_abs_diff <= attention_tolerance
        return self.max_abs_diff <= tolerance * max(1.0, self.max_abs_ref)


def real_frames(checkpoint: str, model: Any, norm: Any, data: str | Path | None, count: int) -> dict[str, Any] | None:
    """Model inputs of real camera frames through the agent's input contract (fp32 on the CPU): `data`'s frames,
    else a zoo model's probe frames, else None."""
    from yawil.policy.inputs import InputSpec
    from yawil.policy.probe import read_probe, sample_probe
    from yawil.policy.runtime import resolve_runtime
    from yawil.zoo import PREFIX, zoo_dir

    if data is None and not checkpoint.startswith(PREFIX):
        return None
    spec = InputSpec.of(model, norm, resolve_runtime("cpu", "fp32", "off"))
    probe = sample_probe(Path(data), spec.kind, count) if data is not None else read_probe(
        zoo_dir(checkpoint[len(PREFIX):]))
    n = len(probe["speed"])
    inputs = spec.from_frames(list(probe["image"]), [float(s) for s in probe["speed"]],
                              [probe["guidance"][i] if spec.kind is not None else None for i in range(n)],
                              [int(probe["command"][i]) if spec.uses_command else None for i in range(n)])
    return dict(inputs.named())


def check_onnx(checkpoint: str | Path, onnx_path: str | Path, batch: int = 4, seed: int = 0,
               data: str | Path | None = None) -> list[Agreement]:
    """Run onnxruntime and torch (fp32) on the same inputs and compare every output: a random batch, and real
    frames where there are some (`real_frames`; those rows are named real:OUTPUT)."""
    import numpy as np
    import onnxruntime as ort
    import torch

    from yawil.policy.checkpoint import Norm, load_checkpoint, model_from_checkpoint
    from yawil.policy.engine import graph_module, image_size

    ckpt = load_checkpoint(checkpoint)
    model = model_from_checkpoint(ckpt).eval()
    names = input_names(model)
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    outputs = [o.name for o in session.get_outputs()]
    from yawil.policy.inputs import example_inputs

    batches = [("", example_inputs(model, batch, seed=seed, image_size=image_size(model)))]
    real = real_frames(str(checkpoint), model, Norm.from_dict(ckpt["norm"]), data, batch)
    if real is not None:
        batches.append(("real:", real))
    rows = []
    for prefix, x in batches:
        with torch.no_grad():
            ref = graph_module(model)(*(x[n].float() if x[n].is_floating_point() else x[n] for n in names))
        got = session.run(None, {n: x[n].contiguous().numpy() for n in names})
        if len(got) != len(ref):
            raise ValueError(f"{onnx_path} has {len(got)} outputs, the torch model gives {len(ref)}")
        for name, g, r in zip(outputs, got, ref, strict=True):
            r = r.numpy()
            finite = bool(np.isfinite(g).all() and np.isfinite(r).all())
            rows.append(Agreement(prefix + name, float(np.max(np.abs(g - r))) if finite else math.inf,
                                  float(np.max(np.abs(r))) if finite else math.inf, finite))
    return rows


MAX_CHECK_BATCH = 256  # the --check comparison's frames: enough for any batch-dependence, small in memory


def run(args: argparse.Namespace) -> int:
    from yawil.fileio import check_output_file

    final = Path(args.onnx)
    if not 1 <= args.batch <= MAX_CHECK_BATCH:  # a batch of 100,000 frames took 21 GB and the OOM killer
        print(f"yawil export: --batch {args.batch}: expected a batch size from 1 to {MAX_CHECK_BATCH}", file=sys.stderr)
        return 2
    if args.data is not None and not args.check:  # only the check reads the frames: it would do nothing
        print(f"yawil export: --data {args.data}: applies to --check (the real frames it compares on); give "
              "--check too, or leave --data out", file=sys.stderr)
        return 2
    from yawil.cliargs import given_options

    for name, (flag, value) in given_options(args, add_parser, "export").items():
        if name in ("batch", "tolerance", "attention_tolerance") and not args.check:  # the check's alone: no effect
            print(f"yawil export: {flag} {value}: applies to --check; give --check too, or leave it out", file=sys.stderr)
            return 2
    for name in ("tolerance", "attention_tolerance"):  # checked before the export, not after its comparison
        v = getattr(args, name)
        if not math.isfinite(v) or v < 0:
            print(f"yawil export: --{name.replace('_', '-')} {v}: expected a number >= 0", file=sys.stderr)
            return 2
    try:
        check_output_file(final, "--onnx", args.force)
    except ValueError as err:
        print(f"yawil export: {err}", file=sys.stderr)
        return 2
    # with --check the graph is checked under a temporary name and takes its place only if it passes
    target = final.with_name(f".{final.name}.unchecked") if args.check else final
    try:
        path = export_onnx(args.checkpoint, target, args.opset)
    except (ValueError, FileNotFoundError) as err:
        print(f"yawil export: {err}", file=sys.stderr)
        return 2
    if not args.check:
        print(f"wrote {path}")
        return 0
    try:
        results = check_onnx(args.checkpoint, path, batch=args.batch, data=args.data)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    all_ok = True
    for a in results:
        ok = a.ok(args.tolerance, args.attention_tolerance)
        all_ok &= ok
        print(f"  {a.output}: max abs difference {a.max_abs_diff:.3g} (max |value| {a.max_abs_ref:.3g}) {'ok' if ok else 'FAIL'}")
    worst = max(a.max_abs_diff for a in results if not a.is_attention)
    if not any(a.output.startswith("real:") for a in results):
        print("  (random inputs only: give --data DIR to compare on dataset frames too)")
    print(
        f"onnxruntime vs torch: max abs difference {worst:.3g} on actions/speed "
        f"({'ok' if all_ok else 'FAIL'}; tolerance {args.tolerance:g}, attention {args.attention_tolerance:g})"
    )
    if not all_ok:
        path.unlink(missing_ok=True)
        print(f"not written: {final} (the check failed)")
        return 1
    os.replace(path, final)
    print(f"wrote {final}")
    return 0
