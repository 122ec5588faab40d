"""CIL (Codevilla et al. 2018), branched: 8 conv layers, speed module, 4 command branches, speed branch.

    image -> conv 5x5/2 32, 3x3 32, 3x3/2 64, 3x3 64, 3x3/2 128, 3x3 128, 3x3 256, 3x3 256 (BN + ReLU,
             no padding as the original) -> flatten -> FC 512, 512 -> p
    speed -> FC 128, 128 -> m
    [p, m] -> FC 512 -> 4 branches FC 256, 256, 3; the command selects one
    p -> FC 256, 256, 1 speed

The flattened width depends on the image size, so `image_size` is part of the config (88 x 200 default).
`CILPerception` is shared with the guided networks of Table I (yawil.models.guided).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from yawil.models.base import NUM_COMMANDS, DrivingModel, ModelOutput, aux_outputs, check_flag, squash_actions
from yawil.models.layers import fc_relu, head, select_branch
from yawil.models.registry import register

# (kernel, stride, channels) of the eight convolutions
CONV_LAYERS: tuple[tuple[int, int, int], ...] = (
    (5, 2, 32), (3, 1, 32), (3, 2, 64), (3, 1, 64), (3, 2, 128), (3, 1, 128), (3, 1, 256), (3, 1, 256),
)  # fmt: skip
STAGE_ENDS = (1, 3, 5, 7)  # conv indices whose outputs are the stages of `activation_maps`


def check_image_size(image_size: Sequence[int]) -> tuple[int, int]:
    """The (H, W) the convolutions accept; raises ValueError when it is too small for eight valid convs."""
    if (
        not isinstance(image_size, Sequence)
        or len(image_size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in image_size)
    ):
        raise ValueError(f"image_size: expected [height, width] as two ints, got {image_size!r}")
    h, w = image_size
    for k, s, _ in CONV_LAYERS:
        h, w = (h - k) // s + 1, (w - k) // s + 1
    if h < 1 or w < 1:
        raise ValueError(f"image_size: {list(image_size)} is too small for the CIL convolutions (at least 77 x 77)")
    return int(image_size[0]), int(image_size[1])


class CILPerception(nn.Module):
    """The CIL image module: eight conv layers and two FC layers to a 512-d feature."""

    def __init__(self, image_size: Sequence[int], conv_dropout: float = 0.0) -> None:
        super().__init__()
        self.image_size = check_image_size(image_size)
        layers: list[nn.Module] = []
        in_ch = 3
        for k, s, out_ch in CONV_LAYERS:
            block = [nn.Conv2d(in_ch, out_ch, k, stride=s, bias=False), nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True)]
            if conv_dropout > 0:
                block.append(nn.Dropout(conv_dropout))
            layers.append(nn.Sequential(*block))
            in_ch = out_ch
        self.convs = nn.ModuleList(layers)
        h, w = self.image_size
        for k, s, _ in CONV_LAYERS:
            h, w = (h - k) // s + 1, (w - k) // s + 1
        self.fc = fc_relu(in_ch * h * w, (512, 512))
        self.out_dim = 512

    def check(self, image: Tensor) -> None:
        """The FC width is fixed by the image size, so any other size is refused clearly."""
        if tuple(image.shape[2:]) != self.image_size:
            raise ValueError(
                f"image: this CIL perception was built for image_size {list(self.image_size)}, "
                f"got [H, W] = {list(image.shape[2:])}"
            )

    def stages(self, x: Tensor) -> list[Tensor]:
        out = []
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i in STAGE_ENDS:
                out.append(x)
        return out

    def forward(self, x: Tensor) -> Tensor:
        for conv in self.convs:
            x = conv(x)
        return self.fc(x.flatten(1))


@register("cil")
class CIL(DrivingModel):
    """Conditional imitation learning, the branched network of Codevilla et al. 2018."""

    def __init__(
        self, image_size: Sequence[int] = (88, 200), dropout: float = 0.5, conv_dropout: float = 0.0,
        speed_input: bool = True, aux: bool = False, lead_stop: bool = False,
    ) -> None:
        """`speed_input`, `aux`, `lead_stop`: YILRatt's inertia variants (docs/training.md), so that CIL can be
        trained with the same recipe as YILRatt for the paper's comparison; the aux head is shared by the
        branches (the scene's target speed does not depend on the command)."""
        super().__init__(guidance=None, guidance_dim=0, uses_command=True)
        self.speed_input = check_flag("speed_input", speed_input)
        self.perception = CILPerception(image_size, conv_dropout)
        self.measurement = fc_relu(1, (128, 128))
        self.join = fc_relu(self.perception.out_dim + 128, (512,))
        self.branches = nn.ModuleList(head(512, (256, 256), 3, dropout) for _ in range(NUM_COMMANDS))
        self.speed_head = head(self.perception.out_dim, (256, 256), 1, dropout)
        n_aux = aux_outputs(aux, lead_stop)
        self.lead_stop = lead_stop
        self.aux_head = head(512, (256,), n_aux, dropout) if n_aux else None

    def forward(
        self, image: Tensor, speed: Tensor, guidance: Tensor | None = None, command: Tensor | None = None
    ) -> ModelOutput:
        _, cmd = self.check_inputs(image, speed, guidance, command)
        assert cmd is not None
        self.perception.check(image)
        feat = self.perception(self.normalise(image))
        if not self.speed_input:
            speed = torch.zeros_like(speed)
        j = self.join(torch.cat([feat, self.measurement(speed.to(feat.dtype))], dim=1))
        branches = squash_actions(torch.stack([b(j) for b in self.branches], dim=1))
        aux = self.aux_head(j) if self.aux_head is not None else None
        return ModelOutput(select_branch(branches, cmd), self.speed_head(feat), [], branches, aux)

    def stage_features(self, image: Tensor) -> list[Tensor]:
        self.perception.check(image)
        return self.perception.stages(self.normalise(image))
