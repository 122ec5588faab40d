"""CILRS (Codevilla et al. 2019): ResNet34 perception, speed input, 4 command branches, speed prediction.

    image -> ResNet34 -> pooled layer4 (512) -> p
    speed -> FC 128, 128 -> m
    [p, m] -> FC 512 -> 4 branches FC 256, 256, 3; the command selects one
    p -> FC 256, 256, 1 speed (from perception only: the fix of CILRS against inertia)
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from yawil.models.base import NUM_COMMANDS, DrivingModel, ModelOutput, aux_outputs, check_flag, squash_actions
from yawil.models.layers import fc_relu, head, select_branch
from yawil.models.registry import register
from yawil.models.resnet import STAGE_CHANNELS, build_resnet34, load_imagenet_weights, resnet_stages


@register("cilrs")
class CILRS(DrivingModel):
    """Conditional imitation learning with ResNet34 and speed prediction."""

    def __init__(self, dropout: float = 0.5, speed_input: bool = True, aux: bool = False, lead_stop: bool = False) -> None:
        """`speed_input`, `aux`, `lead_stop`: YILRatt's inertia variants, as CIL has them (models/cil.py)."""
        super().__init__(guidance=None, guidance_dim=0, uses_command=True)
        self.speed_input = check_flag("speed_input", speed_input)
        self.backbone = build_resnet34()
        feat_dim = STAGE_CHANNELS[-1]
        self.measurement = fc_relu(1, (128, 128))
        self.join = fc_relu(feat_dim + 128, (512,))
        self.branches = nn.ModuleList(head(512, (256, 256), 3, dropout) for _ in range(NUM_COMMANDS))
        self.speed_head = head(feat_dim, (256, 256), 1, dropout)
        n_aux = aux_outputs(aux, lead_stop)
        self.lead_stop = lead_stop
        self.aux_head = head(512, (256,), n_aux, dropout) if n_aux else None

    def forward(
        self, image: Tensor, speed: Tensor, guidance: Tensor | None = None, command: Tensor | None = None
    ) -> ModelOutput:
        _, cmd = self.check_inputs(image, speed, guidance, command)
        assert cmd is not None
        feat = resnet_stages(self.backbone, self.normalise(image))[-1].mean(dim=(2, 3))
        if not self.speed_input:
            speed = torch.zeros_like(speed)
        j = self.join(torch.cat([feat, self.measurement(speed.to(feat.dtype))], dim=1))
        branches = squash_actions(torch.stack([b(j) for b in self.branches], dim=1))
        aux = self.aux_head(j) if self.aux_head is not None else None
        return ModelOutput(select_branch(branches, cmd), self.speed_head(feat), [], branches, aux)

    def stage_features(self, image: Tensor) -> list[Tensor]:
        return resnet_stages(self.backbone, self.normalise(image))

    def load_pretrained(self, path: str | Path) -> None:
        load_imagenet_weights(self.backbone, path)
