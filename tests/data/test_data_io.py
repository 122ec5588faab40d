"""Writing and reading episodes: round trip, manifest, resume, config mismatch, bad records, crash safety."""

from __future__ import annotations

import errno
import json
import os
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from yawil.data.manifest import read_manifest
from yawil.data.reader import open_episode
from yawil.data.schema import SCHEMA_VERSION, FrameRecord
from yawil.data.synthetic import synthetic_episode, write_synthetic_dataset
from yawil.data.writer import DatasetWriter

K = 4
CONFIG = {"guidance": {"spacing": 2.0, "count": K, "reference": "route"}, "collector": {"noise": 0.1}}


def records(n: int, seed: int = 0) -> list[FrameRecord]:
    return synthetic_episode(np.random.default_rng(seed), n, K)


def test_round_trip_every_field(tmp_path: Path) -> None:
    recs = records(70)  # > FLUSH_EVERY, so frames cross a flush
    with DatasetWriter(tmp_path, CONFIG) as w:
        ep = w.begin_episode(7, "town01", "ClearNoon", 123, {"route_length": 250.5, "note": "x"})
        for r in recs:
            ep.append(r)
        entry = ep.commit("goal")
    assert entry.frames == 70 and entry.file == "episodes/ep_000007.h5"
    with open_episode(tmp_path / entry.file) as rd:
        assert len(rd) == 70 and rd.k == K and rd.episode == 7
        assert rd.attrs["town"] == "town01" and rd.attrs["weather"] == "ClearNoon" and rd.attrs["seed"] == 123
        assert rd.attrs["outcome"] == "goal" and rd.attrs["route_length"] == 250.5
        assert rd.attrs["config"] == CONFIG and rd.attrs["meta"] == {"route_length": 250.5, "note": "x"}
        for i in (0, 33, 64, 69, -1):
            got, want = rd[i], recs[i]
            np.testing.assert_array_equal(got.image, want.image)
            for name in ("guidance_yaw", "guidance_xy", "guidance_sim_yaw"):
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
            for name in ("steer", "throttle", "brake", "speed"):
                assert getattr(got, name) == pytest.approx(getattr(want, name), abs=1e-6)
            assert (got.command, got.frame, got.noise, got.lane_follow_turn) == (
                want.command, want.frame, want.noise, want.lane_follow_turn)  # fmt: skip
            assert got.pose == pytest.approx(want.pose)
        with pytest.raises(IndexError):
            rd[70]


def test_manifest_counts_and_resume(tmp_path: Path) -> None:
    m = write_synthetic_dataset(tmp_path, episodes=3, frames=12, k=K)
    assert m.episode_ids() == [0, 1, 2] and m.frames == 36
    assert sum(m.by_command().values()) == 36 and sum(m.by_weather().values()) == 36
    raw = json.loads((tmp_path / "manifest.json").read_text())
    assert raw["schema_version"] == SCHEMA_VERSION == 2 and raw["totals"]["frames"] == 36
    # A resumed writer sees the committed episodes and refuses to write one twice.
    config = read_manifest(tmp_path).config
    w = DatasetWriter(tmp_path, config)
    assert w.has_episode(1) and not w.has_episode(3)
    with pytest.raises(ValueError, match="already exists"):
        w.begin_episode(1, "town01", "ClearNoon", 0)
    ep = w.begin_episode(3, "town01", "WetNoon", 5)
    for r in records(5, seed=3):
        ep.append(r)
    ep.commit("timeout")
    assert read_manifest(tmp_path).episode_ids() == [0, 1, 2, 3]


def test_config_mismatch_names_keys(tmp_path: Path) -> None:
    DatasetWriter(tmp_path, CONFIG)
    other = {"guidance": {"spacing": 3.0, "count": K, "reference": "route"}, "collector": {"noise": 0.1, "x": 1}}
    with pytest.raises(ValueError, match=r"collector\.x: <absent> != 1; guidance\.spacing: 2\.0 != 3\.0"):
        DatasetWriter(tmp_path, other)
    DatasetWriter(tmp_path, json.loads(json.dumps(CONFIG)))  # equal config: fine


def test_bad_records_are_refused(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path, CONFIG)
    ep = w.begin_episode(0, "town01", "ClearNoon", 0)
    good = records(2)
    ep.append(good[0])
    bad_cases = {
        "steer": replace(good[1], steer=1.5),
        "brake": replace(good[1], brake=float("nan")),
        "speed": replace(good[1], speed=-0.1),
        "command": replace(good[1], command=0),
        "image": replace(good[1], image=np.zeros((88, 200), np.uint8)),
        "guidance_xy": replace(good[1], guidance_xy=np.zeros(3, np.float32)),
        "K=": replace(good[1], guidance_yaw=np.zeros(5, np.float32), guidance_sim_yaw=np.zeros(5, np.float32),
                      guidance_xy=np.zeros(10, np.float32)),
        "increase": replace(good[1], frame=good[0].frame),
    }  # fmt: skip
    for field, rec in bad_cases.items():
        with pytest.raises(ValueError, match=field):
            ep.append(rec)
    ep.append(good[1])
    assert ep.commit("goal").frames == 2


def test_crash_and_discard_leave_no_episode(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path, CONFIG)
    with pytest.raises(RuntimeError), w.begin_episode(0, "town01", "ClearNoon", 0) as ep:
        ep.append(records(1)[0])
        raise RuntimeError("simulator died")
    assert read_manifest(tmp_path).episodes == []
    assert list((tmp_path / "episodes").iterdir()) == []
    # A temporary file of a dead writer process is removed when the dataset is reopened.
    stale = tmp_path / "episodes" / ".ep_000005.h5.999999999.tmp"
    stale.write_bytes(b"partial")
    DatasetWriter(tmp_path, CONFIG)
    assert not stale.exists()


