"""`yawil data check`: read every episode of a dataset and name the files that break the schema.

A file is bad when it does not open, lacks a dataset or attribute, disagrees with its manifest entry or with the
manifest's guidance settings, holds labels out of range or NaN (the same test `DrivingDataset` applies,
`schema.label_problems`, and NaN privileged labels beside a known expert reason), or has image chunks that
cannot be decoded (every image is read). Episode files that the manifest does not
list (a crash between rename and manifest update) and stale temporary files are reported as notes: they
are not part of the dataset, so they do not make it bad.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from yawil.data.dataset import load_episode_labels
from yawil.data.manifest import EPISODE_DIR, read_manifest
from yawil.data.reader import open_episode
from yawil.data.schema import COMMAND_NAMES, MAYBE_UNKNOWN

IMAGE_BLOCK = 256  # rows decoded at a time (about 13 MB)
_EPISODE_RE = re.compile(r"^ep_\d+\.h5$")


@dataclass
class CheckReport:
    root: Path
    episodes: int = 0  # episode files checked
    frames: int = 0  # frames in the good ones
    bad: dict[str, list[str]] = field(default_factory=dict)  # file (or manifest) -> problems
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.bad

    def lines(self) -> list[str]:
        out = [f"{self.root}: {self.episodes} episode file(s), {len(self.bad)} bad, {self.frames} good frames"]
        for name, problems in sorted(self.bad.items()):
            out.append(f"BAD {name}")
            out.extend(f"    {p}" for p in problems)
        out.extend(f"note: {n}" for n in self.notes)
        out.append("OK" if self.ok else "FAILED")
        return out


def check_images(path: Path) -> list[str]:
    """Decode every image of an episode file; problems found (empty when all decode)."""
    with open_episode(path) as ep:
        for lo in range(0, len(ep), IMAGE_BLOCK):
            hi = min(lo + IMAGE_BLOCK, len(ep))
            try:
                block = ep.images(slice(lo, hi))
            except (OSError, RuntimeError) as err:
                return [f"image rows {lo}-{hi - 1} cannot be decoded (truncated or corrupt?): {err}"]
            if block.dtype != np.uint8:
                return [f"image: dtype {block.dtype} != expected uint8"]
    return []


def privileged_problems(labels: dict[str, np.ndarray]) -> list[str]:
    """NaN ("unknown") in a privileged label on a row whose expert reason is known: the expert writes its
    target speed, reason and lead together (schema-1 files and frames made without an expert have all of them
    unknown), so a NaN beside a known reason is damage, and aux training would silently skip those rows."""
    known = labels["speed_reason"] >= 0
    problems = []
    for name in sorted(MAYBE_UNKNOWN):
        bad = known & np.isnan(labels[name])
        if bad.any():
            rows = np.nonzero(bad)[0]
            problems.append(f"{name}: NaN at {len(rows)} row(s) whose speed_reason is known, first row "
                            f"{int(rows[0])} (expected a number >= 0 there; NaN only with speed_reason -1)")
    return problems


def guidance_problems(path: Path, manifest_guidance: object) -> list[str]:
    """The episode's guidance settings (its `config` attribute) against the manifest's: an episode of another
    reference or spacing has guidance vectors that mean something else, and a model would learn both."""
    if not isinstance(manifest_guidance, dict):
        return []  # noted once for the dataset
    with open_episode(path) as ep:
        config = ep.attrs["config"]
    own = config.get("guidance") if isinstance(config, dict) else None
    if not isinstance(own, dict):
        return []  # a file that names none contradicts nothing (its K is checked against guidance.count)
    return [f"guidance {key}={own.get(key)!r} in its attributes, the manifest says {manifest_guidance.get(key)!r}"
            for key in sorted(set(own) | set(manifest_guidance)) if own.get(key) != manifest_guidance.get(key)]


def has_checksums(path: Path) -> bool:
    """Whether the episode's images carry HDF5 fletcher32 checksums (files written before they did do not)."""
    import h5py

    with h5py.File(path, "r") as h5:
        return bool(h5["image"].fletcher32)


def remove_bad_episodes(root: str | os.PathLike[str], images: bool = False) -> list[str]:
    """Drop from the manifest, and delete, every episode file that fails `check_dataset`; one line per file.

    Why: a resumed `collect` counted a truncated, missing or zeroed episode as done and the dataset stayed
    broken. Episodes are deterministic in their seed, so a dropped one is re-collected identically."""
    from yawil.data.manifest import manifest_lock, write_manifest

    report = check_dataset(root, images=images)
    if not report.bad or "manifest.json" in report.bad:
        return []
    root = Path(root)
    with manifest_lock(root):
        manifest = read_manifest(root)
        bad = [e for e in manifest.episodes if e.file in report.bad]
        manifest.episodes = [e for e in manifest.episodes if e.file not in report.bad]
        write_manifest(manifest)
    for e in bad:
        (root / e.file).unlink(missing_ok=True)
    return [f"{e.file}: {'; '.join(report.bad[e.file])}" for e in bad]


def check_dataset(root: str | os.PathLike[str], images: bool = True) -> CheckReport:
    """Check a whole dataset root; `images=False` skips decoding images (labels and structure only)."""
    root = Path(root)
    report = CheckReport(root)
    try:
        manifest = read_manifest(root)
    except ValueError as err:
        report.bad["manifest.json"] = [str(err)]
        return report
    g = manifest.config.get("guidance")
    k = int(g["count"]) if isinstance(g, dict) and isinstance(g.get("count"), int) else None
    if k is None:
        report.notes.append("manifest config has no guidance.count: K of the files is not checked against it")
    unchecked = 0
    for entry in manifest.episodes:
        path = manifest.path_of(entry)
        report.episodes += 1
        if not path.is_file():
            report.bad[entry.file] = [f"listed in the manifest but missing: {path}"]
            continue
        size = path.stat().st_size
        size_problem = [f"{size} bytes, the manifest says {entry.bytes} (truncated or rewritten?)"] \
            if entry.bytes and size != entry.bytes else []  # reported when nothing more specific is found
        try:
            labels = load_episode_labels(path, entry, k)
        except ValueError as err:
            report.bad[entry.file] = [str(err).removeprefix(f"{path}: ")]
            continue
        problems = privileged_problems(labels) + guidance_problems(path, g)
        counts = {name: int(np.sum(labels["command"] == value)) for value, name in COMMAND_NAMES.items()}
        if counts != entry.commands:
            problems.append(f"command counts {counts} differ from the manifest's {entry.commands}")
        if images:
            problems += check_images(path)
            if not problems and not has_checksums(path):
                unchecked += 1
        problems = problems or size_problem
        if problems:
            report.bad[entry.file] = problems
        else:
            report.frames += entry.frames
    if unchecked:
        report.notes.append(f"{unchecked} episode file(s) carry no checksums (written before yawil stored them): "
                            "a corrupt image there may decode without an error")
    listed = {Path(e.file).name for e in manifest.episodes}
    ep_dir = root / EPISODE_DIR
    for p in sorted(ep_dir.iterdir()) if ep_dir.is_dir() else []:
        if _EPISODE_RE.match(p.name) and p.name not in listed:
            report.notes.append(f"{EPISODE_DIR}/{p.name} is not in the manifest (ignored by readers; delete it or re-collect)")
        elif p.name.endswith(".tmp"):
            report.notes.append(f"{EPISODE_DIR}/{p.name} is a temporary file of an unfinished episode")
    return report
