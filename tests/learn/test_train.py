"""Training: paper defaults, config precedence, the loop end to end, resume equivalence, branched loss,
normalisation, checkpoints, augmentation."""

from __future__ import annotations

import argparse
import csv
import math
import os
import signal
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml

from yawil import models
from yawil.learn.augment import AugmentConfig, augment_batch, blur
from yawil.learn.cli import _OPTIONS, add_parser, build_config
from yawil.learn.config import TrainConfig
from yawil.learn.loop import train
from yawil.learn.loss import predicted_actions
from yawil.learn.sampling import brake_weights, epoch_batches, label_arrays, label_columns, reason_weights
from yawil.policy.checkpoint import REQUIRED_KEYS, Norm, load_checkpoint, save_checkpoint

torch.set_num_threads(2)
K = 4
SIZE = (80, 80)  # the smallest image the CIL convolutions accept: keeps these tests cheap


class MemoryDataset(torch.utils.data.Dataset):
    """Samples shaped as yawil.data.DrivingDataset gives them, learnable: steer follows the image."""

    def __init__(self, n: int, seed: int, episode0: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.steer = rng.uniform(-0.5, 0.5, n).astype(np.float32)
        self.speed = rng.uniform(0, 8, n).astype(np.float32)
        self.command = rng.integers(0, 4, n).astype(np.int64)
        self.guidance = {
            "yaw": rng.normal(0, 0.3, (n, K)).astype(np.float32),
            "xy": rng.uniform(-1, 1, (n, 2 * K)).astype(np.float32),
            "sim_yaw": rng.normal(0, 0.3, (n, K)).astype(np.float32),
        }
        self.guidance["yaw"][:, 0] = 0.0  # as route-referenced yaw guidance always is
        base = rng.integers(0, 60, (n, 3, *SIZE)).astype(np.int16)
        shade = ((self.steer + 0.5) * 190).astype(np.int16)[:, None, None, None]
        self.images = np.clip(base + shade, 0, 255).astype(np.uint8)
        self.brake = (rng.uniform(0, 1, n) < 0.2).astype(np.float32)  # drawn last: the draws above are unchanged
        self.episode0 = episode0
        self.guidance_config = {"spacing": 2.0, "count": K, "reference": "route"}

    def __len__(self) -> int:
        return len(self.steer)

    def __getitem__(self, i: int) -> dict[str, Any]:
        throttle = 0.5 + 0.1 * float(self.steer[i])
        return {
            "image": self.images[i],
            "speed": self.speed[i : i + 1],
            "action": np.array([self.steer[i], throttle, self.brake[i]], dtype=np.float32),
            "command": self.command[i],
            "guidance_yaw": self.guidance["yaw"][i],
            "guidance_xy": self.guidance["xy"][i],
            "guidance_sim_yaw": self.guidance["sim_yaw"][i],
            "episode": self.episode0 + i // 8,
            "frame": i % 8,
        }

    def labels(self, name: str) -> np.ndarray:
        if name == "speed":
            return self.speed
        if name == "brake":
            return self.brake
        return self.guidance[name.removeprefix("guidance_")]


def splits(n_train: int = 32, n_val: int = 8) -> tuple[Any, Any, dict[str, Any]]:
    tr = MemoryDataset(n_train, seed=1)
    return tr, MemoryDataset(n_val, seed=2, episode0=100), tr.guidance_config


def small(tmp_path: Path, name: str, **kw: Any) -> TrainConfig:
    base: dict[str, Any] = dict(
        model="cil", out=str(tmp_path / name), epochs=2, batch_size=16, lr=1e-3, progress=False,
        precision="fp32", model_args={"dropout": 0.0, "image_size": list(SIZE)},
    )  # fmt: skip
    base.update(kw)
    return TrainConfig(**base)


# ------------------------------------------------------------------------------------------------ config
def test_defaults_are_the_papers() -> None:
    cfg = TrainConfig()
    assert (cfg.batch_size, cfg.lr, cfg.lr_step_epochs, cfg.lr_gamma, cfg.epochs) == (512, 1e-3, 10, 0.5, 100)
    assert (cfg.alpha, cfg.beta, cfg.loss, cfg.model) == (1.0, 0.1, "l1", "yilratt")
    assert cfg.augment.enabled


def test_every_setting_has_a_command_line_option() -> None:
    covered = {dest for _, dest, _, _ in _OPTIONS} | {"model", "data", "out", "model_args", "augment", "progress",
                                                     "reason_fractions",  # --oversample REASON=SHARE
                                                     "data_on_device"}  # --data-on-device
    assert {f.name for f in fields(TrainConfig)} == covered
    cfg = build_config(_parse(["--data", "d", "--oversample", "vehicle=0.2", "--oversample", "red_light=0.1"]))
    assert cfg.reason_fractions == {"vehicle": 0.2, "red_light": 0.1}


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    add_parser(sub)
    return parser.parse_args(["train", *argv])


def test_yaml_then_command_line(tmp_path: Path) -> None:
    f = tmp_path / "c.yaml"
    f.write_text(yaml.safe_dump({"lr": 0.01, "epochs": 7, "augment": {"blur_p": 0.9}, "model": "cilrs"}))
    cfg = build_config(_parse(["--config", str(f), "--epochs", "3", "--augment", "noise_p=0.0", "--data", "d1"]))
    assert (cfg.lr, cfg.epochs, cfg.model, cfg.data) == (0.01, 3, "cilrs", ["d1"])
    assert (cfg.augment.blur_p, cfg.augment.noise_p, cfg.augment.contrast_p) == (0.9, 0.0, 0.5)
    cfg = build_config(_parse(["--no-augment", "--model-arg", "dropout=0.2"]))
    assert not cfg.augment.enabled and cfg.model_args == {"dropout": 0.2}


def test_unknown_and_bad_settings_are_named(tmp_path: Path) -> None:
    f = tmp_path / "c.yaml"
    f.write_text("lr: 0.01\nlearning_rate: 0.1\n")
    with pytest.raises(ValueError, match=r"c\.yaml.*learning_rate"):
        TrainConfig.from_yaml(f)
    f.write_text("augment: {blurr_p: 0.1}\n")
    with pytest.raises(ValueError, match="blurr_p"):
        TrainConfig.from_yaml(f)
    with pytest.raises(ValueError, match="batch_size=0"):
        TrainConfig(batch_size=0)
    with pytest.raises(ValueError, match="loss"):
        TrainConfig(loss="l3")
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        TrainConfig.from_yaml(tmp_path / "nope.yaml")


# --------------------------------------------------------------------------------------------- the loop
def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["state_dict"]


def test_train_end_to_end_and_resume_equivalence(tmp_path: Path) -> None:
    full = train(small(tmp_path, "full"), splits=splits())
    out = Path(full.out)
    for name in ("best.pt", "last.pt", "config.yaml", "metrics.csv", "loss.png"):
        assert (out / name).is_file(), name
    assert list((out / "tb").glob("events.out.tfevents.*"))
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [float(r["epoch"]) for r in rows] == [1.0, 2.0]
    assert float(rows[1]["train_loss"]) < float(rows[0]["train_loss"])
    assert {"val_l1_steer", "val_l1_throttle", "val_l1_brake", "val_l1_speed", "val_brake_recall", "lr", "time"} <= set(rows[0])
    assert yaml.safe_load((out / "config.yaml").read_text())["batch_size"] == 16
    ckpt = load_checkpoint(out / "last.pt")
    assert set(REQUIRED_KEYS) <= set(ckpt) and ckpt["epoch"] == 2 and ckpt["step"] == 4
    assert ckpt["guidance_config"] == {"spacing": 2.0, "count": K, "reference": "route"}

    part = train(small(tmp_path, "part", epochs=1), splits=splits())
    assert part.epochs_done == 1
    resumed = train(small(tmp_path, "part", epochs=2), resume=True, splits=splits())
    assert resumed.epochs_done == 2 and resumed.steps == full.steps
    a, b = _weights(out / "last.pt"), _weights(Path(resumed.out) / "last.pt")
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=1e-6, msg=key)
    assert load_checkpoint(Path(resumed.out) / "last.pt")["metrics"][1]["train_loss"] == pytest.approx(
        full.metrics[1]["train_loss"], abs=1e-6
    )


