"""The ResNet34 perception of YILRatt and CILRS: torchvision's network, its stages, ImageNet weights.

Weights come from a local file only (the state dict that `torchvision.models.resnet34(weights=...)`
downloads); nothing here touches the network.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor, nn
from torchvision.models import ResNet, resnet34

STAGE_CHANNELS = (64, 128, 256, 512)  # widths of layer1..layer4


def build_resnet34() -> ResNet:
    """torchvision's ResNet34 without its classifier, so its state dict keys stay torchvision's."""
    net = resnet34(weights=None)
    net.fc = nn.Identity()  # type: ignore[assignment]
    return net


def resnet_stages(net: ResNet, x: Tensor, stages: int = 4) -> list[Tensor]:
    """Outputs of layer1..layer`stages` for a normalised image (fewer stages: the rest is not computed)."""
    x = net.maxpool(net.relu(net.bn1(net.conv1(x))))
    out = []
    for layer in (net.layer1, net.layer2, net.layer3, net.layer4)[:stages]:
        x = layer(x)
        out.append(x)
    return out


def load_imagenet_weights(net: ResNet, path: str | Path) -> None:
    """Load a torchvision ResNet34 state dict from `path`; fc.* keys are ignored.

    Raises FileNotFoundError when the file is missing and ValueError, naming the file and the keys, when
    it is not a state dict of this network.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pretrained: no such file {str(path)!r} (a torchvision resnet34 state dict)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for a file that is not a checkpoint
        raise ValueError(f"pretrained: {str(path)!r} is not a readable torch state dict: {err}") from err
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(f"pretrained: {str(path)!r} does not hold a state dict (mapping of names to tensors)")
    given = {k: v for k, v in state.items() if not k.startswith("fc.")}
    expected = net.state_dict()
    missing = sorted(set(expected) - set(given))
    unexpected = sorted(set(given) - set(expected))
    wrong = sorted(k for k in set(given) & set(expected) if given[k].shape != expected[k].shape)
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} key(s) {_few(missing)}")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)} key(s) {_few(unexpected)}")
        if wrong:
            shapes = [f"{k}: {list(given[k].shape)} != {list(expected[k].shape)}" for k in wrong[:5]]
            parts.append(f"{len(wrong)} shape mismatch(es) {shapes}")
        raise ValueError(f"pretrained: {str(path)!r} is not a torchvision resnet34 state dict: " + "; ".join(parts))
    net.load_state_dict(given, strict=True)


def _few(keys: list[str], n: int = 5) -> str:
    return str(keys[:n]) + (" ..." if len(keys) > n else "")
