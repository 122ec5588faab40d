"""Writing a dataset: one HDF5 file per episode, renamed into place whole, then listed in the manifest.

Crash safety comes from ordering: frames go to `episodes/.ep_NNNNNN.h5.<pid>.tmp`; `commit` closes it, renames
it to `episodes/ep_NNNNNN.h5`, and only then adds the episode to `manifest.json` (itself rewritten
atomically). A crash therefore loses at most the episode in progress, and a resumed collection asks
`has_episode` (the manifest) to skip what is done.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from yawil.data.manifest import (
    EPISODE_DIR,
    EpisodeEntry,
    Manifest,
    config_diff,
    episode_filename,
    manifest_lock,
    normalise_config,
    read_manifest,
    write_manifest,
)
from yawil.data.schema import (
    COMMAND_NAMES,
    EPISODE_FORMAT,
    IMAGE_SHAPE,
    LABEL_FIELDS,
    SCALAR_FIELDS,
    SCHEMA_VERSION,
    FrameRecord,
    field_dtype,
    field_shape,
)
from yawil.fileio import require_free_space

# Chosen by `benchmarks/loading.py --compare` (docs/dataset.md): one frame per chunk, so a random read
# decompresses exactly one image (8-frame chunks read 6x slower); lzf because it decodes ~1.6x faster
# than gzip level 1, at ~40% more bytes (39 vs 28 kB/frame on synthetic street images).
IMAGE_COMPRESSION: str | None = "lzf"
IMAGE_COMPRESSION_OPTS: int | None = None
IMAGE_CHUNK_FRAMES = 1
LABEL_CHUNK_ROWS = 1024
FLUSH_EVERY = 64  # frames buffered in memory between writes (~3.4 MB of images)

MIN_FREE_BYTES = 32 << 20  # stop before a write can fail: ~10 flushes of images, and the file's metadata


def check_free_space(path: Path) -> None:
    """OSError(ENOSPC) naming the folder when its disk has less than MIN_FREE_BYTES free.

    Why before writing: once HDF5 has failed a write, closing the file fails again at every object h5py
    frees (a hundred 'Exception ignored' tracebacks) and the process segfaulted. Checked before each flush,
    the episode is discarded cleanly and a rerun resumes."""
    require_free_space(path.parent, MIN_FREE_BYTES)


_TMP_RE = re.compile(r"^\.ep_\d+\.h5\.(\d+)\.tmp$")


class DatasetWriter:
    """Creates a dataset at `root`, or reopens it to resume; `config` must equal the stored one.

    `config` is a JSON-serialisable dict describing how the data was made; by convention it holds
    "guidance" (`GuidanceConfig.to_dict()`: spacing, count, reference) and "collector" (the collector's
    settings). When "guidance" has a "count", every frame's guidance_yaw must have that length K.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        config: dict[str, Any],
        *,
        image_compression: str | None = IMAGE_COMPRESSION,
        image_compression_opts: int | None = IMAGE_COMPRESSION_OPTS,
        image_chunk_frames: int = IMAGE_CHUNK_FRAMES,
    ) -> None:
        self.root = Path(root)
        self.config = normalise_config(config)
        if image_chunk_frames < 1:
            raise ValueError(f"image_chunk_frames must be >= 1, got {image_chunk_frames}")
        self.image_compression = image_compression
        self.image_compression_opts = image_compression_opts
        self.image_chunk_frames = image_chunk_frames
        self._open: dict[int, EpisodeWriter] = {}
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"dataset root {self.root} exists and is not a directory")
        (self.root / EPISODE_DIR).mkdir(parents=True, exist_ok=True)
        with manifest_lock(self.root):
            if (self.root / "manifest.json").exists():
                self._check_config(read_manifest(self.root))
            else:
                write_manifest(Manifest(root=self.root, config=self.config))
        self._remove_stale_tmp()

    def _check_config(self, manifest: Manifest) -> None:
        if manifest.schema_version != SCHEMA_VERSION:
            raise ValueError(
                f"{self.root / 'manifest.json'}: a schema-{manifest.schema_version} dataset; this yawil writes schema "
                f"{SCHEMA_VERSION} and does not mix the two in one folder: collect into a new folder (the old one still reads)"
            )
        diff = config_diff(manifest.config, self.config)
        if diff:
            raise ValueError(
                f"{self.root / 'manifest.json'}: config differs from the stored one (stored != given): "
                + "; ".join(diff)
            )

    def _remove_stale_tmp(self) -> None:
        """Delete temporary episode files left by crashed writers (their process no longer exists)."""
        for p in (self.root / EPISODE_DIR).iterdir():
            m = _TMP_RE.match(p.name)
            if m and not _pid_alive(int(m.group(1))):
                with contextlib.suppress(OSError):
                    p.unlink()

    @property
    def expected_k(self) -> int | None:
        g = self.config.get("guidance")
        if isinstance(g, dict) and isinstance(g.get("count"), int):
            return int(g["count"])
        return None

    def manifest(self) -> Manifest:
        return read_manifest(self.root)

    def has_episode(self, episode_id: int) -> bool:
        """True when the episode is committed (listed in the manifest); its file is then complete."""
        return int(episode_id) in read_manifest(self.root).episode_ids()

    def begin_episode(
        self, episode_id: int, town: str, weather: str, seed: int, meta: dict[str, Any] | None = None
    ) -> EpisodeWriter:
        """Start an episode. `meta` is free JSON; a "route_length" (metres) key is also kept in the manifest."""
        if isinstance(episode_id, bool) or not isinstance(episode_id, (int, np.integer)) or episode_id < 0:
            raise ValueError(f"episode_id must be an int >= 0, got {episode_id!r}")
        episode_id = int(episode_id)
        if episode_id in self._open:
            raise ValueError(f"episode {episode_id} is already being written by this writer")
        if self.has_episode(episode_id):
            raise ValueError(f"episode {episode_id} already exists in {self.root}; a resumed collection must skip it")
        ep = EpisodeWriter(self, episode_id, town, weather, seed, meta or {})
        self._open[episode_id] = ep
        return ep

    def add_episode_file(self, entry: EpisodeEntry, data: bytes) -> None:
        """Store an episode file finished by another writer (a Ray worker's, on its own machine): written whole
        under the temporary name an EpisodeWriter of this process would use, fsynced, renamed into place, then
        listed in the manifest: the order and crash recovery of `commit`."""
        if entry.file != episode_filename(entry.episode):
            raise ValueError(f"episode {entry.episode}: file {entry.file!r}, expected {episode_filename(entry.episode)!r}")
        if entry.episode in self._open or self.has_episode(entry.episode):
            raise ValueError(f"episode {entry.episode} already exists in {self.root}; a resumed collection must skip it")
        final = self.root / entry.file
        tmp = _tmp_path(final)
        check_free_space(tmp)
        try:
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, final)
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        self._list(replace(entry, bytes=len(data)))

    def _finish(self, ep: EpisodeWriter, entry: EpisodeEntry | None) -> None:
        self._open.pop(ep.episode_id, None)
        if entry is not None:
            self._list(entry)

    def _list(self, entry: EpisodeEntry) -> None:
        """Add a committed episode to the manifest (rewritten atomically under its lock)."""
        with manifest_lock(self.root):
            manifest = read_manifest(self.root)
            self._check_config(manifest)
            if entry.episode in manifest.episode_ids():
                raise ValueError(f"episode {entry.episode} was committed meanwhile by another writer in {self.root}")
            manifest.episodes.append(entry)
            write_manifest(manifest)

    def close(self) -> None:
        """Discard episodes still open (uncommitted) so no temporary file is left behind."""
        for ep in list(self._open.values()):
            ep.discard()

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EpisodeWriter:
    """Frames of one episode on their way to disk. Use as a context manager: an exception discards it."""

    def __init__(
        self, writer: DatasetWriter, episode_id: int, town: str, weather: str, seed: int, meta: dict[str, Any]
    ) -> None:
        for name, value in (("town", town), ("weather", weather)):
            if not isinstance(value, str) or not value.strip():
                raise ValueError(f"episode {episode_id}: {name} must be a non-empty string, got {value!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise ValueError(f"episode {episode_id}: seed must be an int, got {seed!r}")
        meta = normalise_config(meta)
        rl = meta.get("route_length")
        if rl is not None and (not isinstance(rl, (int, float)) or not math.isfinite(rl) or rl < 0):
            raise ValueError(f"episode {episode_id}: meta['route_length'] must be a number >= 0 (metres), got {rl!r}")
        self.writer = writer
        self.episode_id = episode_id
        self.town, self.weather, self.seed, self.meta = town, weather, int(seed), meta
        self.route_length: float | None = None if rl is None else float(rl)
        self.final_path = writer.root / episode_filename(episode_id)
        self.tmp_path = _tmp_path(self.final_path)
        check_free_space(self.tmp_path)
        self._h5: h5py.File | None = h5py.File(self.tmp_path, "w", libver="latest")
        self._k: int | None = None
        self._n = 0
        self._last_frame = -1
        self._buf: dict[str, list[Any]] = {name: [] for name in ("image", *LABEL_FIELDS)}
        self._done = False

    def __len__(self) -> int:
        return self._n + len(self._buf["image"])

    def append(self, rec: FrameRecord) -> None:
        """Validate and buffer one frame; ValueError (naming episode and frame) if it breaks the schema."""
        if self._done:
            raise ValueError(f"episode {self.episode_id} is already committed or discarded")
        where = f"episode {self.episode_id} frame {rec.frame!r}"
        rec.validate(where)
        k = rec.k
        if self._k is None:
            expected = self.writer.expected_k
            if expected is not None and k != expected:
                raise ValueError(f"{where}: guidance K={k} but the dataset config says guidance.count={expected}")
            self._k = k
            self._create_datasets(k)
        elif k != self._k:
            raise ValueError(f"{where}: guidance K={k} differs from K={self._k} of earlier frames")
        if int(rec.frame) <= self._last_frame:
            raise ValueError(f"{where}: frame indices must increase (previous {self._last_frame})")
        self._last_frame = int(rec.frame)
        b = self._buf
        b["image"].append(rec.image.copy())  # the caller may reuse its buffer
        for name in SCALAR_FIELDS:
            b[name].append(getattr(rec, name))
        for name in ("guidance_yaw", "guidance_xy", "guidance_sim_yaw", "pose"):
            b[name].append(np.array(getattr(rec, name), dtype=field_dtype(name)))
        if len(b["image"]) >= FLUSH_EVERY:
            self._flush()

    def _create_datasets(self, k: int) -> None:
        assert self._h5 is not None
        w = self.writer
        self._h5.create_dataset(
            "image",
            shape=(0, *IMAGE_SHAPE),
            maxshape=(None, *IMAGE_SHAPE),
            dtype=np.uint8,
            chunks=(w.image_chunk_frames, *IMAGE_SHAPE),
            compression=w.image_compression,
            compression_opts=w.image_compression_opts,
            fletcher32=True,  # a checksum per chunk: a flipped byte fails the read (and `data check`), never passes
        )
        for name in LABEL_FIELDS:
            shape = field_shape(name, k)
            self._h5.create_dataset(
                name,
                shape=(0, *shape),
                maxshape=(None, *shape),
                dtype=field_dtype(name),
                chunks=(LABEL_CHUNK_ROWS, *shape),
                compression="gzip",
                compression_opts=4,
                shuffle=True,
                fletcher32=True,
            )

    def _flush(self) -> None:
        m = len(self._buf["image"])
        if m == 0:
            return
        assert self._h5 is not None
        check_free_space(self.tmp_path)
        n0, n1 = self._n, self._n + m
        for name, values in self._buf.items():
            ds = self._h5[name]
            ds.resize(n1, axis=0)
            ds[n0:n1] = np.asarray(values, dtype=field_dtype(name))
            values.clear()
        self._n = n1

    def commit(self, outcome: str) -> EpisodeEntry:
        """Finish the file, rename it into place, list it in the manifest. Returns the manifest entry."""
        if self._done:
            raise ValueError(f"episode {self.episode_id} is already committed or discarded")
        if not isinstance(outcome, str) or not outcome.strip() or "\n" in outcome:
            raise ValueError(f"episode {self.episode_id}: outcome must be a one-line non-empty string, got {outcome!r}")
        if len(self) == 0:
            raise ValueError(f"episode {self.episode_id}: no frames to commit; discard() it instead")
        self._flush()
        h5 = self._h5
        assert h5 is not None and self._k is not None
        attrs = {
            "format": EPISODE_FORMAT,
            "schema_version": SCHEMA_VERSION,
            "episode": self.episode_id,
            "town": self.town,
            "weather": self.weather,
            "seed": self.seed,
            "outcome": outcome,
            "frames": self._n,
            "K": self._k,
            "route_length": math.nan if self.route_length is None else self.route_length,
            "config": json.dumps(self.writer.config, sort_keys=True),
            "meta": json.dumps(self.meta, sort_keys=True),
        }
        for key, value in attrs.items():
            h5.attrs[key] = value
        cmd = h5["command"][:]
        commands = {name: int(np.sum(cmd == value)) for value, name in COMMAND_NAMES.items()}
        noise_frames = int(np.sum(h5["noise"][:]))
        lft_frames = int(np.sum(h5["lane_follow_turn"][:]))
        h5.flush()
        h5.close()
        self._h5 = None
        with open(self.tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(self.tmp_path, self.final_path)
        self._done = True
        entry = EpisodeEntry(
            episode=self.episode_id,
            file=episode_filename(self.episode_id),
            frames=self._n,
            town=self.town,
            weather=self.weather,
            seed=self.seed,
            outcome=outcome,
            route_length=self.route_length,
            commands=commands,
            noise_frames=noise_frames,
            lane_follow_turn_frames=lft_frames,
            bytes=self.final_path.stat().st_size,
        )
        self.writer._finish(self, entry)
        return entry

    def discard(self) -> None:
        """Drop the episode: its temporary file is deleted and the manifest is untouched."""
        if self._done:
            return
        self._done = True
        if self._h5 is not None:
            with contextlib.suppress(Exception):
                self._h5.close()
            self._h5 = None
        with contextlib.suppress(OSError):
            self.tmp_path.unlink()
        self.writer._finish(self, None)

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if not self._done:
            self.discard()  # leaving the block without commit() (or by an exception) drops the episode

    def __del__(self) -> None:
        if not getattr(self, "_done", True):
            self.discard()


def _tmp_path(final: Path) -> Path:
    """Where an episode file is written before its rename: named for this process (see `_TMP_RE`), so that a
    writer that finds it after a crash knows whether its writer still runs."""
    return final.with_name(f".{final.name}.{os.getpid()}.tmp")


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
