"""Inertia countermeasures: speed-input dropout, the speed-blind variant, aux heads on the expert's privileged
labels, driving through a target-speed controller; and the training options they need (init_from, keep_steps)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from yawil import models
from yawil.agent import Agent, SpeedControl
from yawil.data.synthetic import write_synthetic_dataset
from yawil.learn.config import TrainConfig
from yawil.learn.loop import train
from yawil.learn.loss import aux_loss
from yawil.learn.sampling import drop_speed
from yawil.policy.checkpoint import Norm, load_checkpoint

torch.set_num_threads(1)
K = 4


def _yilratt(name: str = "yilratt", **kw: object) -> models.DrivingModel:
    if name in ("cil", "cilrs"):  # command nets: no guidance
        return models.create(name, seed=0, dropout=0.0, **kw)
    return models.create(name, seed=0, guidance_dim=K, dropout=0.0, **kw)


def _run(model: models.DrivingModel, image: torch.Tensor, speed: torch.Tensor, guide: torch.Tensor) -> models.ModelOutput:
    """Forward with guidance, or with a command for the command nets."""
    if model.uses_command:
        return model(image, speed, command=torch.arange(len(image)) % 4)
    return model(image, speed, guidance=guide)


def _inputs(b: int = 2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return torch.rand(b, 3, 88, 200, generator=g), torch.rand(b, 1, generator=g), torch.rand(b, K, generator=g)


@pytest.mark.parametrize("name", ["yilratt", "yaw-guided", "cil", "cilrs"])
def test_aux_head_and_speed_blind_variant(name: str) -> None:
    """YILRatt and the baselines offer the same variants, so a recipe compares on all of them."""
    image, speed, guide = _inputs()
    plain = _yilratt(name).eval()
    assert _run(plain, image, speed, guide).aux is None
    aux = _yilratt(name, aux=True).eval()
    out = _run(aux, image, speed, guide)
    assert out.aux is not None and tuple(out.aux.shape) == (2, len(models.base.AUX_NAMES))
    # the aux head is added last: every other weight is initialised as in the plain model
    for key, value in plain.state_dict().items():
        assert torch.equal(value, aux.state_dict()[key]), key
    blind = _yilratt(name, speed_input=False).eval()
    with torch.inference_mode():
        a = _run(blind, image, speed, guide).actions
        b = _run(blind, image, speed * 0 + 5.0, guide).actions
        c = _run(plain, image, speed * 0 + 5.0, guide).actions
    assert torch.equal(a, b) and not torch.allclose(a, c)
    with pytest.raises(ValueError, match="speed_input"):
        _yilratt(name, speed_input="no")


def test_speed_dropout_is_seeded_and_has_its_rate() -> None:
    speed = torch.ones(20_000, 1)
    g = lambda: torch.Generator().manual_seed(7)  # noqa: E731
    assert torch.equal(drop_speed(speed, 0.0, g()), speed)
    assert torch.equal(drop_speed(speed, 1.0, g()), torch.zeros_like(speed))
    a, b = drop_speed(speed, 0.3, g()), drop_speed(speed, 0.3, g())
    assert torch.equal(a, b) and abs(float((a == 0).float().mean()) - 0.3) < 0.02
    with pytest.raises(ValueError, match="speed_dropout"):
        TrainConfig(speed_dropout=1.5)


def test_aux_loss_counts_known_labels_only() -> None:
    norm = Norm(speed_mean=2.0, speed_std=2.0, guidance_mean=[0.0] * K, guidance_std=[1.0] * K)
    known = torch.tensor([[4.0, 25.0, 2.0, 1.0]])
    target_scaled = torch.tensor([[1.0, 0.5, 0.0, 20.0]])  # target speed, distance/50, lead speed, a confident logit
    assert float(aux_loss(target_scaled, known, norm)) < 1e-6
    unknown = torch.tensor([[math.nan, math.nan, math.nan, -1.0]])
    both = torch.cat([known, unknown])
    pred = torch.cat([target_scaled, torch.full((1, 4), 9.0)])
    assert float(aux_loss(pred, both, norm)) < 1e-6  # the unknown row's wild predictions cost nothing
    assert float(aux_loss(torch.zeros(1, 4), unknown, norm)) == 0.0
    assert float(aux_loss(torch.zeros(1, 4), known, norm)) > 0.1


def _data(tmp_path: Path) -> Path:
    write_synthetic_dataset(tmp_path / "d", episodes=4, frames=12, k=K)
    return tmp_path / "d"


def _cfg(tmp_path: Path, name: str, data: Path, **kw: object) -> TrainConfig:
    base: dict[str, object] = dict(model="yilratt", data=[str(data)], out=str(tmp_path / name), batch_size=4,
                                   max_steps=2, progress=False, precision="fp32", val_fraction=0.25,
                                   model_args={"dropout": 0.0}, augment={"enabled": False})
    base.update(kw)
    return TrainConfig(**base)  # type: ignore[arg-type]


def test_aux_training_keep_steps_and_init_from(tmp_path: Path) -> None:
    data = _data(tmp_path)
    with pytest.raises(ValueError, match="no aux head"):
        train(_cfg(tmp_path, "noaux", data, aux_weight=1.0))
    cfg = _cfg(tmp_path, "aux", data, aux_weight=1.0, model_args={"dropout": 0.0, "aux": True}, keep_steps=[1, 2],
               speed_dropout=0.5, max_steps=3)
    result = train(cfg)
    assert result.steps == 3 and math.isfinite(result.best_val)
    # validation reports what --speed-control would drive by: the target-speed error in m/s
    assert math.isfinite(result.metrics[-1]["val_l1_target_speed"]) and result.metrics[-1]["val_l1_target_speed"] >= 0
    assert math.isnan(train(_cfg(tmp_path, "plain", data, max_steps=1)).metrics[-1]["val_l1_target_speed"])
    kept = load_checkpoint(tmp_path / "aux" / "step_000001.pt")
    assert kept["step"] == 1 and (tmp_path / "aux" / "step_000002.pt").is_file()
    assert not (tmp_path / "aux" / "step_000003.pt").exists()
    # fine-tuning starts from the weights and the normalisation of the given checkpoint
    parent = load_checkpoint(tmp_path / "aux" / "last.pt")
    tuned = _cfg(tmp_path, "tuned", data, aux_weight=1.0, model_args={"dropout": 0.0, "aux": True}, max_steps=1,
                 lr=1e-12, init_from=str(tmp_path / "aux" / "last.pt"))
    train(tuned)
    child = load_checkpoint(tmp_path / "tuned" / "last.pt")
    assert child["norm"] == parent["norm"]
    for name, value in parent["state_dict"].items():
        if "running_" in name or "num_batches" in name:
            continue  # BatchNorm statistics move with any training step, whatever the learning rate
        assert torch.allclose(value.float(), child["state_dict"][name].float(), atol=1e-6), name
    with pytest.raises(ValueError, match="do not fit"):
        train(_cfg(tmp_path, "misfit", data, init_from=str(tmp_path / "aux" / "last.pt")))  # no aux head here
    # an agent drives through the target-speed controller only with an aux head
    agent = Agent.from_checkpoint(tmp_path / "aux" / "last.pt", speed_control=True)
    assert agent.drive.speed_control == "target" and agent.states[0].speed_control is not None
    with pytest.raises(ValueError, match="aux head"):
        Agent.from_checkpoint(tmp_path / "misfit" / "last.pt", speed_control=True) if (tmp_path / "misfit" / "last.pt").exists() \
            else Agent(_yilratt(), Norm(0.0, 1.0, [0.0] * K, [1.0] * K), agent.guidance_config, speed_control=True)


def test_speed_control_brakes_for_a_stop_and_starts_for_a_go() -> None:
    c = SpeedControl()
    throttle, brake = c(0.0, 5.0)
    assert throttle == 0.0 and brake > 0.5
    c.reset()
    throttle, brake = c(5.0, 0.0)
    assert throttle > 0.5 and brake == 0.0
    c.reset()
    assert c(0.0, 0.1) == (0.0, 1.0)  # standing before a stop: hold
    c.reset()
    t1, _ = c(3.0, 2.9)
    for _ in range(20):
        t2, _ = c(3.0, 2.9)
    assert t2 > t1  # the integral closes a steady error


def test_bce_brake_loss_learns_the_mean_where_l1_learns_the_median() -> None:
    from yawil.learn.loss import bce_of_probabilities

    target = torch.tensor([0.0] * 9 + [1.0])  # braking on one frame in ten, the image the same
    grid = torch.linspace(0.01, 0.99, 99)
    bce = torch.stack([bce_of_probabilities(torch.full((10,), float(p)), target) for p in grid])
    l1 = torch.stack([(torch.full((10,), float(p)) - target).abs().mean() for p in grid])
    assert float(grid[int(bce.argmin())]) == pytest.approx(0.1, abs=0.011)  # the mean: brakes above 0.1
    assert float(grid[int(l1.argmin())]) == pytest.approx(0.01)  # the median: never brakes
    with pytest.raises(ValueError, match="brake_loss"):
        TrainConfig(brake_loss="hinge")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.isfinite(bce_of_probabilities(torch.tensor([0.0, 1.0]), torch.tensor([0.0, 1.0])))


def test_aux_loss_option_sets_the_criterion_of_the_aux_regressions() -> None:
    """`aux_loss="mse"`: a lead seen on 1 frame in 10 moves the head's optimum (the mean), under L1 it does not."""
    from yawil.learn.loss import compute_loss
    from yawil.learn.sampling import Batch

    norm = Norm(speed_mean=2.0, speed_std=2.0, guidance_mean=[0.0] * K, guidance_std=[1.0] * K)
    lead = torch.tensor([[4.0, 5.0, 0.0, 0.0]] + [[4.0, 50.0, 0.0, 0.0]] * 9)  # lead distance 5 m once, none 9 times

    def best(criterion: str) -> float:
        grid = torch.linspace(0.0, 1.0, 101)
        costs = []
        for d in grid:
            pred = torch.tensor([[1.0, float(d), -1.0, -20.0]]).repeat(10, 1)
            costs.append(float(aux_loss(pred, lead, norm, criterion)))
        return float(grid[int(torch.tensor(costs).argmin())]) * 50.0

    assert best("l1") == pytest.approx(50.0)  # the median: no lead, ever
    assert best("mse") == pytest.approx(45.5, abs=0.6)  # the mean: the close lead pulls it
    with pytest.raises(ValueError, match="aux_loss"):
        TrainConfig(aux_loss="hinge")

    class Head(torch.nn.Module):  # a model whose aux output is a fixed guess, to see which criterion the loss uses
        def forward(self, image: torch.Tensor, speed: torch.Tensor, **_: object) -> object:
            from yawil.models.base import ModelOutput

            n = image.shape[0]
            return ModelOutput(torch.zeros(n, 3), torch.zeros(n, 1), [], None, torch.full((n, 4), 0.5))

    batch = Batch(image=torch.zeros(10, 3, 8, 8), speed=torch.zeros(10, 1), guidance=None, command=None,
                  action=torch.zeros(10, 3), speed_raw=torch.zeros(10, 1), privileged=lead)
    base = {"model": "yilratt", "aux_weight": 1.0}
    l1 = float(compute_loss(Head(), batch, TrainConfig(**base), norm)[0])  # type: ignore[arg-type]
    mse = float(compute_loss(Head(), batch, TrainConfig(**base, aux_loss="mse"), norm)[0])  # type: ignore[arg-type]
    same_mse = float(compute_loss(Head(), batch, TrainConfig(**base, loss="mse"), norm)[0])  # type: ignore[arg-type]
    assert mse != pytest.approx(l1) and mse == pytest.approx(same_mse)  # actions and speed are 0 = their targets


