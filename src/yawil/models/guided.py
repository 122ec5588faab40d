"""The guided networks of the paper's Table I: one network, three kinds of route guidance.

    image -> CIL perception (8 conv + FC 512, 512) -> p
    [speed, guidance] -> FC 128, 128 -> m
    [p, m] -> FC 512 -> FC 256, 256, 3 (one action head: the guidance, not a command, says where to go)
    p -> FC 256, 256, 1 speed

Registered as "yaw-guided" (yaw guidance computed from route coordinates), "xy-guided" (absolute x, y of
the waypoints, Hecker et al.'s GPS-style guidance) and "simyaw-guided" (lane heading from the simulator,
the paper's "Carla-yaw IL").
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from yawil.models.base import (
    DrivingModel,
    ModelOutput,
    aux_outputs,
    check_flag,
    resolve_guidance,
    squash_actions,
)
from yawil.models.cil import CILPerception
from yawil.models.layers import fc_relu, head
from yawil.models.registry import register

NAMES = {"yaw": "yaw-guided", "xy": "xy-guided", "sim_yaw": "simyaw-guided"}  # guidance kind -> registry name


class GuidedIL(DrivingModel):
    """CIL perception with guidance in the measurement module and a single action head."""

    def __init__(
        self,
        guidance: str,
        guidance_dim: int | None = None,
        image_size: Sequence[int] = (88, 200),
        dropout: float = 0.5,
        conv_dropout: float = 0.0,
        speed_input: bool = True,
        aux: bool = False,
        lead_stop: bool = False,
    ) -> None:
        """`speed_input` and `aux`: the inertia variants of YILRatt (docs/training.md), so that a recipe can be
        compared on the cheap baseline and on YILRatt the same way."""
        super().__init__(guidance=guidance, guidance_dim=resolve_guidance(guidance, guidance_dim), uses_command=False)
        self.name = NAMES[guidance]
        self.speed_input = check_flag("speed_input", speed_input)  # aux and lead_stop: aux_outputs checks them
        self.perception = CILPerception(image_size, conv_dropout)
        self.measurement = fc_relu(1 + self.guidance_dim, (128, 128))
        self.join = fc_relu(self.perception.out_dim + 128, (512,))
        self.action = head(512, (256, 256), 3, dropout)
        self.speed_head = head(self.perception.out_dim, (256, 256), 1, dropout)
        n_aux = aux_outputs(aux, lead_stop)
        self.lead_stop = lead_stop
        self.aux_head = head(512, (256,), n_aux, dropout) if n_aux else None

    def forward(
        self, image: Tensor, speed: Tensor, guidance: Tensor | None = None, command: Tensor | None = None
    ) -> ModelOutput:
        guide, _ = self.check_inputs(image, speed, guidance, command)
        assert guide is not None
        self.perception.check(image)
        feat = self.perception(self.normalise(image))
        if not self.speed_input:
            speed = torch.zeros_like(speed)
        m = self.measurement(torch.cat([speed, guide], dim=1).to(feat.dtype))
        joined = self.join(torch.cat([feat, m], dim=1))
        aux = self.aux_head(joined) if self.aux_head is not None else None
        return ModelOutput(squash_actions(self.action(joined)), self.speed_head(feat), [], None, aux)

    def stage_features(self, image: Tensor) -> list[Tensor]:
        self.perception.check(image)
        return self.perception.stages(self.normalise(image))


@register("yaw-guided")
def yaw_guided(
    guidance_dim: int = 15, image_size: Sequence[int] = (88, 200), dropout: float = 0.5, conv_dropout: float = 0.0,
    speed_input: bool = True, aux: bool = False, lead_stop: bool = False,
) -> GuidedIL:
    """Yaw-guided IL: guidance = route yaws relative to the first one."""
    return GuidedIL("yaw", guidance_dim, image_size, dropout, conv_dropout, speed_input, aux, lead_stop)


@register("xy-guided")
def xy_guided(
    guidance_dim: int = 30, image_size: Sequence[int] = (88, 200), dropout: float = 0.5, conv_dropout: float = 0.0,
    speed_input: bool = True, aux: bool = False, lead_stop: bool = False,
) -> GuidedIL:
    """XY-guided IL: guidance = absolute waypoint coordinates scaled by the map bounds."""
    return GuidedIL("xy", guidance_dim, image_size, dropout, conv_dropout, speed_input, aux, lead_stop)


@register("simyaw-guided")
def simyaw_guided(
    guidance_dim: int = 15, image_size: Sequence[int] = (88, 200), dropout: float = 0.5, conv_dropout: float = 0.0,
    speed_input: bool = True, aux: bool = False, lead_stop: bool = False,
) -> GuidedIL:
    """Simulator-yaw IL ("Carla-yaw IL"): guidance = lane headings reported by the simulator's map."""
    return GuidedIL("sim_yaw", guidance_dim, image_size, dropout, conv_dropout, speed_input, aux, lead_stop)
