"""What every driving network shares: the output record, input checks, ImageNet normalisation.

Training, the agent, export and the heat maps are written against `DrivingModel` and `ModelOutput` only,
so a model is swapped by name without touching them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

NUM_COMMANDS = 4  # branch order: LANEFOLLOW, LEFT, RIGHT, STRAIGHT (yawil.sim.types.COMMANDS)
GUIDANCE_KINDS: dict[str, int] = {"yaw": 15, "xy": 30, "sim_yaw": 15}  # kind -> default width
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class ModelOutput(NamedTuple):
    """One forward pass: the contract that the trainer, agent and heat maps read."""

    actions: Tensor  # [B, 3]: steer in [-1, 1], throttle in [0, 1], brake in [0, 1]
    speed: Tensor  # [B, 1] predicted (normalised) speed
    attention: list[Tensor]  # YILRatt: one [B, h, w] probability map per attended layer; [] otherwise
    branches: Tensor | None  # command models: [B, 4, 3] all branches; None otherwise
    aux: Tensor | None = None  # models built with aux heads: [B, len(AUX_NAMES)] raw predictions; None otherwise


# The privileged labels an aux head predicts (Conditional Affordance Learning's spirit), in output order:
# the expert's target speed and the lead vehicle's speed (both normalised as the speed input), the distance
# to the stop point behind the lead vehicle (/ LEAD_RANGE, the dataset's "none" value) and a logit of
# "a red or yellow stop line is near" (docs/training.md, "Inertia countermeasures").
AUX_NAMES: tuple[str, ...] = ("target_speed", "lead_distance", "lead_speed", "light_ahead")
# With `lead_stop=true` (ours) one more aux output: a logit of "a vehicle standing or nearly (under
# LEAD_STOP_SPEED) is within LEAD_STOP_DISTANCE ahead", learnt by class-weighted cross-entropy. Why: the lead
# distance regression never learnt to see cars at these budgets (docs/experiments.md, 2026-12-02); a rare
# binary event is what a weighted classification loss learns (TransFuser++'s brake class).
LEAD_STOP_DISTANCE = 12.0  # m, the dataset's lead_distance (front bumper to the vehicle followed)
LEAD_STOP_SPEED = 2.0  # m/s, the lead vehicle's speed
LEAD_STOP_FIRES = 0.5  # probability over which the output counts as "yes" (validation, `--speed-control stop`)


def check_flag(name: str, value: bool) -> bool:
    """A model argument that must be true or false (a YAML/JSON "yes" or 1 is refused, not read as true)."""
    if not isinstance(value, bool):
        raise ValueError(f"{name}: expected true or false, got {value!r}")
    return value


def aux_outputs(aux: bool, lead_stop: bool) -> int:
    """Width of the aux head: AUX_NAMES, then the lead-stop logit; refuses lead_stop without aux."""
    check_flag("aux", aux), check_flag("lead_stop", lead_stop)
    if lead_stop and not aux:
        raise ValueError("lead_stop=true is an output of the aux head: build the model with aux=true too")
    return (len(AUX_NAMES) + int(lead_stop)) if aux else 0


def squash_actions(raw: Tensor) -> Tensor:
    """Map raw head outputs to the control ranges: steer tanh, throttle and brake sigmoid."""
    return torch.cat([torch.tanh(raw[..., :1]), torch.sigmoid(raw[..., 1:])], dim=-1)


def resolve_guidance(kind: str, dim: int | None) -> int:
    """Width of a guidance vector: the caller's choice or the kind's default (15 yaws, 30 for x,y)."""
    if kind not in GUIDANCE_KINDS:
        raise ValueError(f"guidance: expected one of {sorted(GUIDANCE_KINDS)}, got {kind!r}")
    if dim is None:
        return GUIDANCE_KINDS[kind]
    if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
        raise ValueError(f"guidance_dim: expected a positive int, got {dim!r}")
    return dim


def _eager() -> bool:
    """Value checks (not shape checks) would break tracing and export, so they run in eager mode only."""
    return not (torch.jit.is_tracing() or torch.compiler.is_compiling())


class DrivingModel(nn.Module):
    """Base of every registered network: attributes of the contract plus checked inputs."""

    name: str
    config: dict[str, Any]
    guidance: str | None
    uses_command: bool
    guidance_dim: int

    def __init__(self, *, guidance: str | None, guidance_dim: int, uses_command: bool) -> None:
        super().__init__()
        self.name = type(self).__name__.lower()
        self.config = {}
        self.guidance = guidance
        self.guidance_dim = guidance_dim if guidance is not None else 0
        self.uses_command = uses_command
        # Not persistent: a checkpoint holds learned weights only, normalisation is part of the code.
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def normalise(self, image: Tensor) -> Tensor:
        """Images arrive in [0, 1]; the backbones expect ImageNet statistics (and the model's dtype)."""
        mean: Tensor = self.mean  # type: ignore[assignment]
        std: Tensor = self.std  # type: ignore[assignment]
        return ((image - mean) / std).to(mean.dtype)

    def check_inputs(
        self, image: Tensor, speed: Tensor, guidance: Tensor | None, command: Tensor | None
    ) -> tuple[Tensor | None, Tensor | None]:
        """Raise ValueError naming the bad argument; return the guidance and command this model uses."""
        if not isinstance(image, Tensor) or image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"image: expected a tensor [B, 3, H, W], got {_shape(image)}")
        if not image.is_floating_point():
            raise ValueError(f"image: expected a float tensor in [0, 1], got dtype {image.dtype}")
        batch = image.shape[0]
        if not isinstance(speed, Tensor) or tuple(speed.shape) != (batch, 1) or not speed.is_floating_point():
            raise ValueError(f"speed: expected a float tensor [{batch}, 1], got {_shape(speed)}")
        used_guidance: Tensor | None = None
        used_command: Tensor | None = None
        if self.guidance is not None:
            expected = (batch, self.guidance_dim)
            if guidance is None:
                raise ValueError(f"guidance: required by {self.name} ({self.guidance}), shape [{batch}, {self.guidance_dim}]")
            if not isinstance(guidance, Tensor) or tuple(guidance.shape) != expected or not guidance.is_floating_point():
                raise ValueError(f"guidance: expected a float tensor [{batch}, {self.guidance_dim}], got {_shape(guidance)}")
            used_guidance = guidance
        if self.uses_command:
            if command is None:
                raise ValueError(f"command: required by {self.name}, an int64 tensor [{batch}] of values 0..3")
            if not isinstance(command, Tensor) or tuple(command.shape) != (batch,) or command.is_floating_point():
                raise ValueError(f"command: expected an integer tensor [{batch}], got {_shape(command)}")
            if _eager() and batch and (int(command.min()) < 0 or int(command.max()) >= NUM_COMMANDS):
                raise ValueError(f"command: values must be in 0..{NUM_COMMANDS - 1}, got {command.tolist()}")
            used_command = command.long()
        return used_guidance, used_command

    def stage_features(self, image: Tensor) -> list[Tensor]:
        """Feature maps [B, C, h, w] of each stage of the perception, from a [0, 1] image.

        Every registered model defines it (its perception's stages); the base class has no perception.
        """
        raise TypeError(f"{type(self).__name__} defines no perception stages (stage_features)")

    @torch.no_grad()
    def activation_maps(self, image: Tensor) -> list[Tensor]:
        """Per-stage maps [B, h, w]: channel mean of |activation|, scaled to sum to 1 (for heat maps)."""
        if not isinstance(image, Tensor) or image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"image: expected a tensor [B, 3, H, W], got {_shape(image)}")
        maps = []
        for feat in self.stage_features(image):
            m = feat.float().abs().mean(dim=1)
            total = m.flatten(1).sum(dim=1).clamp_min(1e-12)
            maps.append(m / total[:, None, None])
        return maps

    def load_pretrained(self, path: str | Path) -> None:
        """Load ImageNet weights into the backbone; only ResNet models have one."""
        raise ValueError(f"pretrained: model {self.name!r} has no ImageNet backbone (only yilratt and cilrs do)")


def _shape(x: object) -> str:
    if isinstance(x, Tensor):
        return f"shape {list(x.shape)} dtype {x.dtype}"
    return f"{type(x).__name__}"