@pytest.mark.parametrize("name", ["yilratt", "yaw-guided", "cil", "cilrs"])
def test_lead_stop_output_widens_the_aux_head(name: str) -> None:
    image, speed, guide = _inputs()
    out = _run(_yilratt(name, aux=True, lead_stop=True).eval(), image, speed, guide)
    assert out.aux is not None and tuple(out.aux.shape) == (2, len(models.base.AUX_NAMES) + 1)
    with pytest.raises(ValueError, match="aux=true"):
        _yilratt(name, lead_stop=True)


def test_lead_stop_labels_and_their_weighted_cross_entropy() -> None:
    from yawil.learn.loss import LEAD_STOP_POS_WEIGHT, aux_targets, lead_stop_targets

    nan = math.nan
    # target speed, lead distance, lead speed, light: a standing car 5 m ahead; a moving one; one far; unknown
    privileged = torch.tensor([[0.0, 5.0, 0.0, 0.0], [4.0, 5.0, 5.0, 0.0], [4.0, 30.0, 0.0, 0.0], [4.0, nan, nan, -1.0]])
    close, seen = lead_stop_targets(privileged)
    assert close.tolist() == [1.0, 0.0, 0.0, 0.0] and seen.tolist() == [True, True, True, False]
    norm = Norm(speed_mean=2.0, speed_std=2.0, guidance_mean=[0.0] * K, guidance_std=[1.0] * K)
    aux = torch.randn(4, 5, generator=torch.Generator().manual_seed(3))
    four, five = float(aux_loss(aux[:, :4], privileged, norm)), float(aux_loss(aux, privileged, norm))
    count = float(aux_targets(privileged, norm)[1].sum())
    p = torch.sigmoid(aux[:3, 4])
    y = close[:3]
    bce = -(LEAD_STOP_POS_WEIGHT * y * p.log() + (1 - y) * (1 - p).log())
    assert five * (count + 3) == pytest.approx(four * count + float(bce.sum()), rel=1e-5)


