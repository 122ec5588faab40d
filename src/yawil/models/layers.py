"""Building blocks shared by the models: fully connected stacks and the linear attention block."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn


def fc_relu(in_dim: int, sizes: Sequence[int]) -> nn.Sequential:
    """Linear + ReLU layers (perception FC, measurement module, join): every layer is hidden."""
    layers: list[nn.Module] = []
    for size in sizes:
        layers += [nn.Linear(in_dim, size), nn.ReLU(inplace=True)]
        in_dim = size
    return nn.Sequential(*layers)


def head(in_dim: int, hidden: Sequence[int], out_dim: int, dropout: float) -> nn.Sequential:
    """A prediction head: hidden Linear + ReLU layers, dropout, then a linear output layer.

    Dropout sits only before the output layer (as CILRS's branches do), a mild regulariser that does not
    slow the fit of the shared features.
    """
    return nn.Sequential(fc_relu(in_dim, hidden), nn.Dropout(dropout), nn.Linear(hidden[-1], out_dim))


def select_branch(branches: Tensor, command: Tensor) -> Tensor:
    """Row `command[b]` of `branches[b]` ([B, 4, 3] -> [B, 3]); gather keeps it exportable."""
    index = command.view(-1, 1, 1).expand(-1, 1, branches.shape[2])
    return branches.gather(1, index).squeeze(1)


class LinearAttention(nn.Module):
    """Jetley et al. 2018 ("learn to pay attention"), the additive compatibility c_i = <u, l_i + g>.

    The local features of one layer are projected by a 1x1 convolution to the width of the global
    feature g; a softmax over the spatial positions gives the attention map a, and the attended vector is
    sum_i a_i l_i (projected local features), of the width of g.
    """

    def __init__(self, local_channels: int, global_dim: int) -> None:
        super().__init__()
        self.project = nn.Conv2d(local_channels, global_dim, kernel_size=1, bias=False)
        self.score = nn.Conv2d(global_dim, 1, kernel_size=1, bias=False)  # the vector u

    def forward(self, local: Tensor, g: Tensor | None) -> tuple[Tensor, Tensor]:
        """Return the attended vector [B, D] and the attention map [B, h, w] (sums to 1).

        `g` None leaves out <u, g>, which is the same at every position and cancels in the softmax.
        """
        proj = self.project(local)
        batch, _, h, w = proj.shape
        scores = self.score(proj if g is None else proj + g[:, :, None, None]).flatten(1)
        att = torch.softmax(scores.float(), dim=1)
        attended = (proj.flatten(2).float() * att[:, None, :]).sum(dim=2)
        return attended.to(proj.dtype), att.view(batch, h, w)
