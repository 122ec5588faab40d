"""The torch view of one or more dataset roots: random access to frames for DataLoader workers.

Labels of every usable episode are read once, when the dataset is built (a few hundred bytes a frame), and
judged with `schema.label_problems`, the same test `yawil data check` applies: a file that does not open or
whose labels break the schema is skipped with a warning naming it. A sample then only reads its image,
one HDF5 chunk. HDF5 handles are opened lazily by the process that reads, and a process that finds
handles made by another (a forked DataLoader worker) opens its own: a handle is never shared across fork.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from yawil.data.manifest import EpisodeEntry, read_manifest
from yawil.data.reader import open_episode
from yawil.data.schema import COMMAND_NAMES, label_problems
from yawil.sim.types import command_index

PathLike = str | os.PathLike[str]

# RoadOption value -> branch index, as a lookup table (index = RoadOption value).
_BRANCH = np.full(max(COMMAND_NAMES) + 1, -1, dtype=np.int64)
for _value in COMMAND_NAMES:
    _BRANCH[_value] = command_index(_value)


def branch_indices(road_options: np.ndarray) -> np.ndarray:
    """RoadOption values -> model branch indices (int64), vectorised `command_index`."""
    return _BRANCH[np.asarray(road_options, dtype=np.int64)]


def as_roots(roots: PathLike | Sequence[PathLike]) -> list[Path]:
    if isinstance(roots, (str, os.PathLike)):
        return [Path(roots)]
    out = [Path(r) for r in roots]
    if not out:
        raise ValueError("no dataset root given")
    return out


def manifest_episodes(roots: Sequence[Path]) -> list[tuple[Path, EpisodeEntry]]:
    """(root, entry) of every listed episode; ValueError when two roots hold the same episode id."""
    seen: dict[int, Path] = {}
    out: list[tuple[Path, EpisodeEntry]] = []
    for root in roots:
        for entry in read_manifest(root).episodes:
            if entry.episode in seen:
                raise ValueError(
                    f"episode id {entry.episode} is in both {seen[entry.episode]} and {root}; episode ids must be "
                    "unique across the roots of one dataset (collect them with different --seed)"
                )
            seen[entry.episode] = root
            out.append((root, entry))
    return out


def load_episode_labels(path: Path, entry: EpisodeEntry | None = None, k: int | None = None) -> dict[str, np.ndarray]:
    """All label columns of an episode file, or ValueError naming the file and every problem found."""
    with open_episode(path) as ep:
        problems: list[str] = []
        if k is not None and ep.k != k:
            problems.append(f"K={ep.k} but the dataset config says guidance.count={k}")
        if entry is not None and (ep.episode != entry.episode or len(ep) != entry.frames):
            problems.append(
                f"file holds episode {ep.episode} with {len(ep)} frames, manifest says episode {entry.episode} "
                f"with {entry.frames} frames"
            )
        try:
            labels = ep.labels()
        except (OSError, RuntimeError, KeyError) as err:
            raise ValueError(f"{path}: label data unreadable (truncated or corrupt?): {err}") from None
        problems += label_problems(labels, ep.k)
    if problems:
        raise ValueError(f"{path}: " + "; ".join(problems))
    return labels


def guidance_config_of(roots: Sequence[Path]) -> dict[str, Any]:
    """The guidance config the roots were written with; ValueError when they disagree or lack one."""
    configs = []
    for root in roots:
        g = read_manifest(root).config.get("guidance")
        if not isinstance(g, dict) or "count" not in g:
            raise ValueError(f"{root}/manifest.json: config has no 'guidance' object with a 'count' (K)")
        configs.append(g)
    for root, g in zip(roots[1:], configs[1:], strict=True):
        if g != configs[0]:
            raise ValueError(f"guidance config of {root} ({g}) differs from that of {roots[0]} ({configs[0]})")
    return dict(configs[0])


@dataclass
class _Episode:
    path: Path
    episode: int
    start: int  # first sample index
    rows: int


class DrivingDataset(Dataset[dict[str, torch.Tensor]]):
    """Frames of the listed episodes (all when `episodes` is None) of one or more dataset roots.

    A sample is a dict of tensors: image uint8 [3, 88, 200], speed float32 [1], action float32 [3]
    (steer, throttle, brake), command int64 [] (branch index), guidance_yaw/xy/sim_yaw float32 [K]/[2K]/[K],
    episode and frame int64 [], privileged float32 [5] (target_speed m/s, lead_distance m, lead_speed m/s,
    light_ahead, speed_reason index; NaN or -1 where unknown). Samples are ordered by root, then manifest order, then row.
    """

    def __init__(self, roots: PathLike | Sequence[PathLike], episodes: Sequence[int] | None = None) -> None:
        self.roots = as_roots(roots)
        self.guidance_config = guidance_config_of(self.roots)
        self.k = int(self.guidance_config["count"])
        listed = manifest_episodes(self.roots)
        if episodes is not None:
            wanted = {int(e) for e in episodes}
            unknown = wanted - {e.episode for _, e in listed}
            if unknown:
                raise ValueError(f"episode(s) {sorted(unknown)[:10]} are not in {[str(r) for r in self.roots]}")
            listed = [(r, e) for r, e in listed if e.episode in wanted]
        self.episodes: list[_Episode] = []
        self.skipped: list[tuple[Path, str]] = []  # (file, why) of unusable episode files
        columns: list[dict[str, np.ndarray]] = []
        start = 0
        for root, entry in listed:
            path = root / entry.file
            try:
                labels = load_episode_labels(path, entry, self.k)
            except ValueError as err:
                self.skipped.append((path, str(err)))
                warnings.warn(f"skipping corrupt episode file: {err}", RuntimeWarning, stacklevel=2)
                continue
            n = len(labels["frame"])
            self.episodes.append(_Episode(path, entry.episode, start, n))
            columns.append(labels)
            start += n
        self._n = start
        self._labels = _concat(columns, self.k)
        self._labels["episode"] = np.concatenate(
            [np.full(e.rows, e.episode, dtype=np.int64) for e in self.episodes] or [np.zeros(0, np.int64)]
        )
        self._labels["branch"] = branch_indices(self._labels["command"])
        # sample -> (episode position, row): two small arrays, shared copy-on-write by forked workers
        self._ep_of = np.concatenate(
            [np.full(e.rows, i, dtype=np.int32) for i, e in enumerate(self.episodes)] or [np.zeros(0, np.int32)]
        )
        self._row_of = np.concatenate([np.arange(e.rows, dtype=np.int64) for e in self.episodes] or [np.zeros(0, np.int64)])
        self._pid = -1
        self._files: dict[int, h5py.File] = {}
        self._foreign: list[dict[int, h5py.File]] = []  # another process's handles: kept, never used or closed

    def __len__(self) -> int:
        return self._n

    @property
    def episode_ids(self) -> list[int]:
        return [e.episode for e in self.episodes]

    def labels(self, name: str) -> np.ndarray:
        """A label column of every sample without reading images (a copy).

        Names: speed [N], action [N, 3], command [N] (branch index, as in samples), road_option [N]
        (RoadOption value), steer, throttle, brake, guidance_yaw [N, K], guidance_xy [N, 2K],
        guidance_sim_yaw [N, K], pose [N, 3], episode, frame, noise and lane_follow_turn (bool) [N].
        """
        lab = self._labels
        if name == "action":
            return np.stack([lab["steer"], lab["throttle"], lab["brake"]], axis=1)
        if name == "command":
            return lab["branch"].copy()
        if name == "road_option":
            return lab["command"].astype(np.int64)
        if name in ("noise", "lane_follow_turn"):
            return lab[name].astype(bool)
        if name in lab and name != "branch":
            return lab[name].copy()
        raise KeyError(f"no label {name!r}; known: action, command, road_option, {', '.join(sorted(set(lab) - {'command', 'branch'}))}")

    def _file(self, ep: int) -> h5py.File:
        pid = os.getpid()
        if pid != self._pid:  # first use in this process (e.g. a freshly forked worker)
            if self._files:
                self._foreign.append(self._files)
            self._files, self._pid = {}, pid
        f = self._files.get(ep)
        if f is None:
            f = self._files[ep] = h5py.File(self.episodes[ep].path, "r")
        return f

    def image(self, i: int) -> np.ndarray:
        """The (88, 200, 3) uint8 image of sample i; ValueError naming file and row if it cannot be read."""
        ep, row = int(self._ep_of[i]), int(self._row_of[i])
        try:
            return np.asarray(self._file(ep)["image"][row])
        except (OSError, KeyError, RuntimeError) as err:
            raise ValueError(f"{self.episodes[ep].path}: image row {row} unreadable (corrupt file?): {err}") from None

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        n = self._n
        if not -n <= i < n:
            raise IndexError(f"sample {i} out of range for {n} samples")
        i = int(i) % n
        lab = self._labels
        img = self.image(i)
        return {
            "image": torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))),
            "speed": torch.tensor([lab["speed"][i]], dtype=torch.float32),
            "action": torch.tensor([lab["steer"][i], lab["throttle"][i], lab["brake"][i]], dtype=torch.float32),
            "command": torch.tensor(int(lab["branch"][i]), dtype=torch.int64),
            "guidance_yaw": torch.from_numpy(lab["guidance_yaw"][i].copy()),
            "guidance_xy": torch.from_numpy(lab["guidance_xy"][i].copy()),
            "guidance_sim_yaw": torch.from_numpy(lab["guidance_sim_yaw"][i].copy()),
            "episode": torch.tensor(int(lab["episode"][i]), dtype=torch.int64),
            "frame": torch.tensor(int(lab["frame"][i]), dtype=torch.int64),
            # schema-2 privileged labels (NaN / -1: unknown, e.g. a schema-1 file): targets of aux heads
            "privileged": torch.tensor([lab["target_speed"][i], lab["lead_distance"][i], lab["lead_speed"][i],
                                        lab["light_ahead"][i], lab["speed_reason"][i]], dtype=torch.float32),
        }

    def close(self) -> None:
        """Close this process's HDF5 handles (they reopen on the next read)."""
        if self._pid == os.getpid():
            for f in self._files.values():
                f.close()
        self._files = {}

    def __getstate__(self) -> dict[str, Any]:  # spawned workers get a pickled copy: no handles in it
        state = self.__dict__.copy()
        state.update(_files={}, _foreign=[], _pid=-1)
        return state