def test_pedestrian_stops_join_the_lead_stop_class_when_asked() -> None:
    """`stop_pedestrians`: a frame where the expert stops for a pedestrian (reason, target under 1 m/s) is a
    positive of the lead-stop output, even with no vehicle known; without the flag the labels are as before."""
    from yawil.data.schema import SPEED_REASONS
    from yawil.learn.loss import lead_stop_targets

    nan, ped, cruise = math.nan, float(SPEED_REASONS.index("pedestrian")), float(SPEED_REASONS.index("cruise"))
    # a pedestrian stop; a pedestrian slow-down (target 3 m/s); a cruise frame; a pedestrian stop, lead unknown
    privileged = torch.tensor([[0.0, 50.0, 0.0, 0.0, ped], [3.0, 50.0, 0.0, 0.0, ped],
                               [5.0, 50.0, 0.0, 0.0, cruise], [0.5, nan, nan, -1.0, ped]])
    assert lead_stop_targets(privileged)[0].tolist() == [0.0, 0.0, 0.0, 0.0]
    close, seen = lead_stop_targets(privileged, ("pedestrian",))
    assert close.tolist() == [1.0, 0.0, 0.0, 1.0] and seen.tolist() == [True, True, True, True]
    with pytest.raises(ValueError, match="fifth column"):
        lead_stop_targets(privileged[:, :4], ("pedestrian",))


