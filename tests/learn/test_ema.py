"""The weight average (`--ema`): its update rule, what the checkpoints hold, exact resume, fine-tuning from it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_train import small, splits

from yawil.learn.ema import make_ema, warmup_decay
from yawil.learn.loop import train
from yawil.learn.validate import validate
from yawil.policy.checkpoint import load_checkpoint, model_from_checkpoint


def test_warmup_decay_ramps_up_to_the_decay() -> None:
    assert warmup_decay(0.995, 0) == pytest.approx(0.1)
    assert warmup_decay(0.995, 10) == pytest.approx(11 / 20)
    assert warmup_decay(0.995, 10_000) == 0.995
    assert all(warmup_decay(0.99, n) <= warmup_decay(0.99, n + 1) for n in range(500))


def test_the_average_follows_its_formula_for_parameters_and_buffers() -> None:
    net = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.BatchNorm1d(2))
    ema = make_ema(net, 0.9)
    expected = [p.detach().clone() for p in net.state_dict().values() if p.is_floating_point()]
    ema.update_parameters(net)  # the first update copies
    for n in range(1, 6):
        with torch.no_grad():
            for p in net.parameters():
                p.add_(torch.randn_like(p))
            net[1].running_mean.add_(1.0)
            net[1].num_batches_tracked.add_(1)
        ema.update_parameters(net)
        d = warmup_decay(0.9, n - 1)
        current = [p.detach() for p in net.state_dict().values() if p.is_floating_point()]
        expected = [d * e + (1 - d) * c for e, c in zip(expected, current, strict=True)]
    got = [p for p in ema.module.state_dict().values() if p.is_floating_point()]
    for e, g in zip(expected, got, strict=True):
        torch.testing.assert_close(g, e)
    assert int(ema.module[1].num_batches_tracked) == int(net[1].num_batches_tracked)  # integers follow


def test_checkpoints_drive_and_validate_the_average(tmp_path: Path) -> None:
    result = train(small(tmp_path, "ema", ema=0.9), splits=splits())
    ckpt = load_checkpoint(Path(result.out) / "last.pt")
    assert ckpt["ema"] == {"updates": result.steps}
    averaged, raw = ckpt["state_dict"], ckpt["raw_state_dict"]
    assert set(averaged) == set(raw)
    assert any(not torch.equal(averaged[k], raw[k]) for k in averaged if averaged[k].is_floating_point())
    # the validation columns are those of the weights the checkpoint drives with
    from yawil.learn.config import TrainConfig
    from yawil.learn.sampling import sequential_batches
    from yawil.learn.setup import make_loader
    from yawil.policy.checkpoint import Norm
    from yawil.policy.runtime import resolve_runtime

    cfg = TrainConfig.from_dict(ckpt["train_config"])
    _, val_ds, _ = splits()
    runtime = resolve_runtime("cpu", "fp32", "off")
    model = model_from_checkpoint(ckpt)
    loader = make_loader(val_ds, sequential_batches(len(val_ds), cfg.batch_size), cfg, runtime)
    val = validate(model, loader, Norm.from_dict(ckpt["norm"]), model.guidance, cfg, runtime)
    assert val["val_loss"] == pytest.approx(ckpt["metrics"][-1]["val_loss"], rel=1e-5)


def test_a_stopped_run_with_the_average_resumes_to_the_same_weights(tmp_path: Path) -> None:
    full = train(small(tmp_path, "full", ema=0.9), splits=splits())
    train(small(tmp_path, "part", ema=0.9, max_steps=3), splits=splits())
    resumed = train(small(tmp_path, "part", ema=0.9), resume=True, splits=splits())
    assert resumed.steps == full.steps
    a, b = load_checkpoint(Path(full.out) / "last.pt"), load_checkpoint(Path(resumed.out) / "last.pt")
    assert a["ema"] == b["ema"]
    for part in ("state_dict", "raw_state_dict"):
        for key in a[part]:
            torch.testing.assert_close(a[part][key], b[part][key], rtol=0, atol=1e-6, msg=f"{part} {key}")
    with pytest.raises(ValueError, match="'ema'"):
        train(small(tmp_path, "part", ema=0.5, epochs=3), resume=True, splits=splits())


def test_fine_tuning_starts_from_the_average(tmp_path: Path) -> None:
    first = train(small(tmp_path, "first", ema=0.9, epochs=1), splits=splits())
    source = Path(first.out) / "last.pt"
    second = train(small(tmp_path, "second", epochs=1, max_steps=1, lr=1e-12, init_from=str(source)), splits=splits())
    a, b = load_checkpoint(source)["state_dict"], load_checkpoint(Path(second.out) / "last.pt")["state_dict"]
    for key in a:  # one step at a negligible rate: the weights are the average it started from
        if a[key].is_floating_point() and "running" not in key:
            torch.testing.assert_close(b[key], a[key], rtol=0, atol=1e-6, msg=key)


def test_a_bad_decay_is_named() -> None:
    from yawil.learn.config import TrainConfig

    for bad in (1.0, -0.1, "0.9"):
        with pytest.raises(ValueError, match="ema="):
            TrainConfig(ema=bad)  # type: ignore[arg-type]
