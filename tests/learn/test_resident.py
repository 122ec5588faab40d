"""`--data-on-device` (yawil.learn.resident) on the CPU device: the batches are the DataLoader's, a run trains,
resumes to an uninterrupted run's weights and ends with the DataLoader run's weights; a split that does not
fit is refused in one line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from test_train import K, _parse, _weights, small, splits
from torch.utils.data import default_collate

from yawil.learn.cli import build_config
from yawil.learn.loop import train
from yawil.learn.resident import ResidentData, check_fits, kept_keys, load_splits, sample_bytes
from yawil.learn.sampling import epoch_batches, prepare_batch
from yawil.policy.checkpoint import Norm
from yawil.policy.runtime import resolve_runtime


def test_batches_equal_the_loaders_for_the_same_indices(tiny_dataset: Any) -> None:
    from yawil.data import DrivingDataset

    ds = DrivingDataset(tiny_dataset(episodes=3, frames=6, k=K))
    cfg = small(Path("unused"), "x", augment={"enabled": False})
    runtime = resolve_runtime("cpu", "fp32", "on")
    keys = kept_keys("yaw")
    data = ResidentData.load(ds, keys, cfg, runtime)
    assert len(data) == len(ds) == 18 and data.nbytes == 18 * sample_bytes(ds, keys)
    assert data.tensors["image"].dtype == torch.uint8 and data.tensors["image"].shape == (18, 3, 88, 200)
    assert set(data.tensors) == set(keys)  # nothing else is held (episode, frame, other guidance kinds)
    norm = Norm.from_arrays(ds.labels("speed"), ds.labels("guidance_yaw"))
    order = epoch_batches(len(ds), 5, seed=3, epoch=1)
    for index, got in zip(order, data.batches(order), strict=True):
        want = default_collate([ds[i] for i in index])
        for key in keys:
            assert got[key].dtype == want[key].dtype and got[key].shape == want[key].shape, key
            assert torch.equal(got[key], want[key]), key
        a, b = (prepare_batch(r, norm, "yaw", True, runtime) for r in (got, want))
        assert a.image.is_contiguous(memory_format=torch.channels_last)
        for name in ("image", "speed", "guidance", "command", "action", "speed_raw", "privileged"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_a_run_on_the_device_resumes_exactly_and_matches_the_loaders_run(tmp_path: Path) -> None:
    """Augmentation on (it draws on the device in both modes): the same steps give the same weights."""
    loader_run = train(small(tmp_path, "loader"), splits=splits())
    full = train(small(tmp_path, "full", data_on_device=True), splits=splits())
    assert full.steps == loader_run.steps == 4 and full.metrics[1]["train_loss"] < full.metrics[0]["train_loss"]
    part = train(small(tmp_path, "part", data_on_device=True, max_steps=3), splits=splits())
    assert part.stopped_by == "max_steps"
    resumed = train(small(tmp_path, "part", data_on_device=True), resume=True, splits=splits())
    assert resumed.steps == 4
    a, b, c = (_weights(Path(r.out) / "last.pt") for r in (full, resumed, loader_run))
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)
        torch.testing.assert_close(a[key], c[key], rtol=0, atol=0, msg=key)
    assert resumed.metrics[-1]["val_loss"] == pytest.approx(full.metrics[-1]["val_loss"], abs=1e-6)


def test_a_split_that_does_not_fit_is_refused_in_one_line(tmp_path: Path) -> None:
    check_fits(10**9, torch.device("cpu"))  # the CPU: host memory, no check
    check_fits(8 * 10**9, torch.device("cuda"), free=10 * 10**9)
    with pytest.raises(ValueError, match=r"^--data-on-device: .* need 9\.0 GB on cuda, but 10\.0 GB are free") as err:
        check_fits(9 * 10**9, torch.device("cuda"), free=10 * 10**9)
    assert "\n" not in str(err.value)
    tr, val, _ = splits()
    cfg = small(tmp_path, "x", data_on_device=True)
    train_data, val_data = load_splits(tr, val, None, cfg, resolve_runtime("cpu", "fp32", "off"), announce=False)
    assert (len(train_data), val_data is not None and len(val_data)) == (32, 8)


def test_the_flag_sets_the_field() -> None:
    assert build_config(_parse(["--data", "d", "--data-on-device"])).data_on_device is True
    assert build_config(_parse(["--data", "d"])).data_on_device is False