def test_reader_names_bad_files(tmp_path: Path) -> None:
    m = write_synthetic_dataset(tmp_path, episodes=1, frames=4, k=K)
    path = m.path_of(m.episodes[0])
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(ValueError, match=r"ep_000000\.h5.*schema_version 99"):
        open_episode(path)
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)
    with pytest.raises(ValueError, match=r"ep_000000\.h5.*truncated or corrupt"):
        open_episode(path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ValueError, match="manifest.json"):
        read_manifest(tmp_path)


def test_synthetic_dataset_is_deterministic(tmp_path: Path) -> None:
    a = write_synthetic_dataset(tmp_path / "a", episodes=1, frames=6, k=K, seed=3)
    b = write_synthetic_dataset(tmp_path / "b", episodes=1, frames=6, k=K, seed=3)
    with open_episode(a.path_of(a.episodes[0])) as ra, open_episode(b.path_of(b.episodes[0])) as rb:
        np.testing.assert_array_equal(ra.images(slice(None)), rb.images(slice(None)))
        for name, col in ra.labels().items():
            np.testing.assert_array_equal(col, rb.labels()[name])


def _downgrade_to_schema_1(root: Path) -> None:
    """What a schema-1 dataset looks like: no V2 fields, version 1 in the files and the manifest."""
    from yawil.data.schema import V2_FIELDS

    for path in sorted((root / "episodes").glob("ep_*.h5")):
        with h5py.File(path, "r+") as f:
            for name in V2_FIELDS:
                del f[name]
            f.attrs["schema_version"] = 1
    raw = json.loads((root / "manifest.json").read_text())
    raw["schema_version"] = 1
    (root / "manifest.json").write_text(json.dumps(raw))


def test_schema_1_datasets_still_read_and_train_but_take_no_new_episodes(tmp_path: Path) -> None:
    from yawil.data.check import check_dataset
    from yawil.data.dataset import DrivingDataset

    write_synthetic_dataset(tmp_path / "old", episodes=2, frames=10, k=K)
    _downgrade_to_schema_1(tmp_path / "old")
    m = read_manifest(tmp_path / "old")
    assert m.schema_version == 1
    with open_episode(m.path_of(m.episodes[0])) as ep:
        labels = ep.labels()
        rec = ep[0]
    assert (labels["driver"] == 0).all() and (labels["round"] == 0).all() and (labels["speed_reason"] == -1).all()
    assert np.isnan(labels["target_speed"]).all() and np.isnan(rec.lead_distance) and rec.light_ahead == -1
    assert check_dataset(tmp_path / "old").ok
    ds = DrivingDataset(tmp_path / "old")
    sample = ds[0]
    assert torch_isnan_all(sample["privileged"][:3]) and float(sample["privileged"][3]) == -1.0
    with pytest.raises(ValueError, match="schema-1 dataset"):
        DatasetWriter(tmp_path / "old", m.config)


def torch_isnan_all(t: object) -> bool:
    import torch

    return bool(torch.isnan(t).all())  # type: ignore[arg-type]


def test_privileged_fields_are_validated(tmp_path: Path) -> None:
    rec = synthetic_episode(np.random.default_rng(0), 1, K)[0]
    for field, bad in (("driver", 3), ("round", -1), ("speed_reason", 8), ("light_ahead", 2), ("target_speed", -1.0),
                       ("lead_distance", float("inf"))):
        with pytest.raises(ValueError, match=field):
            replace(rec, **{field: bad}).validate()
    replace(rec, target_speed=float("nan"), driver=2, round=3).validate()


def test_a_full_disk_stops_collection_in_one_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Checked before each write: the episode's temporary file is removed and nothing half-written stays."""
    import shutil

    from yawil.data.writer import MIN_FREE_BYTES

    real = shutil.disk_usage
    free = {"bytes": 10 * MIN_FREE_BYTES}
    monkeypatch.setattr(shutil, "disk_usage",
                        lambda p: real(p)._replace(free=free["bytes"]))  # type: ignore[attr-defined]
    m = write_synthetic_dataset(tmp_path / "d", episodes=1, frames=5, k=3)
    free["bytes"] = MIN_FREE_BYTES - 1
    with pytest.raises(OSError, match="the disk is \\(nearly\\) full") as err:
        write_synthetic_dataset(tmp_path / "d", episodes=1, frames=5, k=3, first_episode=1)
    assert err.value.errno == errno.ENOSPC
    assert sorted(p.name for p in (tmp_path / "d" / "episodes").iterdir()) == [m.episodes[0].file.split("/")[-1]]


def test_a_failed_checkpoint_write_names_the_full_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    import yawil.policy.checkpoint as ck

    def fail(*a: object, **k: object) -> None:
        raise RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos 4416 vs 4310")

    monkeypatch.setattr(ck.torch, "save", fail)
    monkeypatch.setattr(ck.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(100, 100, 0))  # type: ignore[attr-defined]
    ckpt = {**{k: None for k in ck.REQUIRED_KEYS}, "state_dict": {}}
    with pytest.raises(OSError, match="the disk is full") as err:
        ck.save_checkpoint(ckpt, tmp_path / "last.pt")
    assert err.value.errno == errno.ENOSPC and list(tmp_path.iterdir()) == []
