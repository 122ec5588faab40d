"""yawil.models: the output contract, branch selection, learning, config round-trip, weights, bad input."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
import torchvision
from torch import Tensor

from yawil.cli import main
from yawil.models import DrivingModel, ModelOutput, create, feature_maps, list_models
from yawil.models.layers import LinearAttention

torch.set_num_threads(2)

NAMES = ["yilratt", "cil", "cilrs", "yaw-guided", "xy-guided", "simyaw-guided"]
RESNET = {"yilratt", "cilrs"}
SMALL_RESNET = (32, 32)  # smallest useful input: layer4 is 1 x 1
SMALL_CIL = (80, 80)  # the CIL convolutions need at least 77 x 77


def small(name: str, **cfg: Any) -> DrivingModel:
    """A model for small test images, seeded."""
    if name not in RESNET:
        cfg.setdefault("image_size", SMALL_CIL)
    return create(name, seed=0, **cfg)


def inputs(model: DrivingModel, batch: int, size: tuple[int, int], seed: int = 1) -> dict[str, Any]:
    g = torch.Generator().manual_seed(seed)
    return {
        "image": torch.rand(batch, 3, *size, generator=g),
        "speed": torch.rand(batch, 1, generator=g),
        "guidance": torch.rand(batch, model.guidance_dim, generator=g) if model.guidance else None,
        "command": torch.arange(batch) % 4 if model.uses_command else None,
    }


def size_of(name: str) -> tuple[int, int]:
    return SMALL_RESNET if name in RESNET else SMALL_CIL


def check_probability_map(m: Tensor, batch: int) -> None:
    assert m.dim() == 3 and m.shape[0] == batch
    assert m.dtype == torch.float32
    assert bool((m >= 0).all())
    torch.testing.assert_close(m.flatten(1).sum(1), torch.ones(batch), atol=1e-5, rtol=0)


def test_registry_names() -> None:
    assert sorted(list_models()) == sorted(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_full_size_output_contract(name: str) -> None:
    model = create(name, seed=0).eval()
    assert model.name == name
    x = inputs(model, 2, (88, 200))
    with torch.no_grad():
        out = model(**x)
    assert isinstance(out, ModelOutput)
    assert out.actions.shape == (2, 3) and out.speed.shape == (2, 1)
    steer, pedals = out.actions[:, 0], out.actions[:, 1:]
    assert bool((steer.abs() <= 1).all()) and bool(((pedals >= 0) & (pedals <= 1)).all())
    if name == "yilratt":
        assert [tuple(a.shape) for a in out.attention] == [(2, 22, 50), (2, 11, 25), (2, 6, 13)]
        for a in out.attention:
            check_probability_map(a, 2)
    else:
        assert out.attention == []
    if model.uses_command:
        assert out.branches is not None and out.branches.shape == (2, 4, 3)
        assert model.guidance is None and model.guidance_dim == 0
    else:
        assert out.branches is None
        assert model.guidance_dim == {"yaw": 15, "sim_yaw": 15, "xy": 30}[model.guidance or ""]


def test_yilratt_attention_any_size_and_guidance_kinds() -> None:
    for kind, dim in (("yaw", 15), ("xy", 30), ("sim_yaw", 15)):
        model = create("yilratt", guidance=kind, seed=0).eval()
        assert (model.guidance, model.guidance_dim) == (kind, dim)
    model = create("yilratt", guidance="xy", guidance_dim=7, seed=0).eval()
    x = inputs(model, 3, (44, 100))
    with torch.no_grad():
        out = model(**x)
    assert [tuple(a.shape[1:]) for a in out.attention] == [(11, 25), (6, 13), (3, 7)]
    for a in out.attention:
        check_probability_map(a, 3)


def test_linear_attention_matches_the_formula() -> None:
    torch.manual_seed(0)
    block = LinearAttention(local_channels=6, global_dim=10)
    local, g = torch.randn(2, 6, 3, 5), torch.randn(2, 10)
    vec, att = block(local, g)
    proj = torch.einsum("dc,bchw->bdhw", block.project.weight[:, :, 0, 0], local).flatten(2)  # l_i, [B, D, n]
    u = block.score.weight[0, :, 0, 0]
    c = torch.einsum("d,bdn->bn", u, proj + g[:, :, None])  # c_i = <u, l_i + g>
    a = torch.softmax(c, dim=1)
    torch.testing.assert_close(att, a.view(2, 3, 5))
    torch.testing.assert_close(vec, torch.einsum("bn,bdn->bd", a, proj))
    # <u, g> is the same at every position, so the softmax removes it: g does not move the map
    # (documented in docs/models.md; the test pins the behaviour the paper's formula implies).
    torch.testing.assert_close(block(local, torch.randn(2, 10))[1], att)


def test_yilratt_without_layer4_gives_the_papers_outputs() -> None:
    """Skipping layer4 (the default) is exact up to rounding, because <u, g> cancels in the softmax."""
    paper = small("yilratt", compute_global=True).eval()
    fast = small("yilratt").eval()
    assert fast.config["compute_global"] is False
    fast.load_state_dict(paper.state_dict())
    x = inputs(paper, 3, (64, 96))
    with torch.no_grad():
        a, b = paper(**x), fast(**x)
    torch.testing.assert_close(b.actions, a.actions, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(b.speed, a.speed, atol=1e-5, rtol=1e-4)
    for ma, mb in zip(a.attention, b.attention, strict=True):
        torch.testing.assert_close(mb, ma, atol=1e-6, rtol=1e-4)
    calls: list[str] = []
    fast.backbone.layer4.register_forward_hook(lambda *_: calls.append("layer4"))
    paper.backbone.layer4.register_forward_hook(lambda *_: calls.append("paper layer4"))
    with torch.no_grad():
        fast(**x), paper(**x)
    assert calls == ["paper layer4"]  # the default never runs layer4


@pytest.mark.parametrize("name", ["cil", "cilrs"])
def test_command_selects_branch(name: str) -> None:
    model = small(name).eval()
    x = inputs(model, 4, size_of(name))
    picked = []
    with torch.no_grad():
        for c in range(4):
            x["command"] = torch.full((4,), c, dtype=torch.int64)
            out = model(**x)
            assert out.branches is not None
            torch.testing.assert_close(out.actions, out.branches[:, c], rtol=0, atol=0)
            picked.append(out.actions)
        x["command"] = torch.tensor([3, 0, 2, 1])
        mixed = model(**x).actions
    for i, c in enumerate([3, 0, 2, 1]):
        torch.testing.assert_close(mixed[i], picked[c][i], rtol=0, atol=1e-6)
    assert not torch.allclose(picked[0], picked[1])


@pytest.mark.parametrize("name", ["yilratt", "yaw-guided", "xy-guided", "simyaw-guided"])
def test_guidance_and_speed_reach_the_actions(name: str) -> None:
    model = small(name).eval()
    x = inputs(model, 2, size_of(name))
    with torch.no_grad():
        base = model(**x)
        turned = model(**{**x, "guidance": x["guidance"] + 1.0})
        faster = model(**{**x, "speed": x["speed"] + 1.0})
    assert not torch.allclose(base.actions, turned.actions)
    assert not torch.allclose(base.actions, faster.actions)
    # the speed head sees perception only, as the paper's S(P(o))
    torch.testing.assert_close(base.speed, turned.speed, rtol=0, atol=0)
    torch.testing.assert_close(base.speed, faster.speed, rtol=0, atol=0)


@pytest.mark.parametrize("name", NAMES)
def test_overfits_a_tiny_batch(name: str) -> None:
    model = small(name, dropout=0.0).train()
    batch = 8
    x = inputs(model, batch, size_of(name))
    g = torch.Generator().manual_seed(2)
    target = torch.cat([torch.rand(batch, 1, generator=g) * 1.6 - 0.8, torch.rand(batch, 2, generator=g) * 0.8 + 0.1], 1)
    target_speed = torch.rand(batch, 1, generator=g)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    first = last = None
    for _ in range(300):
        out = model(**x)
        loss = torch.nn.functional.mse_loss(out.actions, target) + 0.1 * torch.nn.functional.mse_loss(out.speed, target_speed)
        last = loss.item()
        first = last if first is None else first
        if last < 0.05 * first:
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert first is not None and last is not None
    assert last < 0.1 * first, f"{name}: loss {first:.4f} -> {last:.4f}"


@pytest.mark.parametrize("name", NAMES)
def test_config_round_trip_and_seed(name: str) -> None:
    model = small(name, dropout=0.25)
    assert model.config["dropout"] == 0.25
    again = create(model.name, **model.config)
    assert again.config == model.config
    assert (again.guidance, again.guidance_dim, again.uses_command) == (model.guidance, model.guidance_dim, model.uses_command)
    same = small(name, dropout=0.25)
    a, b, c = model.state_dict(), again.state_dict(), same.state_dict()
    assert list(a) == list(b) and all(a[k].shape == b[k].shape for k in a)
    assert all(torch.equal(a[k], c[k]) for k in a)  # same seed, same weights, bit for bit
    other = create(name, seed=1, **model.config)
    assert any(not torch.equal(a[k], v) for k, v in other.state_dict().items() if v.is_floating_point())


@pytest.fixture(scope="module")
def imagenet_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "resnet34.pth"
    torch.manual_seed(3)
    torch.save(torchvision.models.resnet34().state_dict(), path)  # with fc.* keys, as torchvision ships it
    return path


@pytest.mark.parametrize("name", sorted(RESNET))
def test_pretrained_loads_into_backbone(name: str, imagenet_file: Path) -> None:
    model = create(name, pretrained=imagenet_file, seed=0)
    given = torch.load(imagenet_file, weights_only=True)
    loaded = model.state_dict()
    for key, value in given.items():
        if not key.startswith("fc."):
            assert torch.equal(loaded[f"backbone.{key}"], value), key
    assert "pretrained" not in model.config


def test_pretrained_errors(tmp_path: Path, imagenet_file: Path) -> None:
    missing = tmp_path / "nope.pth"
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        create("yilratt", pretrained=missing)
    r18 = tmp_path / "resnet18.pth"
    torch.save(torchvision.models.resnet18().state_dict(), r18)
    with pytest.raises(ValueError, match=r"resnet18\.pth.*(missing|unexpected).*layer"):
        create("cilrs", pretrained=r18)
    state = torch.load(imagenet_file, weights_only=True)
    state["conv1.weight"] = torch.zeros(64, 3, 3, 3)
    del state["bn1.bias"]
    bad = tmp_path / "bad.pth"
    torch.save(state, bad)
    with pytest.raises(ValueError, match=r"bad\.pth.*bn1\.bias.*conv1\.weight"):
        create("yilratt", pretrained=bad)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pth"):
        create("yilratt", pretrained=junk)
    with pytest.raises(ValueError, match="no ImageNet backbone"):
        create("cil", pretrained=imagenet_file)


@pytest.mark.parametrize("name", ["yilratt", "cilrs", "cil"])
def test_activation_maps_are_probability_maps(name: str) -> None:
    model = small(name).eval()
    image = inputs(model, 2, size_of(name))["image"]
    maps = feature_maps(model, image)
    assert len(maps) == 4
    for m in maps:
        check_probability_map(m, 2)
    if name in RESNET:
        assert [tuple(m.shape[1:]) for m in maps] == [(8, 8), (4, 4), (2, 2), (1, 1)]


def test_bf16_channels_last_forward() -> None:
    model = small("yilratt").eval().to(memory_format=torch.channels_last)
    x = inputs(model, 2, (44, 100))
    x["image"] = x["image"].contiguous(memory_format=torch.channels_last)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(**x)
        ref = model.float()(**x)
    assert out.actions.shape == (2, 3) and bool(out.actions.isfinite().all())
    for a in out.attention:
        check_probability_map(a, 2)
    assert ref.actions.shape == (2, 3)


@pytest.mark.parametrize("name", ["yilratt", "cil"])
def test_float64_inputs_are_accepted(name: str) -> None:
    model = small(name).eval()
    x = inputs(model, 2, size_of(name))
    x64 = {k: v.double() if v is not None and v.is_floating_point() else v for k, v in x.items()}
    with torch.no_grad():
        ref, out = model(**x), model(**x64)
    assert out.actions.dtype == torch.float32
    torch.testing.assert_close(out.actions, ref.actions)


def test_bad_inputs_raise_naming_the_argument() -> None:
    yil = small("yilratt").eval()
    cil = small("cil").eval()
    xy = inputs(yil, 2, SMALL_RESNET)
    xc = inputs(cil, 2, SMALL_CIL)
    cases: list[tuple[DrivingModel, dict[str, Any], str]] = [
        (yil, {**xy, "guidance": None}, r"guidance: required .*\[2, 15\]"),
        (yil, {**xy, "guidance": torch.zeros(2, 14)}, r"guidance: expected .*\[2, 15\]"),
        (yil, {**xy, "speed": torch.zeros(2)}, r"speed: expected .*\[2, 1\]"),
        (yil, {**xy, "image": torch.zeros(2, 1, 32, 32)}, r"image: expected .*\[B, 3, H, W\]"),
        (yil, {**xy, "image": torch.zeros(2, 3, 32, 32, dtype=torch.uint8)}, r"image: expected a float"),
        (cil, {**xc, "command": None}, r"command: required"),
        (cil, {**xc, "command": torch.tensor([0, 4])}, r"command: values must be in 0\.\.3"),
        (cil, {**xc, "command": torch.tensor([0.0, 1.0])}, r"command: expected an integer tensor \[2\]"),
        (cil, {**xc, "command": torch.tensor([0, 1, 2])}, r"command: expected an integer tensor \[2\]"),
        (cil, {**xc, "image": torch.zeros(2, 3, 88, 200)}, r"image: .*image_size \[80, 80\]"),
    ]
    for model, x, pattern in cases:
        with pytest.raises(ValueError, match=pattern):
            model(**x)
    with pytest.raises(ValueError, match="unknown name 'resnet'"):
        create("resnet")
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['guidance'\]"):
        create("yaw-guided", guidance="xy")
    with pytest.raises(ValueError, match="guidance: expected one of"):
        create("yilratt", guidance="gps")
    with pytest.raises(ValueError, match="guidance_dim"):
        create("yilratt", guidance_dim=0)
    with pytest.raises(ValueError, match="image_size"):
        create("cil", image_size=(64, 64))
    with pytest.raises(ValueError, match="image_size"):
        create("xy-guided", image_size=(88,))


def test_models_command_lists_every_model(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    for name in NAMES:
        assert name in out
    assert "23,044,164" in out  # YILRatt: ResNet34 without fc + attention + heads


def test_a_model_option_of_the_wrong_kind_is_named() -> None:
    """`--model-arg dropout=abc` used to end in a TypeError inside torch."""
    for name, key, value, want in (("yilratt", "dropout", "abc", "a number"), ("yilratt", "aux", 1, "true or false"),
                                   ("cil", "image_size", 88, "a list")):
        with pytest.raises(ValueError, match=f"option {key}=.* must be {want}"):
            create(name, **{key: value})
