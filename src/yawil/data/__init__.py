"""The dataset: one HDF5 file per episode plus manifest.json (docs/dataset.md).

The public names are re-exported lazily (PEP 562): `yawil.data.DrivingDataset` imports torch, but
`import yawil.data.writer` (the collector, in every worker process) must not pay for it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS: dict[str, str] = {
    "CheckReport": "check",
    "check_dataset": "check",
    "DrivingDataset": "dataset",
    "branch_indices": "dataset",
    "split_episodes": "dataset",
    "EpisodeEntry": "manifest",
    "Manifest": "manifest",
    "read_manifest": "manifest",
    "EpisodeReader": "reader",
    "open_episode": "reader",
    "IMAGE_SHAPE": "schema",
    "SCHEMA_VERSION": "schema",
    "FrameRecord": "schema",
    "compute_stats": "stats",
    "write_stats": "stats",
    "SUBSETS": "subset",
    "select_rows": "subset",
    "write_subset": "subset",
    "DatasetWriter": "writer",
    "EpisodeWriter": "writer",
    "write_synthetic_dataset": "synthetic",
}
__all__ = [
    "CheckReport",
    "DatasetWriter",
    "DrivingDataset",
    "EpisodeEntry",
    "EpisodeReader",
    "EpisodeWriter",
    "FrameRecord",
    "IMAGE_SHAPE",
    "Manifest",
    "SCHEMA_VERSION",
    "SUBSETS",
    "branch_indices",
    "check_dataset",
    "compute_stats",
    "open_episode",
    "read_manifest",
    "select_rows",
    "split_episodes",
    "write_stats",
    "write_subset",
    "write_synthetic_dataset",
]

if TYPE_CHECKING:
    from yawil.data.check import CheckReport, check_dataset
    from yawil.data.dataset import DrivingDataset, branch_indices, split_episodes
    from yawil.data.manifest import EpisodeEntry, Manifest, read_manifest
    from yawil.data.reader import EpisodeReader, open_episode
    from yawil.data.schema import IMAGE_SHAPE, SCHEMA_VERSION, FrameRecord
    from yawil.data.stats import compute_stats, write_stats
    from yawil.data.subset import SUBSETS, select_rows, write_subset
    from yawil.data.synthetic import write_synthetic_dataset
    from yawil.data.writer import DatasetWriter, EpisodeWriter


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'yawil.data' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"yawil.data.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
