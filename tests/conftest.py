"""Fixtures shared by the whole suite: a tiny checkpoint and a tiny synthetic dataset.

The directory of this file is on `sys.path` (pytest's default import mode), so the helper modules beside it
(`carla_fakes`, `scripted_world`) are importable from the test folders below.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pytest


class TinyCheckpoint(NamedTuple):
    path: Path
    norm: Any  # yawil.policy.checkpoint.Norm


@pytest.fixture
def tiny_checkpoint(tmp_path: Path) -> Callable[..., TinyCheckpoint]:
    """A factory of untrained checkpoints: `tiny_checkpoint(name, **model_cfg)` writes `<folder>/<name>.pt`
    (folder: the test's tmp_path unless given) and returns its path and normalisation.

    - `guidance`: the guidance config stored with it (default `GuidanceConfig()`'s)
    - `speed`: the speed normalisation (mean, std)
    - `spread`: guidance statistics spread out (means -0.1..0.1, stds 0.5..1.5, so a test sees that they are
      used) instead of means 0 and stds 1
    - `train_config`: the stored train config (default {"model": name})
    - anything else goes to `yawil.models.create(name, seed=0, ...)`
    """
    from yawil import models
    from yawil.guidance import GuidanceConfig
    from yawil.policy.checkpoint import Norm, make_checkpoint, save_checkpoint

    def make(name: str, *, folder: Path | None = None, guidance: Mapping[str, Any] | None = None,
             speed: tuple[float, float] = (2.5, 1.5), spread: bool = False,
             train_config: Mapping[str, Any] | None = None, **model_cfg: Any) -> TinyCheckpoint:
        model = models.create(name, seed=0, **model_cfg)
        dim = model.guidance_dim if model.guidance else 0
        if spread:
            norm = Norm(*speed, tuple(np.linspace(-0.1, 0.1, dim)), tuple(np.linspace(0.5, 1.5, dim)))
        else:
            norm = Norm(*speed, tuple(np.zeros(dim)), tuple(np.ones(dim)))
        path = (folder or tmp_path) / f"{name}.pt"
        gc = dict(guidance) if guidance is not None else GuidanceConfig().to_dict()
        save_checkpoint(make_checkpoint(model, norm, gc, dict(train_config) if train_config is not None
                                        else {"model": name}), path)
        return TinyCheckpoint(path, norm)

    return make


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """A factory of small synthetic datasets written by yawil.data's writer, made once per session for each
    set of arguments: `tiny_dataset(episodes=2, frames=5, k=15)`. Shared: tests only read them."""
    from yawil.data.synthetic import write_synthetic_dataset

    made: dict[tuple[Any, ...], Path] = {}

    def make(episodes: int = 2, frames: int = 5, k: int = 15, seed: int = 0) -> Path:
        key = (episodes, frames, k, seed)
        if key not in made:
            root = tmp_path_factory.mktemp("tiny_dataset") / "data"
            write_synthetic_dataset(root, episodes=episodes, frames=frames, k=k, seed=seed)
            made[key] = root
        return made[key]

    return make
