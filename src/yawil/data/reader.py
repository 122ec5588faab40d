"""Reading one episode file back: random access to frames, labels in bulk, metadata decoded."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from yawil.data.schema import (
    ALL_FIELDS,
    EPISODE_FORMAT,
    IMAGE_SHAPE,
    LABEL_FIELDS,
    READABLE_VERSIONS,
    REQUIRED_ATTRS,
    V2_FIELDS,
    FrameRecord,
    field_dtype,
)


class EpisodeReader:
    """An open episode file. Opening checks the structure (attrs, datasets, lengths), not the values."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            self._h5 = h5py.File(self.path, "r")
        except OSError as err:
            raise ValueError(f"{self.path}: cannot open as HDF5 (truncated or corrupt?): {err}") from None
        try:
            self.attrs = self._read_attrs()
            self._check_datasets()
        except (OSError, KeyError, RuntimeError) as err:
            self._h5.close()
            raise ValueError(f"{self.path}: unreadable episode structure (corrupt?): {err}") from None
        except BaseException:
            self._h5.close()
            raise

    def _read_attrs(self) -> dict[str, Any]:
        raw = self._h5.attrs
        missing = [a for a in REQUIRED_ATTRS if a not in raw]
        if missing:
            raise ValueError(f"{self.path}: missing attribute(s) {missing}")
        if raw["format"] != EPISODE_FORMAT:
            raise ValueError(f"{self.path}: attribute 'format' is {raw['format']!r}, expected {EPISODE_FORMAT!r}")
        version = raw["schema_version"]
        version = version.item() if isinstance(version, np.generic) else version
        if version not in READABLE_VERSIONS or isinstance(version, bool):
            raise ValueError(f"{self.path}: schema_version {version!r} is not supported (this yawil reads {list(READABLE_VERSIONS)})")
        out: dict[str, Any] = {}
        for key in REQUIRED_ATTRS:
            v = raw[key]
            out[key] = v.item() if isinstance(v, np.generic) else v
        try:
            out["config"] = json.loads(out["config"])
            out["meta"] = json.loads(out["meta"])
        except (TypeError, json.JSONDecodeError) as err:
            raise ValueError(f"{self.path}: attribute 'config' or 'meta' is not JSON: {err}") from None
        rl = float(out["route_length"])
        out["route_length"] = None if math.isnan(rl) else rl
        return out

    @property
    def stored_fields(self) -> tuple[str, ...]:
        """The fields this file's schema version holds (a schema-1 file lacks V2_FIELDS)."""
        if int(self.attrs["schema_version"]) >= 2:
            return ALL_FIELDS
        return tuple(f for f in ALL_FIELDS if f not in V2_FIELDS)

    def _check_datasets(self) -> None:
        missing = [f for f in self.stored_fields if f not in self._h5]
        if missing:
            raise ValueError(f"{self.path}: missing dataset(s) {missing}")
        n = int(self.attrs["frames"])
        for name in self.stored_fields:
            rows = self._h5[name].shape[0]
            if rows != n:
                raise ValueError(f"{self.path}: dataset {name!r} has {rows} rows, attribute 'frames' says {n}")
        if self._h5["image"].shape[1:] != IMAGE_SHAPE:
            raise ValueError(f"{self.path}: image shape {self._h5['image'].shape[1:]} != {IMAGE_SHAPE}")

    @property
    def episode(self) -> int:
        return int(self.attrs["episode"])

    @property
    def k(self) -> int:
        return int(self.attrs["K"])

    def __len__(self) -> int:
        return int(self.attrs["frames"])

    def labels(self) -> dict[str, np.ndarray]:
        """Every label column of the episode (all but images), read at once; a schema-1 file's missing
        columns come filled with V2_FIELDS' "unknown" values."""
        n = len(self)
        return {name: self._h5[name][:] if name in self._h5 or name not in V2_FIELDS
                else np.full(n, V2_FIELDS[name], dtype=field_dtype(name)) for name in LABEL_FIELDS}

    def image(self, i: int) -> np.ndarray:
        return np.asarray(self._h5["image"][i])

    def images(self, rows: np.ndarray | slice) -> np.ndarray:
        """Several images; `rows` sorted ascending (h5py's rule for fancy indexing)."""
        return np.asarray(self._h5["image"][rows])

    def __getitem__(self, i: int) -> FrameRecord:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.path}: frame row {i} out of range for {n} rows")
        i %= n
        h = self._h5
        row = {name: h[name][i : i + 1] if name in h else np.full(1, V2_FIELDS[name], dtype=field_dtype(name))
               for name in LABEL_FIELDS}
        return FrameRecord.from_labels(np.asarray(h["image"][i]), row, 0)

    def close(self) -> None:
        self._h5.close()

    def __enter__(self) -> EpisodeReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_episode(path: str | os.PathLike[str]) -> EpisodeReader:
    """Open an episode file; ValueError naming the file if it is not a readable yawil episode."""
    return EpisodeReader(path)
