"""The model-input contract: the one place where a dataset batch, a dataset frame or an Observation becomes the
inputs of a driving network, for training, the agent, heat maps and ONNX export alike.

    spec = InputSpec.of(model, norm, runtime)      # what the model takes (guidance kind, command) and how
    x = spec.from_batch(raw)                        # a DataLoader batch (training, validation)
    x = spec.from_frame(image, speed, g, option)    # one frame: an Observation (the agent) or a FrameRecord
    out = x.forward(model)                          # model(image, speed, guidance=..., command=...)

The inputs (`ModelInputs`, in the ONNX graph's order): `image` float32 [B, 3, H, W] in [0, 1] (uint8 / 255;
channels_last memory when the Runtime says so); `speed` float32 [B, 1] normalised with the checkpoint's `Norm`;
`guidance` float32 [B, D] normalised (guided models: the kind the model names, read from the dataset field
`guidance_<kind>` or computed from the route by `observation_guidance`), else None; `command` int64 [B], the
branch index of the road option (`yawil.sim.types.command_index`; CIL, CILRS), else None.

A batch arrives as the dataset gives it (image uint8 [B, 3, H, W], command already a branch index); a frame as
the camera gives it (uint8 [H, W, 3], command a RoadOption value). Both paths keep the exact operations (and so
the exact values, dtypes and memory layouts) the trainer and the agent have always used.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from yawil.guidance import GUIDANCE_KINDS, GuidanceConfig, compute_guidance
from yawil.policy.checkpoint import Norm
from yawil.policy.runtime import Runtime
from yawil.sim.types import Observation, RoadOption, command_index

INPUT_NAMES = ("image", "speed", "guidance", "command")  # every input, in the ONNX graph's order


def guidance_key(kind: str) -> str:
    """The dataset field of a guidance kind (batch key, FrameRecord attribute, label column): guidance_<kind>."""
    if kind not in GUIDANCE_KINDS:
        raise ValueError(f"guidance kind must be one of {GUIDANCE_KINDS}, got {kind!r}")
    return f"guidance_{kind}"


def guidance_kind(model: Any) -> str | None:
    """The guidance kind a model takes (yaw, xy, sim_yaw), or None for a model that takes the command."""
    kind: str | None = getattr(model, "guidance", None)
    return kind


def takes_command(model: Any) -> bool:
    """Whether a model takes the high-level command (the branched CIL and CILRS)."""
    return bool(getattr(model, "uses_command", False))


def input_names(model: Any) -> list[str]:
    """The inputs a model takes, in order: image, speed, then guidance (guided) and/or command (branched)."""
    names = ["image", "speed"]
    if guidance_kind(model) is not None:
        names.append("guidance")
    if takes_command(model):
        names.append("command")
    return names


@dataclass(frozen=True)
class ModelInputs:
    """The prepared inputs of one forward pass (see the module's docstring for shapes and units).

    `speed_raw` is the measured speed in m/s before normalisation ([B, 1]), kept for losses and metrics; it is
    not a network input.
    """

    image: Tensor
    speed: Tensor
    guidance: Tensor | None = None
    command: Tensor | None = None
    speed_raw: Tensor | None = None

    def as_dict(self) -> dict[str, Tensor | None]:
        """The four network inputs by name (None where the model takes no such input)."""
        return {"image": self.image, "speed": self.speed, "guidance": self.guidance, "command": self.command}

    def named(self) -> dict[str, Tensor]:
        """The inputs present, by name, in the ONNX graph's order (`input_names`)."""
        return {name: t for name, t in self.as_dict().items() if t is not None}

    def forward(self, model: Any) -> Any:
        """Run a driving network on these inputs (its ModelOutput)."""
        return model(self.image, self.speed, guidance=self.guidance, command=self.command)


@dataclass(frozen=True)
class InputSpec:
    """What one model takes and how its inputs are prepared: the checkpoint's normalisation, the guidance kind
    (None: no guidance), whether it takes the command, and the Runtime (device, channels_last)."""

    norm: Norm
    kind: str | None
    uses_command: bool
    runtime: Runtime

    @classmethod
    def of(cls, model: Any, norm: Norm, runtime: Runtime) -> InputSpec:
        return cls(norm, guidance_kind(model), takes_command(model), runtime)

    @property
    def guidance_key(self) -> str | None:
        return None if self.kind is None else guidance_key(self.kind)

    def names(self) -> list[str]:
        return [n for n, on in zip(INPUT_NAMES, (True, True, self.kind is not None, self.uses_command), strict=True) if on]

    # ---- a dataset batch (DataLoader output: image uint8 [B, 3, H, W], command a branch index)
    def from_batch(self, raw: Mapping[str, Any]) -> ModelInputs:
        dev = self.runtime.device
        image = torch.as_tensor(raw["image"]).to(dev, non_blocking=True).float().div_(255.0)
        if self.runtime.channels_last:
            image = image.contiguous(memory_format=torch.channels_last)
        speed_raw = torch.as_tensor(raw["speed"]).to(dev).float().reshape(-1, 1)
        guidance = None
        if self.kind is not None:
            guidance = self.norm.guidance(torch.as_tensor(raw[guidance_key(self.kind)]).to(dev).float())
        command = torch.as_tensor(raw["command"]).to(dev).long().reshape(-1) if self.uses_command else None
        return ModelInputs(image, self.norm.speed(speed_raw), guidance, command, speed_raw)

    # ---- frames as the camera gives them: uint8 (H, W, 3), the speed in m/s, raw guidance, a RoadOption value
    def image(self, image: np.ndarray) -> Tensor:
        """uint8 (H, W, 3) -> float [1, 3, H, W] in [0, 1] on the device (a permuted view: channels_last memory)."""
        t = torch.from_numpy(np.ascontiguousarray(image)).to(self.runtime.device).permute(2, 0, 1)[None].float().div_(255.0)
        if self.runtime.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        return t

    def images(self, images: Sequence[np.ndarray]) -> Tensor:
        """B uint8 (H, W, 3) frames -> float [B, 3, H, W] in [0, 1], each row as `image` gives it."""
        rows = [self.image(i) for i in images]
        t = rows[0] if len(rows) == 1 else torch.cat(rows)
        if self.runtime.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        return t

    def from_frame(
        self, image: np.ndarray, speed: float, guidance: np.ndarray | None = None, command: int | None = None
    ) -> ModelInputs:
        """One frame's inputs. `guidance`: the raw (unnormalised) vector of the model's kind; `command`: the road
        option (RoadOption value), turned into its branch index here."""
        return self.from_frames([image], [speed], [guidance], [command])

    def from_frames(
        self,
        images: Sequence[np.ndarray],
        speeds: Sequence[float],
        guidance: Sequence[np.ndarray | None],
        commands: Sequence[int | None],
    ) -> ModelInputs:
        """B frames' inputs, row by row the values `from_frame` gives each (the agent's batch of episodes)."""
        dev = self.runtime.device
        g = None
        if self.kind is not None:
            if any(v is None for v in guidance):
                raise ValueError(f"the model takes {self.kind} guidance; none was given")
            raw = np.stack([np.asarray(v, dtype=np.float32) for v in guidance])
            g = self.norm.guidance(torch.from_numpy(raw).to(dev))
        c = None
        if self.uses_command:
            if any(v is None for v in commands):
                raise ValueError("the model takes the command; none was given")
            c = torch.tensor([command_index(int(v)) for v in commands], dtype=torch.int64, device=dev)  # type: ignore[arg-type]
        speed_raw = torch.tensor([[float(v)] for v in speeds], dtype=torch.float32, device=dev)
        return ModelInputs(self.images(images), self.norm.speed(speed_raw), g, c, speed_raw)

    def from_record(self, record: Any) -> ModelInputs:
        """A stored frame (`yawil.data.schema.FrameRecord`) with its own speed, guidance and command."""
        key = self.guidance_key
        return self.from_frame(
            record.image,
            record.speed,
            None if key is None else getattr(record, key),
            record.command if self.uses_command else None,
        )


_ROAD_OPTIONS = frozenset(int(o) for o in RoadOption)


def check_observation(obs: Observation) -> np.ndarray:
    """The observation's camera image, once its speed and command are checked too: a NaN speed or an unknown
    road option drove without a word (a guided model never reads the command). Per step: two comparisons."""
    speed = obs.speed
    if isinstance(speed, bool) or not isinstance(speed, int | float | np.integer | np.floating) or not math.isfinite(speed):
        raise ValueError(f"observation speed={speed!r}: expected a finite number (m/s)")
    if obs.command not in _ROAD_OPTIONS or isinstance(obs.command, bool):
        raise ValueError(f"observation command={obs.command!r}: expected a road option, one of "
                         f"{sorted(_ROAD_OPTIONS)} ({', '.join(o.name for o in RoadOption)})")
    return check_observation_image(obs)


def check_observation_image(obs: Observation) -> np.ndarray:
    """The observation's camera image, refused unless uint8 (H, W, 3)."""
    if obs.image is None:
        raise ValueError("observation has no camera image; the scenario must have camera=True for a learned agent")
    img = np.asarray(obs.image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"observation image: expected uint8 (H, W, 3), got {img.dtype} {img.shape}")
    return img


def observation_guidance(
    obs: Observation,
    config: GuidanceConfig,
    kind: str,
    *,
    hint: int | None,
    yaw_noise_deg: float = 0.0,
    rng: np.random.Generator | None = None,
    yaw_noise_mode: str = "raw",
) -> tuple[np.ndarray, int]:
    """The raw guidance vector of `kind` for an observation (float32) and the route-projection hint for the next
    frame. `rng` is drawn from only when `yaw_noise_deg` > 0 (Table II)."""
    g, hint_out = compute_guidance(
        obs.route.xy,
        obs.route.lane_yaw,
        (obs.pose.x, obs.pose.y),
        obs.pose.yaw,
        obs.bounds,
        config,
        hint_index=hint,
        yaw_noise_deg=yaw_noise_deg,
        rng=rng if yaw_noise_deg > 0 else None,
        yaw_noise_mode=yaw_noise_mode,
    )
    return np.asarray(g.get(kind), dtype=np.float32), hint_out


def example_inputs(model: Any, batch: int, seed: int = 0, image_size: tuple[int, int] = (88, 200)) -> dict[str, Any]:
    """A random batch of valid inputs (seeded), for tracing a graph (the engines, the ONNX export) and for the
    export's agreement check: the model's inputs of the contract (`ModelInputs.named`), drawn in the order image,
    speed, guidance, command."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, *image_size, generator=g)
    speed = torch.randn(batch, 1, generator=g)
    guidance = torch.randn(batch, int(model.guidance_dim), generator=g) if guidance_kind(model) is not None else None
    command = torch.randint(0, 4, (batch,), generator=g, dtype=torch.int64) if takes_command(model) else None
    return dict(ModelInputs(image, speed, guidance, command).named())
