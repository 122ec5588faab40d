"""`manifest.json`: which episodes a dataset holds, with the counts needed to plan training and subsets.

The manifest is the dataset's table of contents: an episode exists when, and only when, it is listed here
(its file is renamed into place before the entry is added). It is rewritten atomically (temporary file +
rename) under an exclusive lock, so several collector processes may share one root and a crash never
leaves a half-written manifest.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from yawil.data.schema import DATASET_FORMAT, READABLE_VERSIONS, SCHEMA_VERSION

MANIFEST_NAME = "manifest.json"
LOCK_NAME = ".manifest.lock"
EPISODE_DIR = "episodes"


def episode_filename(episode_id: int) -> str:
    return f"{EPISODE_DIR}/ep_{episode_id:06d}.h5"


@dataclass
class EpisodeEntry:
    episode: int
    file: str  # relative to the dataset root
    frames: int
    town: str
    weather: str
    seed: int
    outcome: str
    route_length: float | None
    commands: dict[str, int]  # road option name -> frames
    noise_frames: int = 0
    lane_follow_turn_frames: int = 0
    bytes: int = 0

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str) -> EpisodeEntry:
        try:
            return cls(
                episode=int(d["episode"]),
                file=str(d["file"]),
                frames=int(d["frames"]),
                town=str(d["town"]),
                weather=str(d["weather"]),
                seed=int(d["seed"]),
                outcome=str(d["outcome"]),
                route_length=None if d.get("route_length") is None else float(d["route_length"]),
                commands={str(k): int(v) for k, v in dict(d["commands"]).items()},
                noise_frames=int(d.get("noise_frames", 0)),
                lane_follow_turn_frames=int(d.get("lane_follow_turn_frames", 0)),
                bytes=int(d.get("bytes", 0)),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{where}: bad episode entry {d!r}: {err!r}") from None


@dataclass
class Manifest:
    root: Path
    config: dict[str, Any]
    schema_version: int = SCHEMA_VERSION
    episodes: list[EpisodeEntry] = field(default_factory=list)

    def episode_ids(self) -> list[int]:
        return [e.episode for e in self.episodes]

    def entry(self, episode_id: int) -> EpisodeEntry:
        for e in self.episodes:
            if e.episode == episode_id:
                return e
        raise KeyError(f"episode {episode_id} is not in {self.root / MANIFEST_NAME}")

    def path_of(self, entry: EpisodeEntry) -> Path:
        return self.root / entry.file

    @property
    def frames(self) -> int:
        return sum(e.frames for e in self.episodes)

    def by_command(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for e in self.episodes:
            for k, v in e.commands.items():
                out[k] = out.get(k, 0) + v
        return out

    def by_weather(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for e in self.episodes:
            out[e.weather] = out.get(e.weather, 0) + e.frames
        return out

    def to_json(self) -> dict[str, Any]:
        eps = sorted(self.episodes, key=lambda e: e.episode)
        return {
            "format": DATASET_FORMAT,
            "schema_version": self.schema_version,
            "config": self.config,
            "totals": {  # derived, for people reading the file; ignored when read back
                "episodes": len(eps),
                "frames": self.frames,
                "by_command": dict(sorted(self.by_command().items())),
                "by_weather": dict(sorted(self.by_weather().items())),
            },
            "episodes": [asdict(e) for e in eps],
        }


def read_manifest(root: str | os.PathLike[str]) -> Manifest:
    """Read `root/manifest.json`; ValueError naming the file when it is missing, malformed or too new."""
    root = Path(root)
    path = root / MANIFEST_NAME
    if not path.is_file():
        raise ValueError(f"{path}: no manifest; is {root} a yawil dataset (made by DatasetWriter)?")
    try:
        d = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: unreadable manifest: {err}") from None
    if not isinstance(d, dict) or d.get("format") != DATASET_FORMAT:
        raise ValueError(f"{path}: 'format' must be {DATASET_FORMAT!r}, got {d.get('format') if isinstance(d, dict) else d!r}")
    version = d.get("schema_version")
    if version not in READABLE_VERSIONS or isinstance(version, bool):
        raise ValueError(f"{path}: schema_version {version!r} is not supported (this yawil reads {list(READABLE_VERSIONS)})")
    if not isinstance(d.get("config"), dict) or not isinstance(d.get("episodes"), list):
        raise ValueError(f"{path}: 'config' must be an object and 'episodes' a list")
    episodes = [EpisodeEntry.from_dict(e, str(path)) for e in d["episodes"]]
    ids = [e.episode for e in episodes]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise ValueError(f"{path}: episode ids listed twice: {dup}")
    return Manifest(root=root, config=d["config"], schema_version=version, episodes=episodes)


def write_manifest(manifest: Manifest) -> None:
    atomic_write_text(manifest.root / MANIFEST_NAME, json.dumps(manifest.to_json(), indent=1) + "\n")


def atomic_write_text(path: Path, text: str) -> None:
    """Readers see the old file or the new one, never half (`yawil.fileio.write_atomic`)."""
    from yawil.fileio import write_atomic

    write_atomic(path, text)


@contextlib.contextmanager
def manifest_lock(root: Path) -> Iterator[None]:
    """Exclusive advisory lock on the dataset root, held while the manifest is read-modified-written."""
    root.mkdir(parents=True, exist_ok=True)
    with open(root / LOCK_NAME, "a") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def normalise_config(config: dict[str, Any]) -> dict[str, Any]:
    """JSON round trip, so tuples and lists (and int keys) compare as they will once stored."""
    if not isinstance(config, dict):
        raise ValueError(f"dataset config must be a dict, got {type(config).__name__}")
    try:
        out: dict[str, Any] = json.loads(json.dumps(config, sort_keys=True, allow_nan=False))
    except (TypeError, ValueError) as err:
        raise ValueError(f"dataset config must be JSON-serialisable (finite numbers, str keys): {err}") from None
    return out


def config_diff(old: Any, new: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ, each as 'key: stored != given'."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        for k in sorted(set(old) | set(new)):
            key = f"{prefix}.{k}" if prefix else str(k)
            if k not in old:
                out.append(f"{key}: <absent> != {new[k]!r}")
            elif k not in new:
                out.append(f"{key}: {old[k]!r} != <absent>")
            else:
                out.extend(config_diff(old[k], new[k], key))
        return out
    return [] if old == new else [f"{prefix or '<root>'}: {old!r} != {new!r}"]
