"""`yawil data subset`: the training sets of the square experiment (the paper's Table I), as new datasets.

Every frame falls in exactly one class:

- junction turn: command LEFT or RIGHT (a road-option turn);
- lane-follow curve: `lane_follow_turn` set and not a junction turn (the collector sets it only on
  LANEFOLLOW frames whose route ahead curves);
- straight: everything else (LANEFOLLOW on straight road, and STRAIGHT through junctions).

Subsets: `road-option-turns` (1) = junction turns + straight; `lane-follow-turns` (2) = lane-follow
curves + straight; `all` (3) = every frame. A subset is written as a complete dataset (copies of the
selected rows, same episode ids, same file layout) so that every reader, DrivingDataset included,
takes it as is. It is built in a temporary directory beside the destination and renamed into place at
the end: the destination either does not exist or is complete.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from yawil.data.dataset import load_episode_labels
from yawil.data.manifest import Manifest, normalise_config, read_manifest
from yawil.data.reader import open_episode
from yawil.data.schema import FrameRecord
from yawil.data.writer import DatasetWriter, _pid_alive
from yawil.fileio import _check_writable_parent
from yawil.sim.types import RoadOption

SUBSETS: tuple[str, ...] = ("road-option-turns", "lane-follow-turns", "all")
BLOCK = 256  # rows copied at a time


def frame_classes(command: np.ndarray, lane_follow_turn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(junction turn, lane-follow curve) masks; frames in neither are straight."""
    command = np.asarray(command)
    junction = np.isin(command, (int(RoadOption.LEFT), int(RoadOption.RIGHT)))
    curve = np.asarray(lane_follow_turn).astype(bool) & ~junction
    return junction, curve


def select_rows(command: np.ndarray, lane_follow_turn: np.ndarray, only: str) -> np.ndarray:
    """Boolean mask of the frames that subset `only` keeps."""
    junction, curve = frame_classes(command, lane_follow_turn)
    if only == "road-option-turns":
        return ~curve
    if only == "lane-follow-turns":
        return ~junction
    if only == "all":
        return np.ones(len(junction), dtype=bool)
    raise ValueError(f"subset must be one of {', '.join(SUBSETS)}, got {only!r}")


def subset_config(source: Manifest, only: str) -> dict[str, Any]:
    cfg = dict(source.config)
    cfg["subset"] = {"only": only, "source": str(source.root.resolve()), "parent": source.config.get("subset")}
    return normalise_config(cfg)


def write_subset(src: str | os.PathLike[str], dst: str | os.PathLike[str], only: str, quiet: bool = True) -> Manifest:
    """Write subset `only` of dataset `src` as a new dataset `dst`; returns its manifest.

    If `dst` already holds the same subset of the same source, nothing is done; any other existing `dst`
    is a ValueError, as is an unusable source episode file (naming it: a subset without it would silently be
    another experiment's training set); the temporary folder is then removed, `dst` never appears.
    """
    if only not in SUBSETS:
        raise ValueError(f"subset must be one of {', '.join(SUBSETS)}, got {only!r}")
    src, dst = Path(src), Path(dst)
    source = read_manifest(src)
    config = subset_config(source, only)
    if dst.exists():
        try:
            existing = read_manifest(dst)
        except ValueError:
            existing = None
        if existing is not None and existing.config == config:
            if not quiet:
                print(f"{dst} already holds subset {only} of {src}: nothing to do")
            return existing
        raise ValueError(f"{dst} already exists and is not subset {only!r} of {src}; remove it or choose another --out")
    if dst.resolve().is_relative_to(src.resolve()):
        raise ValueError(f"the subset {dst} must not be inside its source {src}")
    _check_writable_parent(dst, "--out")  # else the OS error names the temporary folder it is built in
    _remove_stale_tmp(dst)
    tmp = dst.with_name(f".{dst.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with DatasetWriter(tmp, config) as w:
            for entry in source.episodes:
                path = source.path_of(entry)
                labels = load_episode_labels(path, entry)  # a ValueError naming the file
                keep = np.nonzero(select_rows(labels["command"], labels["lane_follow_turn"], only))[0]
                if len(keep) == 0:
                    continue
                _copy_episode(w, path, keep, labels)
        manifest = read_manifest(tmp)
        os.rename(tmp, dst)  # atomic; fails rather than merge if dst appeared meanwhile
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    manifest.root = dst
    if not quiet:
        print(f"subset {only} of {src}: {manifest.frames} of {source.frames} frames, "
              f"{len(manifest.episodes)} of {len(source.episodes)} episodes -> {dst}")  # fmt: skip
    return manifest


def _copy_episode(w: DatasetWriter, path: Path, keep: np.ndarray, labels: dict[str, np.ndarray]) -> None:
    with open_episode(path) as src:
        a = src.attrs
        meta = dict(a["meta"])
        if a["route_length"] is not None:
            meta.setdefault("route_length", a["route_length"])
        with w.begin_episode(int(a["episode"]), str(a["town"]), str(a["weather"]), int(a["seed"]), meta) as ep:
            for lo in range(0, len(keep), BLOCK):
                rows = keep[lo : lo + BLOCK]
                try:
                    images = src.images(slice(int(rows[0]), int(rows[-1]) + 1))[rows - rows[0]]
                except (OSError, RuntimeError) as err:  # h5py's checksum or decode error names no file
                    raise ValueError(f"{path}: image rows {int(rows[0])}-{int(rows[-1])} cannot be decoded "
                                     f"(truncated or corrupt?): {err}; yawil data check names every bad file") from None
                for img, r in zip(images, rows, strict=True):
                    ep.append(FrameRecord.from_labels(img, labels, int(r)))
            ep.commit(str(a["outcome"]))


_TMP_RE = re.compile(r"^\.(.+)\.tmp-(\d+)$")


def _remove_stale_tmp(dst: Path) -> None:
    """Temporary subset directories of `dst` left by crashed processes."""
    if not dst.parent.is_dir():
        return
    for p in dst.parent.iterdir():
        m = _TMP_RE.match(p.name)
        if m and m.group(1) == dst.name and p.is_dir() and not _pid_alive(int(m.group(2))):
            shutil.rmtree(p, ignore_errors=True)