def test_budget_stop_mid_epoch_then_resume(tmp_path: Path) -> None:
    stopped = train(small(tmp_path, "b", epochs=1, max_steps=1), splits=splits())
    assert (stopped.stopped_by, stopped.steps, stopped.epochs_done) == ("max_steps", 1, 0)
    assert (Path(stopped.out) / "best.pt").is_file()  # a partial epoch still leaves a usable model
    resumed = train(small(tmp_path, "b", epochs=1), resume=True, splits=splits())
    assert (resumed.steps, resumed.epochs_done) == (2, 1)
    with pytest.raises(ValueError, match="'lr'"):
        train(small(tmp_path, "b", epochs=2, lr=0.5), resume=True, splits=splits())
    with pytest.raises(FileExistsError, match="--resume"):
        train(small(tmp_path, "b"), splits=splits())


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_stops_between_steps_and_resume_is_exact(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          sig: int) -> None:
    """Ctrl-C or SIGTERM during a step (here: while its batch is prepared) lets the step finish, saves, and
    the resumed run ends with the uninterrupted run's weights, BatchNorm statistics included."""
    import yawil.learn.loop as train_module

    full = train(small(tmp_path, "full", epochs=1), splits=splits(64))  # 4 batches of 16
    real_step = train_module.prepare_batch
    calls = {"n": 0}

    def signal_on_third_batch(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), sig)
        return real_step(*args, **kwargs)

    monkeypatch.setattr(train_module, "prepare_batch", signal_on_third_batch)
    before = signal.getsignal(signal.SIGINT)  # default_int_handler, or SIG_IGN in a job started in the background
    from yawil.signals import Terminated

    with pytest.raises(KeyboardInterrupt) as stop:
        train(small(tmp_path, "i", epochs=1), splits=splits(64))
    # SIGTERM and SIGHUP end as every command ends on them (exit 143 / 129), Ctrl-C as Ctrl-C (130)
    assert isinstance(stop.value, Terminated) == (sig != signal.SIGINT)
    assert sig == signal.SIGINT or stop.value.signum == sig  # type: ignore[attr-defined]
    assert load_checkpoint(tmp_path / "i" / "last.pt")["position"]["step"] == 3  # the step under way finished
    assert signal.getsignal(signal.SIGINT) is before  # handlers are given back
    monkeypatch.setattr(train_module, "prepare_batch", real_step)
    resumed = train(small(tmp_path, "i", epochs=1), resume=True, splits=splits(64))
    assert (resumed.epochs_done, resumed.steps) == (1, 4)
    a, b = _weights(Path(full.out) / "last.pt"), _weights(tmp_path / "i" / "last.pt")
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_an_interrupt_s_validation_does_not_choose_best(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The validation run at a Ctrl-C is recorded (`interrupted`) but never chooses best.pt: here it scores
    best of all, and the resumed run's best.pt is still the uninterrupted run's (step 4, not step 3)."""
    import yawil.learn.loop as train_module

    real_validate, real_step = train_module.validate, train_module.prepare_batch
    calls = {"validate": 0, "batch": 0}

    def validate(*args: Any, **kwargs: Any) -> dict[str, float]:
        calls["validate"] += 1  # in the interrupted run, the first call is the interrupt's
        return {**real_validate(*args, **kwargs), "val_loss": 0.1 if calls["validate"] == 1 else 0.5}

    monkeypatch.setattr(train_module, "validate", validate)
    full = train(small(tmp_path, "full", epochs=1), splits=splits(64))
    calls["validate"] = 0

    def signal_on_third_batch(*args: Any, **kwargs: Any) -> Any:
        calls["batch"] += 1
        if calls["batch"] == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return real_step(*args, **kwargs)

    monkeypatch.setattr(train_module, "prepare_batch", signal_on_third_batch)
    with pytest.raises(KeyboardInterrupt):
        train(small(tmp_path, "i", epochs=1), splits=splits(64))
    assert not (tmp_path / "i" / "best.pt").exists()  # no scheduled validation has run yet
    monkeypatch.setattr(train_module, "prepare_batch", real_step)
    train(small(tmp_path, "i", epochs=1), resume=True, splits=splits(64))
    best = load_checkpoint(tmp_path / "i" / "best.pt")
    assert best["step"] == 4 and [m.get("interrupted") for m in best["metrics"]] == [1.0, None]
    a, b = _weights(Path(full.out) / "best.pt"), _weights(tmp_path / "i" / "best.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_missing_or_damaged_episode_file_is_refused_before_training(tmp_path: Path) -> None:
    """The manifest lists an episode whose file is gone or damaged: train names it instead of training on
    the rest (an empty training split, or half the data with exit 0)."""
    from yawil.data.synthetic import write_synthetic_dataset
    from yawil.learn.config import TrainConfig
    from yawil.learn.setup import open_splits

    data = tmp_path / "data"
    write_synthetic_dataset(data, episodes=4, frames=4, seed=0)
    files = sorted((data / "episodes").glob("*.h5"))
    files[1].unlink()
    files[2].write_bytes(b"damaged")
    cfg = TrainConfig.from_dict({"model": "yaw-guided", "data": [str(data)], "out": str(tmp_path / "r")})
    import warnings

    with warnings.catch_warnings(), pytest.raises(
            ValueError, match=r"2 episode file\(s\) listed in the manifest cannot be read.*ep_0000"):
        warnings.simplefilter("error")  # the refusal is the one line: no warning before it
        open_splits(cfg)


def test_a_disk_without_room_for_the_checkpoints_is_refused_before_the_first_step(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno
    import shutil

    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=32 << 20))
    with pytest.raises(OSError, match="MiB needed for this run's checkpoints") as err:
        train(small(tmp_path, "full", epochs=1), splits=splits(64))
    assert err.value.errno == errno.ENOSPC and not (tmp_path / "full" / "last.pt").exists()


def test_an_unreadable_batch_saves_the_run_and_names_the_problem(tmp_path: Path) -> None:
    """A corrupt episode met mid-epoch: the finished steps are saved and the error is one ValueError."""
    _, va, gc = splits(64)

    class Corrupt(MemoryDataset):
        def __getitem__(self, i: int) -> Any:
            if i == self.bad_index:
                raise OSError("Can't synchronously read data (data error detected by fletcher32 checksum)")
            return super().__getitem__(i)

    bad = Corrupt(64, seed=1)
    bad.bad_index = -1
    order = epoch_batches(64, 16, 0, 0)  # seed 0, epoch 0: the run's order
    bad.bad_index = int(order[2][0])  # the first sample of the third batch
    with pytest.raises(ValueError, match="fletcher32 checksum.*saved at step 2.*--resume"):
        train(small(tmp_path, "c", epochs=1), splits=(bad, va, gc))
    assert load_checkpoint(tmp_path / "c" / "last.pt")["position"]["step"] == 2


def test_a_second_ctrl_c_stops_at_once_without_saving(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import yawil.learn.loop as train_module

    real_step = train_module.prepare_batch
    calls = {"n": 0}

    def two_signals(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
        return real_step(*args, **kwargs)

    monkeypatch.setattr(train_module, "prepare_batch", two_signals)
    with pytest.raises(KeyboardInterrupt):
        train(small(tmp_path, "j", epochs=1), splits=splits(64))
    assert not (tmp_path / "j" / "last.pt").exists()  # a half-done step is never saved


@pytest.fixture(scope="module")
def real_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small dataset written by yawil.data's writer (synthetic images, 5 episodes of 10 frames, K = 4)."""
    from yawil.data import write_synthetic_dataset

    root = tmp_path_factory.mktemp("data") / "synthetic"
    write_synthetic_dataset(root, episodes=5, frames=10, k=K, seed=0)
    return root


def test_guided_model_on_written_episodes_stores_norm_for_the_agent(tmp_path: Path, real_data: Path) -> None:
    from yawil.agent import Agent
    from yawil.data import DrivingDataset, split_episodes

    cfg = TrainConfig(
        model="yaw-guided", data=[str(real_data)], out=str(tmp_path / "g"), epochs=1, batch_size=16,
        val_fraction=0.2, progress=False,
    )  # fmt: skip
    res = train(cfg)
    assert res.metrics and math.isfinite(res.metrics[0]["val_loss"])
    ckpt = load_checkpoint(Path(res.out) / "best.pt")
    assert ckpt["guidance_kind"] == "yaw" and ckpt["model_config"]["guidance_dim"] == K
    assert ckpt["guidance_config"] == {"spacing": 2.0, "count": K, "reference": "route"}
    train_ids, _ = split_episodes([real_data], 0.2, 0)
    ds = DrivingDataset([real_data], episodes=train_ids)
    norm = Norm.from_dict(ckpt["norm"])
    assert norm.speed_mean == pytest.approx(float(ds.labels("speed").mean()), rel=1e-6)
    assert np.allclose(norm.guidance_mean, ds.labels("guidance_yaw").mean(0), atol=1e-6)
    assert np.allclose(norm.guidance_std, ds.labels("guidance_yaw").std(0), atol=1e-6)
    agent = Agent.from_checkpoint(Path(res.out) / "best.pt")
    assert agent.norm == norm and agent.guidance_config.count == K


def test_norm_keeps_constant_components_finite() -> None:
    g = np.zeros((5, 3))
    g[:, 1] = [1, 2, 3, 4, 5]
    norm = Norm.from_arrays(np.full(5, 2.0), g)
    assert norm.speed_std == 1.0 and norm.guidance_std[0] == 1.0 and norm.guidance_std[1] == pytest.approx(np.std([1, 2, 3, 4, 5]))
    out = norm.guidance(torch.tensor(g, dtype=torch.float32))
    assert torch.isfinite(out).all() and torch.all(out[:, 0] == 0)
    with pytest.raises(ValueError, match="empty"):
        Norm.from_arrays(np.zeros(0), None)


def test_branched_loss_uses_the_commands_branch() -> None:
    model = models.create("cil", seed=0, dropout=0.0)
    image, speed = torch.rand(4, 3, 88, 200), torch.zeros(4, 1)
    command = torch.tensor([2, 2, 1, 2])
    out = model(image, speed, command=command)
    pred = predicted_actions(model, out, command)
    assert torch.equal(pred, out.branches[torch.arange(4), command])
    pred.sum().backward()
    heads: Any = model.branches
    grads = [sum(float(p.grad.abs().sum()) for p in b.parameters() if p.grad is not None) for b in heads]
    assert grads[1] > 0 and grads[2] > 0 and grads[0] == 0 and grads[3] == 0


def test_label_arrays_with_and_without_a_labels_method() -> None:
    ds = MemoryDataset(10, seed=4)

    class Plain(torch.utils.data.Dataset):
        def __len__(self) -> int:
            return len(ds)

        def __getitem__(self, i: int) -> dict[str, Any]:
            return ds[i]

    fast, slow = label_arrays(ds, "xy"), label_arrays(Plain(), "xy")
    assert np.allclose(fast[0], slow[0]) and fast[1] is not None and slow[1] is not None
    assert np.allclose(fast[1], slow[1]) and slow[1].shape == (10, 2 * K)
    assert label_arrays(ds, None)[1] is None
    assert np.array_equal(label_columns(Plain(), ["brake"])[0], ds.labels("brake"))  # read from the action


def test_epoch_order_is_a_seeded_permutation() -> None:
    a = epoch_batches(50, 16, seed=3, epoch=1)
    assert a == epoch_batches(50, 16, seed=3, epoch=1) != epoch_batches(50, 16, seed=3, epoch=2)
    assert sorted(i for b in a for i in b) == list(range(50)) and [len(b) for b in a] == [16, 16, 16, 2]


def test_brake_fraction_draws_slowing_down_frames_at_the_asked_share() -> None:
    brake, speed = np.zeros(4000), np.full(4000, 5.0)
    brake[:300] = 1.0
    speed[200:300] = 0.0  # 200 frames slowing down (5 %), 100 standing on the brake: not oversampled
    p = brake_weights(brake, speed, 0.3)
    assert p.sum() == pytest.approx(1.0) and p[0] > p[250] == p[-1]
    a = epoch_batches(4000, 64, seed=3, epoch=0, p=p)
    assert a == epoch_batches(4000, 64, seed=3, epoch=0, p=p) != epoch_batches(4000, 64, seed=3, epoch=1, p=p)
    drawn = np.array([i for b in a for i in b])
    assert len(drawn) == 4000 and abs(float((drawn < 200).mean()) - 0.3) < 0.03
    with pytest.raises(ValueError, match="brake_fraction=0.3: the training split has 0 slowing-down frames"):
        brake_weights(np.ones(10), np.zeros(10), 0.3)
    with pytest.raises(ValueError, match="differ in length"):
        brake_weights(np.ones(10), np.zeros(9), 0.3)
    with pytest.raises(ValueError, match="brake_fraction"):
        TrainConfig(brake_fraction=1.0)


def test_reason_fractions_draw_each_reason_at_its_share() -> None:
    from yawil.data.schema import SPEED_REASONS

    reason = np.zeros(4000, dtype=np.int8)  # cruise
    reason[:100] = SPEED_REASONS.index("vehicle")
    reason[100:600] = SPEED_REASONS.index("red_light")
    p = reason_weights(reason, {"vehicle": 0.2})
    assert p.sum() == pytest.approx(1.0) and p[0] > p[100] == p[-1]
    drawn = np.array([i for b in epoch_batches(4000, 64, seed=1, epoch=0, p=p) for i in b])
    assert abs(float((drawn < 100).mean()) - 0.2) < 0.03
    with pytest.raises(ValueError, match="no frame whose expert reason is 'pedestrian'"):
        reason_weights(reason, {"pedestrian": 0.1})
    with pytest.raises(ValueError, match="nothing is left"):
        reason_weights(np.zeros(10), {"cruise": 0.5})
    with pytest.raises(ValueError, match="reason_fractions"):
        TrainConfig(reason_fractions={"lorry": 0.1})
    with pytest.raises(ValueError, match="reason_fractions"):
        TrainConfig(reason_fractions={"vehicle": 0.6, "red_light": 0.5})
    with pytest.raises(ValueError, match="not together with brake_fraction"):
        TrainConfig(reason_fractions={"vehicle": 0.2}, brake_fraction=0.2)


def test_brake_fraction_run_resumes_to_the_same_weights(tmp_path: Path) -> None:
    full = train(small(tmp_path, "full", brake_fraction=0.5), splits=splits())
    plain = train(small(tmp_path, "plain"), splits=splits())
    assert full.metrics[0]["train_loss"] != plain.metrics[0]["train_loss"]  # other frames were drawn
    train(small(tmp_path, "part", brake_fraction=0.5, epochs=1), splits=splits())
    resumed = train(small(tmp_path, "part", brake_fraction=0.5, epochs=2), resume=True, splits=splits())
    a, b = _weights(Path(full.out) / "last.pt"), _weights(Path(resumed.out) / "last.pt")
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=1e-6, msg=key)