def test_stop_reasons_label_the_expert_stops_of_each_reason_named() -> None:
    """`stop_reasons`: the expert's stops for crossing traffic ("vehicle" with no standing car ahead) and at
    junctions join the class; a reason not named, or a slow-down above 1 m/s, does not; stop_pedestrians is
    "pedestrian" among them."""
    from yawil.data.schema import SPEED_REASONS
    from yawil.learn.config import TrainConfig
    from yawil.learn.loss import lead_stop_targets

    veh, junc, ped = (float(SPEED_REASONS.index(r)) for r in ("vehicle", "junction", "pedestrian"))
    # stop for a crossing car (no lead within 12 m); junction wait; junction slow-down at 2 m/s; pedestrian stop
    privileged = torch.tensor([[0.0, 50.0, 5.0, 0.0, veh], [0.3, math.nan, math.nan, -1.0, junc],
                               [2.0, 50.0, 5.0, 0.0, junc], [0.0, 50.0, 5.0, 0.0, ped]])
    assert lead_stop_targets(privileged)[0].tolist() == [0.0, 0.0, 0.0, 0.0]
    close, seen = lead_stop_targets(privileged, ("vehicle", "junction"))
    assert close.tolist() == [1.0, 1.0, 0.0, 0.0] and seen.tolist() == [True, True, True, True]
    both = TrainConfig(stop_reasons=["junction", "pedestrian"], stop_pedestrians=True, aux_weight=0.5)
    assert both.stop_label_reasons() == ("junction", "pedestrian")
    for bad in (["cruise"], ["vehicle", "vehicle"], "vehicle"):
        with pytest.raises(ValueError, match="stop_reasons"):
            TrainConfig(stop_reasons=bad, aux_weight=0.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="stop_reasons"):
        TrainConfig(stop_reasons=["vehicle"])  # no aux loss: nothing would learn them


def test_stop_pedestrians_needs_the_aux_loss_and_the_lead_stop_output(tmp_path: Path) -> None:
    from yawil.learn.config import TrainConfig
    from yawil.learn.setup import check_model_fits

    with pytest.raises(ValueError, match="stop_pedestrians"):
        TrainConfig(stop_pedestrians=True)
    with pytest.raises(ValueError, match="lead_stop=true"):
        check_model_fits(TrainConfig(stop_pedestrians=True, aux_weight=0.5, model_args={"aux": True}))
    with pytest.raises(ValueError, match="lead_stop=true"):
        check_model_fits(TrainConfig(stop_reasons=["junction"], aux_weight=0.5, model_args={"aux": True}))
    check_model_fits(TrainConfig(stop_pedestrians=True, aux_weight=0.5, model_args={"aux": True, "lead_stop": True}))
