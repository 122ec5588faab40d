"""Driving networks by name: YILRatt (the paper), CIL, CILRS and the guided networks of Table I.

    model = create("yilratt", guidance="yaw")
    out = model(image, speed, guidance=g)          # ModelOutput(actions, speed, attention, branches)
    rebuilt = create(model.name, **model.config)   # what a checkpoint stores
"""

from __future__ import annotations

from torch import Tensor

# Importing the model files registers them, in this order.
from yawil.models import cil, cilrs, guided, yilratt  # noqa: F401
from yawil.models.base import GUIDANCE_KINDS, NUM_COMMANDS, DrivingModel, ModelOutput
from yawil.models.registry import create, list_models, parameter_count, register


def feature_maps(model: DrivingModel, image: Tensor) -> list[Tensor]:
    """Per-stage activation maps [B, h, w] summing to 1 (ResNet layer1..layer4, or CIL's conv stages)."""
    return model.activation_maps(image)


__all__ = [
    "GUIDANCE_KINDS",
    "NUM_COMMANDS",
    "DrivingModel",
    "ModelOutput",
    "create",
    "feature_maps",
    "list_models",
    "parameter_count",
    "register",
]
