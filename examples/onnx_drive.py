"""Drive with an exported yawil model in ONNX Runtime, as `yawil bench` drives it.

    yawil export zoo:yilratt-dagger-dense3 --onnx yilratt.onnx
    python examples/onnx_drive.py yilratt.onnx yilratt-dagger-dense3   # drives that zoo model's recorded probe frames

The preprocessing needs nothing but the graph's metadata and numpy: the image is uint8 (H, W, 3) -> float32
[1, 3, H, W] / 255; the speed and the guidance are normalised with `yawil.norm`; a branched model takes the
command as a branch index (`yawil.sim.types.command_index`). The drive-time rules (speed control from the aux
head's target speed, the lead-stop class and its release, post-processing) are stateful per episode; they are
named in `yawil.drive` and applied here with `yawil.policy.drive`, the same code the yawil agent runs.
docs/training.md ("ONNX export") documents inputs, outputs and metadata.
"""

from __future__ import annotations

import json
import sys
from typing import Any

import numpy as np
import onnxruntime as ort

from yawil.policy.drive import DriveSettings, PostProcess
from yawil.sim.types import Control, command_index


class OnnxDriver:
    """One episode at a time: `reset(seed)`, then `step(image, speed, guidance, command)` per frame."""

    def __init__(self, path: str) -> None:
        self.session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        meta = self.session.get_modelmeta().custom_metadata_map
        self.norm: dict[str, Any] = json.loads(meta["yawil.norm"])
        drive = {k: v for k, v in json.loads(meta["yawil.drive"]).items() if k != "reference"}
        self.drive = DriveSettings(**{**drive, "post": PostProcess(**drive["post"])})
        self.inputs = [i.name for i in self.session.get_inputs()]
        self.outputs = [o.name for o in self.session.get_outputs()]
        self.state = self.drive.episode(0)

    def reset(self, seed: int = 0) -> None:
        self.state = self.drive.episode(seed)

    def _speed_of(self, value: float) -> float:  # a normalised speed output -> m/s (float32, as the agent does)
        return float(np.float32(value) * self.norm["speed_std"] + self.norm["speed_mean"])

    def step(self, image: np.ndarray, speed: float, guidance: np.ndarray | None = None,
             command: int | None = None) -> Control:
        """One frame: camera uint8 (H, W, 3), speed m/s, the raw guidance vector, the road option (RoadOption)."""
        n = self.norm
        feed = {"image": (np.ascontiguousarray(image).transpose(2, 0, 1)[None].astype(np.float32) / np.float32(255.0)),
                "speed": np.array([[(np.float32(speed) - n["speed_mean"]) / n["speed_std"]]], dtype=np.float32)}
        if "guidance" in self.inputs:
            g = (np.asarray(guidance, np.float32) - np.asarray(n["guidance_mean"], np.float32)) / np.asarray(
                n["guidance_std"], np.float32)
            feed["guidance"] = g[None].astype(np.float32)
        if "command" in self.inputs:
            feed["command"] = np.array([command_index(int(command))], dtype=np.int64)  # type: ignore[arg-type]
        out = dict(zip(self.outputs, self.session.run(None, feed), strict=True))
        aux = out["aux"][0] if "aux" in out else None
        decision = self.drive.decide(out["actions"][0], aux, self._speed_of, self.state, max(float(speed), 0.0))
        return self.drive.post(decision.actions, float(speed))


def main(path: str, zoo_name: str) -> None:
    from yawil.policy.probe import read_probe
    from yawil.zoo import zoo_dir

    probe = read_probe(zoo_dir(zoo_name))  # recorded frames: camera, speed, raw guidance, road option
    driver = OnnxDriver(path)
    for i in range(len(probe["speed"])):
        c = driver.step(probe["image"][i], float(probe["speed"][i]), probe["guidance"][i], int(probe["command"][i]))
        print(f"frame {i}: steer {c.steer:+.4f} throttle {c.throttle:.4f} brake {c.brake:.4f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "yilratt-dagger-dense3")
