"""The drive-time engines side by side on one model: forward time per frame, and how far each one's actions are
from the float32 model on frames the expert drives.

    .venv/bin/python benchmarks/engines.py [--agent zoo:yilratt-dagger-dense3] [--engines torch,openvino,openvino-int8]
        [--frames 200] [--threads 1] [--batches 1,8]

Test frames: `--frames` frames of town01 driven by the expert with seed 1 (`yawil.policy.quantize.expert_calibration`;
the int8 engine calibrates on seed 0's, so it is not judged on the frames it was calibrated on). For each engine and
batch size: the median time per frame of the forward pass (`Engine.run`, inputs prepared beforehand) over
`--runs` passes, whether each row of a batch equals the same frame at batch 1 bit for bit, and the mean and 99th
percentile of |action - float32 action| per action (steer, throttle, brake) against torch fp32, and on how many
frames the two outputs the drive decides by (the lead-stop class and the light output, at P 0.5) fall on the other
side of the threshold from fp32 (with the fp32 and engine counts of lead-stop positives). Prints a markdown
table with the CPU model and the load average.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from yawil.agent import Agent  # noqa: E402
from yawil.models.base import LEAD_STOP_FIRES  # noqa: E402
from yawil.policy.drive import LEAD_STOP_OUTPUT, LIGHT_FIRES, LIGHT_OUTPUT  # noqa: E402
from yawil.policy.inputs import ModelInputs  # noqa: E402
from yawil.policy.quantize import expert_calibration  # noqa: E402


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown CPU"


def stack(rows: list[list[np.ndarray]], names: list[str]) -> ModelInputs:
    return ModelInputs(**{n: torch.from_numpy(np.concatenate([r[i] for r in rows])) for i, n in enumerate(names)})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agent", default="zoo:yilratt-dagger-dense3")
    ap.add_argument("--engines", default="torch,onnxruntime,openvino,openvino-int8")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--batches", default="1,8")
    ap.add_argument("--runs", type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    batches = [int(b) for b in args.batches.split(",")]
    ref_agent = Agent.from_checkpoint(args.agent, precision="fp32", channels_last="off", engine="torch")
    names = ref_agent.spec.names()
    frames = expert_calibration(ref_agent.spec, ref_agent.guidance_config, frames=args.frames, seed=1)
    ref_out = [ref_agent.engine.run(stack([f], names)) for f in frames]
    ref = np.concatenate([o.actions for o in ref_out])
    ref_aux = None if ref_out[0].aux is None else np.concatenate([o.aux for o in ref_out])
    load0 = os.getloadavg()
    print(f"{args.agent}, {args.frames} town01 expert frames (seed 1), {args.threads} thread(s); CPU: {cpu_model()}, "
          f"{os.cpu_count()} cores; load average before: {load0[0]:.2f}")
    print("\n| engine | batch | ms per frame | rows = batch 1 | mean abs diff vs fp32 (steer, throttle, brake) | p99 | "
          "decisions moved: lead-stop, light |")
    print("|---|---|---|---|---|---|---|")
    for name in args.engines.split(","):
        agent = Agent.from_checkpoint(args.agent, engine=name)
        engine = agent.engine
        single = None
        for b in batches:
            runs = [engine.run(stack(frames[i:i + b], names)) for i in range(0, len(frames) - len(frames) % b, b)]
            out = np.concatenate([r.actions for r in runs])
            moved = "n/a (no aux head)"
            if ref_aux is not None and ref_aux.shape[1] > LEAD_STOP_OUTPUT:
                aux = np.concatenate([r.aux for r in runs])
                fires = [1 / (1 + np.exp(-a[:, [LEAD_STOP_OUTPUT, LIGHT_OUTPUT]])) > (LEAD_STOP_FIRES, LIGHT_FIRES)
                         for a in (aux, ref_aux[:len(aux)])]  # the drive's own thresholds on the logits
                flips = (fires[0] != fires[1]).sum(0)
                moved = f"{flips[0]} of {len(aux)} ({fires[1][:, 0].sum()} -> {fires[0][:, 0].sum()}), {flips[1]}"
            if single is None:
                single = out
            same = np.array_equal(out, single[:len(out)])
            x = stack(frames[:b], names)
            for _ in range(3):
                engine.run(x)
            times = []
            for _ in range(args.runs):
                t = time.perf_counter()
                engine.run(x)
                times.append((time.perf_counter() - t) / b * 1e3)
            diff = np.abs(out - ref[:len(out)])
            print(f"| {engine.label} | {b} | {statistics.median(times):.2f} | {'yes' if same else 'no'} | "
                  f"{', '.join(f'{v:.4f}' for v in diff.mean(0))} | "
                  f"{', '.join(f'{v:.4f}' for v in np.percentile(diff, 99, axis=0))} | {moved} |", flush=True)
    load1 = os.getloadavg()
    print(f"\nload average after: {load1[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
