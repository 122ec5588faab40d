"""DrivingDataset: samples, labels(), DataLoader workers, split by episode, corrupt files skipped."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

import yawil.data
from yawil.data.dataset import DrivingDataset, split_episodes
from yawil.data.reader import open_episode
from yawil.data.synthetic import write_synthetic_dataset
from yawil.sim.types import command_index

K = 3


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    r = tmp_path_factory.mktemp("ds")
    write_synthetic_dataset(r, episodes=5, frames=8, k=K, seed=1)
    return r


def test_sample_matches_the_file(root: Path) -> None:
    ds = DrivingDataset(root)
    assert len(ds) == 40 and ds.episode_ids == [0, 1, 2, 3, 4]
    assert ds.guidance_config == {"spacing": 2.0, "count": K, "reference": "route"}
    s = ds[11]  # episode 1, row 3
    shapes = {k: (tuple(v.shape), v.dtype) for k, v in s.items()}
    assert shapes == {
        "image": ((3, 88, 200), torch.uint8), "speed": ((1,), torch.float32), "action": ((3,), torch.float32),
        "command": ((), torch.int64), "guidance_yaw": ((K,), torch.float32), "guidance_xy": ((2 * K,), torch.float32),
        "guidance_sim_yaw": ((K,), torch.float32), "episode": ((), torch.int64), "frame": ((), torch.int64),
        "privileged": ((5,), torch.float32),
    }  # fmt: skip
    with open_episode(root / "episodes" / "ep_000001.h5") as ep:
        rec = ep[3]
    np.testing.assert_array_equal(s["image"].numpy().transpose(1, 2, 0), rec.image)
    assert s["action"].tolist() == pytest.approx([rec.steer, rec.throttle, rec.brake])
    assert int(s["command"]) == command_index(rec.command) and int(s["frame"]) == rec.frame and int(s["episode"]) == 1
    np.testing.assert_array_equal(s["guidance_xy"].numpy(), rec.guidance_xy)
    assert ds[-1]["frame"] == ds[39]["frame"]
    with pytest.raises(IndexError):
        ds[40]


def test_labels_agree_with_samples(root: Path) -> None:
    ds = DrivingDataset(root, episodes=[4, 2])
    assert ds.episode_ids == [2, 4] and len(ds) == 16
    samples = [ds[i] for i in range(len(ds))]
    for name in ("speed", "action", "command", "guidance_yaw", "guidance_xy", "guidance_sim_yaw", "episode", "frame"):
        want = np.stack([s[name].numpy() for s in samples]).reshape(ds.labels(name).shape)
        np.testing.assert_array_equal(ds.labels(name), want)
    assert set(np.unique(ds.labels("road_option"))) <= {1, 2, 3, 4}
    with pytest.raises(KeyError, match="no label 'image'"):
        ds.labels("image")
    with pytest.raises(ValueError, match=r"episode\(s\) \[9\]"):
        DrivingDataset(root, episodes=[9])


def test_dataloader_with_two_workers(root: Path) -> None:
    ds = DrivingDataset(root)
    ds[0]  # the parent opens a handle before forking: workers must open their own
    loader = torch.utils.data.DataLoader(
        ds, batch_size=7, shuffle=True, num_workers=2, generator=torch.Generator().manual_seed(0)
    )
    seen = []
    for batch in loader:
        assert batch["image"].dtype == torch.uint8 and batch["image"].shape[1:] == (3, 88, 200)
        seen += list(zip(batch["episode"].tolist(), batch["frame"].tolist(), strict=True))
    assert sorted(seen) == sorted(zip(ds.labels("episode").tolist(), ds.labels("frame").tolist(), strict=True))
    ds.close()


def test_split_by_episode_is_deterministic(root: Path) -> None:
    train, val = split_episodes(root, val_fraction=0.2, seed=0)
    assert len(val) == 1 and sorted(train + val) == [0, 1, 2, 3, 4] and not set(train) & set(val)
    assert split_episodes([root], 0.2, 0) == (train, val)
    splits = {tuple(split_episodes(root, 0.4, s)[1]) for s in range(10)}
    assert len(splits) > 1 and all(len(v) == 2 for v in splits)
    assert split_episodes(root, 0.0, 0) == ([0, 1, 2, 3, 4], [])
    with pytest.raises(ValueError, match="val_fraction"):
        split_episodes(root, 1.0)
    # The module contract yawil.learn.setup.open_splits relies on.
    assert yawil.data.split_episodes is split_episodes and yawil.data.DrivingDataset is DrivingDataset


def test_two_roots_and_duplicate_ids(tmp_path: Path, root: Path) -> None:
    write_synthetic_dataset(tmp_path / "b", episodes=2, frames=4, k=K, first_episode=10)
    ds = DrivingDataset([root, tmp_path / "b"])
    assert len(ds) == 48 and ds.episode_ids[-2:] == [10, 11]
    write_synthetic_dataset(tmp_path / "c", episodes=1, frames=4, k=K)
    with pytest.raises(ValueError, match="episode id 0 is in both"):
        DrivingDataset([root, tmp_path / "c"])
    write_synthetic_dataset(tmp_path / "d", episodes=1, frames=4, k=K + 1, first_episode=20)
    with pytest.raises(ValueError, match="guidance config"):
        DrivingDataset([root, tmp_path / "d"])


def test_corrupt_files_are_skipped_with_a_warning(tmp_path: Path) -> None:
    m = write_synthetic_dataset(tmp_path, episodes=3, frames=5, k=K)
    truncated, with_nan = m.path_of(m.episodes[0]), m.path_of(m.episodes[1])
    with open(truncated, "r+b") as f:
        f.truncate(os.path.getsize(truncated) // 2)
    with h5py.File(with_nan, "r+") as f:
        f["guidance_yaw"][2, 1] = np.nan
    with pytest.warns(RuntimeWarning) as caught:
        ds = DrivingDataset(tmp_path)
    msgs = " | ".join(str(w.message) for w in caught)
    assert "ep_000000.h5" in msgs and "truncated" in msgs
    assert "ep_000001.h5" in msgs and "guidance_yaw: NaN" in msgs
    assert ds.episode_ids == [2] and len(ds) == 5 and len(ds.skipped) == 2
