"""Models by name, timm-style: each model file registers its builder with `@register(name)`.

`create(name, **cfg)` records the resolved keyword arguments in `model.config`, so
`create(model.name, **model.config)` rebuilds the same network (a checkpoint only stores name + config).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import torch

from yawil.models.base import DrivingModel

Builder = TypeVar("Builder", bound=Callable[..., DrivingModel])

_REGISTRY: dict[str, Callable[..., DrivingModel]] = {}


def register(name: str) -> Callable[[Builder], Builder]:
    """Decorator: make a model class or builder function available to `create` under `name`."""

    def deco(builder: Builder) -> Builder:
        if name in _REGISTRY:
            raise ValueError(f"model name {name!r} is already registered")
        _REGISTRY[name] = builder
        return builder

    return deco


def list_models() -> list[str]:
    """Registered names in registration order."""
    return list(_REGISTRY)


def _check_option(model: str, key: str, value: Any, default: Any) -> None:
    """A value of the default's kind, or ValueError naming it (a string where a number belongs used to reach
    the constructor and end in a TypeError deep in torch)."""
    if default is inspect.Parameter.empty or default is None or value is None:
        return
    if isinstance(default, bool):
        ok, want = isinstance(value, bool), "true or false"
    elif isinstance(default, int | float):
        ok, want = isinstance(value, int | float) and not isinstance(value, bool), "a number"
    elif isinstance(default, str):
        ok, want = isinstance(value, str), "a string"
    elif isinstance(default, tuple | list):
        ok, want = isinstance(value, tuple | list), f"a list like {list(default)}"
    else:
        return
    if not ok:
        raise ValueError(f"model {model!r}: option {key}={value!r} must be {want} (default {default!r})")


def check_options(name: str, **cfg: Any) -> Any:
    """The builder of `name` once its name and options are known good (ValueError naming them): lets a
    config be checked before any data is read or weights are built."""
    if name not in _REGISTRY:
        raise ValueError(f"model: unknown name {name!r}; known: {', '.join(_REGISTRY)}")
    builder = _REGISTRY[name]
    params = inspect.signature(builder).parameters
    unknown = sorted(set(cfg) - set(params))
    if unknown:
        raise ValueError(f"model {name!r}: unknown option(s) {unknown}; accepted: {sorted(params)}")
    for key, value in cfg.items():
        _check_option(name, key, value, params[key].default)
    return builder


def has_aux_head(name: str, **cfg: Any) -> bool:
    """Whether `create(name, **cfg)` has an aux head, from its options alone (no weights built): a model has one
    when its builder takes `aux` and it is true."""
    params = inspect.signature(check_options(name, **cfg)).parameters
    return "aux" in params and bool(cfg.get("aux", params["aux"].default))


def create(name: str, *, pretrained: str | Path | None = None, seed: int | None = None, **cfg: Any) -> DrivingModel:
    """Build a model by name.

    pretrained: a local torchvision ResNet34 state dict loaded into the backbone (never downloaded).
    seed: makes the initial weights reproducible bit for bit without touching the global RNG.
    """
    builder = check_options(name, **cfg)
    bound = inspect.signature(builder).bind(**cfg)
    bound.apply_defaults()
    if seed is None:
        model = builder(**bound.arguments)
    else:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = builder(**bound.arguments)
    model.name = name
    config = {}
    for key, value in bound.arguments.items():
        if value is None and isinstance(getattr(model, key, None), int | float | str):
            value = getattr(model, key)  # defaults that depend on other options, resolved by the model
        config[key] = list(value) if isinstance(value, tuple) else value
    model.config = config
    if pretrained is not None:
        model.load_pretrained(pretrained)
    return model


def parameter_count(model: torch.nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
