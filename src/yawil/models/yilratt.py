"""YILRatt, the paper's network: ResNet34 + linear attention (perception), measurements, action, speed.

    image -> ResNet34 -> layer1, layer2, layer3 --attention(g)--> 3 x 512 -> P(o)   (g = pooled layer4)
    [speed, guidance] -> FC 128, 128 -> m
    [P(o), m] -> FC 512 -> FC 256, 256 -> 3 actions (tanh steer, sigmoid throttle and brake)
    P(o) -> FC 256, 256 -> 1 speed (perception only, as the paper's loss S(P(o)))
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from yawil.models.base import (
    DrivingModel,
    ModelOutput,
    aux_outputs,
    check_flag,
    resolve_guidance,
    squash_actions,
)
from yawil.models.layers import LinearAttention, fc_relu, head
from yawil.models.registry import register
from yawil.models.resnet import STAGE_CHANNELS, build_resnet34, load_imagenet_weights, resnet_stages


@register("yilratt")
class YILRatt(DrivingModel):
    """Yaw-guided imitation learning with ResNet34 and attention (the paper's Figure 2)."""

    def __init__(self, guidance: str = "yaw", guidance_dim: int | None = None, dropout: float = 0.5,
                 compute_global: bool = False, speed_input: bool = True, aux: bool = False,
                 lead_stop: bool = False) -> None:
        """`compute_global`: run layer4 and add g to the compatibility as the paper writes it. Off by default:
        <u, g> is the same at every position and cancels in the softmax, so the outputs are the same up to
        float rounding and layer4 (about a fifth of the backbone's time) is skipped (docs/models.md).

        Variants (not the paper's; docs/training.md, "Inertia countermeasures"): `speed_input=False` feeds
        the measurement layer a zero speed (the inputs stay the same, so agent and export need no change);
        `aux=True` adds a head on the joined features predicting AUX_NAMES (the expert's target speed, the
        lead vehicle, a light ahead); `lead_stop=True` one more, the logit of a standing vehicle close ahead."""
        super().__init__(guidance=guidance, guidance_dim=resolve_guidance(guidance, guidance_dim), uses_command=False)
        self.compute_global = check_flag("compute_global", compute_global)
        self.speed_input = check_flag("speed_input", speed_input)  # aux and lead_stop: aux_outputs checks them
        global_dim = STAGE_CHANNELS[-1]
        self.backbone = build_resnet34()
        self.attention = nn.ModuleList(LinearAttention(c, global_dim) for c in STAGE_CHANNELS[:3])
        feat_dim = global_dim * len(self.attention)
        self.measurement = fc_relu(1 + self.guidance_dim, (128, 128))
        self.join = fc_relu(feat_dim + 128, (512,))
        self.action = head(512, (256, 256), 3, dropout)
        self.speed_head = head(feat_dim, (256, 256), 1, dropout)
        n_aux = aux_outputs(aux, lead_stop)
        self.lead_stop = lead_stop
        self.aux_head = head(512, (256,), n_aux, dropout) if n_aux else None

    def perceive(self, image: Tensor) -> tuple[Tensor, list[Tensor]]:
        """Concatenated attended vectors P(o) [B, 1536] and the three attention maps."""
        g: Tensor | None = None
        if self.compute_global:
            l1, l2, l3, l4 = resnet_stages(self.backbone, self.normalise(image))
            g = l4.mean(dim=(2, 3))
        else:
            l1, l2, l3 = resnet_stages(self.backbone, self.normalise(image), stages=3)
        vectors, maps = [], []
        for block, local in zip(self.attention, (l1, l2, l3), strict=True):
            v, a = block(local, g)
            vectors.append(v)
            maps.append(a)
        return torch.cat(vectors, dim=1), maps

    def forward(
        self, image: Tensor, speed: Tensor, guidance: Tensor | None = None, command: Tensor | None = None
    ) -> ModelOutput:
        guide, _ = self.check_inputs(image, speed, guidance, command)
        assert guide is not None
        feat, maps = self.perceive(image)
        if not self.speed_input:
            speed = torch.zeros_like(speed)
        m = self.measurement(torch.cat([speed, guide], dim=1).to(feat.dtype))
        joined = self.join(torch.cat([feat, m], dim=1))
        raw = self.action(joined)
        aux = self.aux_head(joined) if self.aux_head is not None else None
        return ModelOutput(squash_actions(raw), self.speed_head(feat), maps, None, aux)

    def stage_features(self, image: Tensor) -> list[Tensor]:
        return resnet_stages(self.backbone, self.normalise(image))

    def load_pretrained(self, path: str | Path) -> None:
        load_imagenet_weights(self.backbone, path)