# -------------------------------------------------------------------------------------------- checkpoint
def test_load_checkpoint_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")
    torch.save({"state_dict": {}}, tmp_path / "plain.pt")
    with pytest.raises(ValueError, match="not a yawil checkpoint"):
        load_checkpoint(tmp_path / "plain.pt")
    torch.save({"format": "yawil-checkpoint", "format_version": 1}, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match="model_name"):
        load_checkpoint(tmp_path / "partial.pt")
    with pytest.raises(ValueError, match="without"):
        save_checkpoint({"format": "yawil-checkpoint"}, tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()


# ------------------------------------------------------------------------------------------ augmentation
def test_augmentation_per_sample_and_seeded() -> None:
    images = torch.rand(64, 3, 88, 200, generator=torch.Generator().manual_seed(0))
    cfg = AugmentConfig()
    a = augment_batch(images, cfg, torch.Generator().manual_seed(5))
    b = augment_batch(images, cfg, torch.Generator().manual_seed(5))
    c = augment_batch(images, cfg, torch.Generator().manual_seed(6))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.min() >= 0 and a.max() <= 1 and a.shape == images.shape
    changed = (a - images).abs().flatten(1).mean(1)
    assert (changed > 0).sum() > 32  # most samples touched...
    assert changed.std() > 0.005  # ...by different amounts
    assert torch.equal(augment_batch(images, AugmentConfig(enabled=False), torch.Generator()), images)
    with pytest.raises(ValueError, match="blur_p"):
        AugmentConfig(blur_p=1.5)


def test_augmentation_matches_torchvision_v2() -> None:
    from torchvision.transforms.v2 import functional as TF

    img = torch.rand(1, 3, 40, 60)
    only: dict[str, Any] = dict(brightness_p=0.0, contrast_p=0.0, blur_p=0.0, noise_p=0.0, dropout_p=0.0)
    for op, fn in (
        ("brightness", lambda x, f: TF.adjust_brightness(x, f)),
        ("contrast", lambda x, f: TF.adjust_contrast(x, f)),
    ):
        cfg = AugmentConfig(**{**only, f"{op}_p": 1.0})
        gen = torch.Generator().manual_seed(0)
        out = augment_batch(img, cfg, gen)
        # replay the draws: the per-sample parameters are the first [10, B] uniforms
        u = torch.rand((10, 1), generator=torch.Generator().manual_seed(0))
        factor = 1 - 0.4 + 0.8 * float(u[1 if op == "brightness" else 3, 0])
        torch.testing.assert_close(out, fn(img, factor), atol=1e-6, rtol=0)
    sigmas = torch.tensor([0.7, 1.3])
    two = torch.rand(2, 3, 40, 60)
    got = blur(two, sigmas, 5)
    for i in range(2):
        ref = TF.gaussian_blur(two[i : i + 1], [5, 5], [float(sigmas[i])] * 2)
        torch.testing.assert_close(got[i : i + 1], ref, atol=1e-5, rtol=0)


def test_colour_augmentation_matches_torchvision_and_leaves_the_old_draws_alone() -> None:
    from torchvision.transforms.v2 import functional as TF

    img = torch.rand(1, 3, 40, 60)
    only: dict[str, Any] = dict(brightness_p=0.0, contrast_p=0.0, blur_p=0.0, noise_p=0.0, dropout_p=0.0)
    for op, fn in (
        ("saturation", lambda x, f: TF.adjust_saturation(x, f)),
        ("gamma", lambda x, f: TF.adjust_gamma(x, f)),
    ):
        out = augment_batch(img, AugmentConfig(**{**only, f"{op}_p": 1.0}), torch.Generator().manual_seed(0))
        gen = torch.Generator().manual_seed(0)
        torch.rand((10, 1), generator=gen)  # the standard operations' draws come first
        v = torch.rand((8, 1), generator=gen)
        strength = 0.5 if op == "saturation" else 0.4
        factor = 1 - strength + 2 * strength * float(v[1 if op == "saturation" else 7, 0])
        torch.testing.assert_close(out, fn(img, factor), atol=1e-6, rtol=0)
    out = augment_batch(img, AugmentConfig(**{**only, "gain_p": 1.0}), torch.Generator().manual_seed(0))
    ratio = (out / img)[0].flatten(1)
    assert torch.all(ratio.std(dim=1)[out[0].flatten(1).max(dim=1).values < 1] < 1e-5)  # one gain per channel
    assert ratio.mean(dim=1).unique().numel() == 3 and torch.all((ratio > 0.8 - 1e-6) & (ratio < 1.2 + 1e-6))
    # with the colour operations on, the standard operations draw and act exactly as before
    images = torch.rand(80, 3, 20, 30, generator=torch.Generator().manual_seed(1))
    gen_a, gen_b = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    base = augment_batch(images, AugmentConfig(), gen_a)
    colour = AugmentConfig(saturation_p=1.0, gain_p=1.0, gamma_p=1.0, saturation=0.0, gain=0.0, gamma=0.0)
    torch.testing.assert_close(augment_batch(images, colour, gen_b), base, atol=1e-6, rtol=0)  # identity strengths
    torch.rand((8, 80), generator=gen_a)
    assert torch.equal(torch.rand(4, generator=gen_a), torch.rand(4, generator=gen_b))  # and draw once more
    with pytest.raises(ValueError, match="gamma"):
        AugmentConfig(gamma=1.0)


def test_yawil_train_command_and_resume(tmp_path: Path, real_data: Path) -> None:
    from yawil.cli import main

    out = tmp_path / "run"
    common = ["--out", str(out), "--no-progress", "--max-steps", "2"]
    first = ["--model", "cil", "--data", str(real_data), "--epochs", "1", "--batch-size", "16", "--val-fraction", "0.2"]
    assert main(["train", *first, *common]) == 0  # 40 training frames: 3 steps an epoch, stopped after 2
    # max_steps counts across resumes: the saved limit (2) must be raised to go on
    assert main(["train", "--resume", "--max-steps", "100", "--out", str(out), "--no-progress"]) == 0
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [round(float(r["epoch"]), 2) for r in rows] == [0.67, 1.0]  # the partial epoch, then the whole one
    assert load_checkpoint(out / "last.pt")["step"] == 3
    assert yaml.safe_load((out / "config.yaml").read_text())["data"] == [str(real_data)]
    assert main(["train", "--resume", "--out", str(tmp_path / "nothing")]) == 2
    assert main(["train", "--data", str(tmp_path / "no-data"), "--out", str(tmp_path / "x")]) == 2


def test_a_one_episode_dataset_trains_without_validation(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`collect --frames 400` gives one episode: the smallest natural first run trains, with a warning."""
    from yawil.cli import main
    from yawil.data import write_synthetic_dataset

    write_synthetic_dataset(tmp_path / "one", episodes=1, frames=12, k=K, seed=0)
    out = tmp_path / "run"
    argv = ["train", "--model", "cil", "--data", str(tmp_path / "one"), "--out", str(out), "--epochs", "2",
            "--batch-size", "8", "--no-progress", "--precision", "fp32"]
    assert main(argv) == 0
    assert "training without validation" in capsys.readouterr().err
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert len(rows) == 2 and all(math.isnan(float(r["val_loss"])) for r in rows)
    best, last = _weights(out / "best.pt"), _weights(out / "last.pt")
    assert all(torch.equal(best[k], last[k]) for k in last)  # best follows last when nothing is validated
    with pytest.raises(ValueError, match="val_fraction"):
        TrainConfig(val_fraction=1.0)


def test_pretrained_backbone_is_loaded(tmp_path: Path) -> None:
    import torchvision

    from yawil.learn.setup import build_model

    net = torchvision.models.resnet34()
    torch.nn.init.constant_(net.conv1.weight, 0.125)
    torch.save(net.state_dict(), tmp_path / "r34.pth")
    cfg = TrainConfig(model="yilratt", pretrained=str(tmp_path / "r34.pth"))
    model = build_model(cfg, {"yaw": K, "xy": 2 * K, "sim_yaw": K})
    assert model.guidance_dim == K
    first = next(p for name, p in model.named_parameters() if name.endswith("conv1.weight"))
    assert torch.all(first == 0.125)
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        build_model(TrainConfig(model="cil", pretrained=str(tmp_path / "nope.pth")), {"yaw": K, "xy": 8, "sim_yaw": K})


def test_a_run_older_than_a_setting_resumes_with_that_settings_default() -> None:
    """A checkpoint written before a setting existed (reason_fractions, aux_loss) trained with its default:
    resuming it with the default is allowed, with anything else refused in one line."""
    from yawil.learn.setup import check_resumable

    cfg = TrainConfig(model="yaw-guided", data=["d"])
    saved = {k: v for k, v in cfg.to_dict().items() if k not in ("reason_fractions", "aux_loss")}
    check_resumable(saved, cfg, Path("run/last.pt"))
    with pytest.raises(ValueError, match="'aux_loss' was 'same', now 'mse'"):
        check_resumable(saved, TrainConfig(model="yaw-guided", data=["d"], aux_loss="mse"), Path("run/last.pt"))