def _concat(columns: list[dict[str, np.ndarray]], k: int) -> dict[str, np.ndarray]:
    from yawil.data.schema import LABEL_FIELDS, field_dtype, field_shape

    return {
        name: np.concatenate([c[name] for c in columns])
        if columns
        else np.zeros((0, *field_shape(name, k)), dtype=field_dtype(name))
        for name in LABEL_FIELDS
    }


def split_episodes(
    roots: PathLike | Sequence[PathLike], val_fraction: float = 0.1, seed: int = 0
) -> tuple[list[int], list[int]]:
    """(train ids, validation ids), split by episode: a seeded permutation of the sorted ids of the manifests.

    The validation side gets round(val_fraction * n) episodes, at least one when val_fraction > 0, and the
    training side at least one. Same roots, fraction and seed: same split.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    ids = sorted(e.episode for _, e in manifest_episodes(as_roots(roots)))
    n = len(ids)
    n_val = 0 if val_fraction == 0.0 else max(1, round(val_fraction * n))
    if n - n_val < 1:
        raise ValueError(
            f"cannot split {n} episode(s) of {[str(r) for r in as_roots(roots)]} with val_fraction={val_fraction}: "
            "need at least one episode on each side"
        )
    order = np.random.default_rng(seed).permutation(n)
    val = sorted(ids[i] for i in order[:n_val])
    train = sorted(ids[i] for i in order[n_val:])
    return train, val
