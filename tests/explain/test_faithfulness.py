"""The deletion test of heat maps (issue 42): a model whose output depends on a known region, maps that point
at it or elsewhere, masks, the activation-map baseline, and `yawil explain --faithfulness` end to end."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from yawil.explain import faithfulness as fa

H, W = 88, 200
ROWS, COLS = slice(44, 66), slice(100, 150)  # the region the synthetic model reads: 22 x 50 px, 6.25 % of the image


def _image(seed: int = 0) -> np.ndarray:
    """Dark noisy image with a bright region where the model looks: deleting the region changes its output."""
    rng = np.random.default_rng(seed)
    img = rng.integers(10, 60, size=(H, W, 3), dtype=np.uint8)
    img[ROWS, COLS] = rng.integers(200, 250, size=(22, 50, 3), dtype=np.uint8)
    return img


def _region_model(images: np.ndarray) -> dict[str, np.ndarray]:
    """Output = mean brightness of the region (its only input): nothing outside changes it."""
    x = np.asarray(images, dtype=np.float64) / 255.0
    return {"brake": x[:, ROWS, COLS].mean(axis=(1, 2, 3)), "steer": x[:, ROWS, COLS, 0].mean(axis=(1, 2)) - 0.5}


def _map_on(rows: slice, cols: slice, shape: tuple[int, int] = (22, 50)) -> np.ndarray:
    """A feature-resolution map (a quarter of the image size, like layer 1) that is 1 on the image region."""
    m = np.full(shape, 1e-6)
    fy, fx = shape[0] / H, shape[1] / W
    m[int(rows.start * fy):int(rows.stop * fy), int(cols.start * fx):int(cols.stop * fx)] = 1.0
    return m


def _frames(maps: dict[str, np.ndarray], n: int = 4) -> list[fa.Frame]:
    return [fa.Frame(_image(i), maps, _region_model, {"i": i}) for i in range(n)]


def _row(result: fa.DeletionResult, m: str, k: float, out: str = "brake") -> dict[str, Any]:
    return next(r for r in result.summary() if r["map"] == m and r["k"] == k and r["output"] == out)


@pytest.mark.parametrize("random", fa.RANDOMS)
def test_a_map_on_the_region_the_output_reads_is_faithful(random: str) -> None:
    maps = {"layer 1": _map_on(ROWS, COLS), "layer 2": _map_on(ROWS, COLS, (11, 25))}
    result = fa.deletion_test(_frames(maps), fa.DeletionSettings(ks=(5, 10, 20), random=random, seed=1))
    assert result.maps == ["layer 1", "layer 2", "mean"] and result.outputs == ["brake", "steer"]
    for m in result.maps:
        for k in (5.0, 10.0):
            r = _row(result, m, k)
            assert r["ratio"] > 5, r  # the top k % all lie in the region, k % at random hardly touch it
            assert r["bottom"] < 0.02 * r["top"]  # the least attended pixels lie (nearly all) outside it
            assert r["ratio_lo"] is not None and r["ratio_lo"] > 3


def test_a_map_pointing_elsewhere_gives_a_ratio_below_one() -> None:
    maps = {"layer 1": _map_on(slice(0, 22), slice(0, 50))}  # the sky in the top-left corner
    result = fa.deletion_test(_frames(maps), fa.DeletionSettings(ks=(5, 20), seed=2))
    assert result.maps == ["layer 1"]
    r = _row(result, "layer 1", 5.0)  # 5 % < the corner's 6.25 %: all in the corner
    assert r["top"] < 1e-9 and r["random"] > 0 and r["ratio"] < 0.1
    r = _row(result, "layer 1", 20.0)  # the corner, then 13.75 % of equally unattended pixels in random order
    assert r["ratio"] < 1.0
    for k in (5.0, 20.0):
        assert _row(result, "layer 1", k)["bottom"] > 0  # its least attended pixels include the region


def test_masking_nothing_changes_nothing() -> None:
    result = fa.deletion_test(_frames({"layer 1": _map_on(ROWS, COLS)}, n=2), fa.DeletionSettings(ks=(0,)))
    assert np.all(result.deltas == 0)
    assert _row(result, "layer 1", 0.0)["ratio"] is None  # 0 / 0 is no ratio, not a number
    img = _image()
    order = fa.pixel_order(fa.image_map(_map_on(ROWS, COLS), H, W), np.random.default_rng(0))
    for which in ("top", "bottom"):
        mask = fa.region(order, 0.0, which)
        assert not mask.any()
        assert np.array_equal(fa.masked(img, mask, fa.filler(img, "mean")), img)


def test_masks_have_k_percent_of_the_pixels_and_fill_them() -> None:
    img = _image()
    order = fa.pixel_order(fa.image_map(_map_on(ROWS, COLS), H, W), np.random.default_rng(0))
    top = fa.region(order, 5.0, "top").reshape(H, W)
    assert top.sum() == round(0.05 * H * W)
    assert top[ROWS, COLS].all() or top[ROWS, COLS].sum() == top.sum()  # 5 % < the region's 6.25 %: all inside
    out = fa.masked(img, top, fa.filler(img, "mean"))
    assert np.all(out[top] == np.round(img.reshape(-1, 3).mean(axis=0)).astype(np.uint8))
    assert np.array_equal(out[~top], img[~top])
    blurred = fa.filler(img, "blur", 3.0)
    assert blurred.shape == img.shape and blurred.dtype == np.uint8
    assert blurred.std() < img.std()  # smoother
    flat = np.full((H, W, 3), 77, dtype=np.uint8)
    assert np.array_equal(fa.gaussian_blur(flat, 4.0), flat)


def test_seeded_random_masks_are_reproducible() -> None:
    maps = {"layer 1": np.ones((22, 50)), "layer 2": np.ones((11, 25))}
    for how in fa.RANDOMS:
        a = fa.random_saliency(maps, H, W, how, np.random.default_rng(7))
        b = fa.random_saliency(maps, H, W, how, np.random.default_rng(7))
        c = fa.random_saliency(maps, H, W, how, np.random.default_rng(8))
        assert list(a) == ["layer 1", "layer 2", "mean"]
        assert all(np.array_equal(a[n], b[n]) for n in a)
        assert not np.array_equal(a["layer 1"], c["layer 1"])
    # a flat map has no top: ties go in a seeded order, not the image's top rows first
    flat = fa.pixel_order(np.ones((H, W)), np.random.default_rng(3))
    assert np.array_equal(flat, fa.pixel_order(np.ones((H, W)), np.random.default_rng(3)))
    rows = fa.region(flat, 10.0).reshape(H, W).any(axis=1)
    assert rows.sum() > H // 2
    # the whole test: the same seed gives the same numbers
    frames = _frames({"layer 1": _map_on(ROWS, COLS)}, n=2)
    one = fa.deletion_test(frames, fa.DeletionSettings(ks=(10,), seed=5, draws=2))
    two = fa.deletion_test(frames, fa.DeletionSettings(ks=(10,), seed=5, draws=2))
    assert np.array_equal(one.deltas, two.deltas)


def test_settings_are_checked() -> None:
    for bad in ({"ks": (120,)}, {"ks": ()}, {"fill": "zero"}, {"random": "noise"}, {"draws": 0}, {"blur_sigma": 0}):
        with pytest.raises(ValueError):
            fa.DeletionSettings(**bad)
    with pytest.raises(ValueError, match="react"):
        fa.ClosedLoopSettings(horizon=3, react=5)


def test_braking_moments_are_onsets() -> None:
    assert fa.braking_moments([0, 0.5, 0.5, 0, 0.2, 0, 0, 1], 10) == [1, 4, 7]
    assert fa.braking_moments([0.3, 0.3, 0], 10) == [0]
    assert fa.braking_moments([0, 1] * 20, 3) == [1, 21, 39]  # first, middle, last of 20
    assert fa.braking_moments([0, 0.5, 0, 0.5], 10, speeds=[0, 0.2, 3, 3], min_speed=0.5) == [3]  # not standing


def test_explain_faithfulness_end_to_end(tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.cli import main
    from yawil.guidance import GuidanceConfig

    data = tiny_dataset(episodes=2, frames=5, k=15)
    ckpt = tiny_checkpoint("yilratt", guidance=GuidanceConfig(count=15).to_dict(), guidance_dim=15, aux=True,
                           lead_stop=True)
    out = tmp_path / "f"
    args = ["explain", "--checkpoint", str(ckpt.path), "--frames", str(data), "--faithfulness", "--count", "2",
            "--ks", "10,40", "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "deletion test, 2 frames, attention maps" in printed and "lead_stop" in printed
    record = json.loads((out / "faithfulness.json").read_text())
    assert record["maps"] == ["layer 1", "layer 2", "layer 3", "mean"] and record["map_source"] == "attention"
    assert {"steer", "throttle", "brake", "speed", "target_speed", "lead_stop"} <= set(record["outputs"])
    assert len(record["results"]) == 4 * 2 * len(record["outputs"]) and len(record["frames"]) == 2
    assert (out / "faithfulness.csv").read_text().startswith("map,k,output,top,random,bottom,ratio")
    assert "| map | k % |" in (out / "faithfulness.md").read_text()
    assert (out / "faithfulness.png").stat().st_size > 0
    from yawil.agent import Agent

    yil = Agent.from_checkpoint(ckpt.path).model
    assert len(fa.activation_maps(yil, _image())) == 3  # its forward never reaches layer 4: no map of it


def test_cilrs_gets_the_activation_map_baseline(tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any) -> None:
    """A network without attention: channel-mean |activation| maps, the last conv stage's at the image's shape."""
    from yawil.agent import Agent

    data = tiny_dataset(episodes=2, frames=5, k=15)
    agent = Agent.from_checkpoint(tiny_checkpoint("cilrs").path)
    img = _image()
    amap = fa.activation_map(agent.model, img)
    assert amap.shape == (H, W) and np.all(amap >= 0) and amap.sum() == pytest.approx(1.0)
    maps = fa.activation_maps(agent.model, img)
    assert [m.shape for m in maps] == [(22, 50), (11, 25), (6, 13), (3, 7)]  # layer 4 is the last conv stage
    result = fa.deletion_test_dataset(agent, data, 1, fa.DeletionSettings(ks=(20,)))
    assert result.source == "activation" and result.maps == ["layer 1", "layer 2", "layer 3", "layer 4", "mean"]
    assert result.outputs == ["steer", "throttle", "brake", "speed"]
    with pytest.raises(ValueError, match="no attention"):
        fa.deletion_test_dataset(agent, data, 1, fa.DeletionSettings(ks=(20,)), source="attention")


def test_closed_loop_replays_to_each_braking_moment(tmp_path: Path, tiny_checkpoint: Any) -> None:
    """An agent that drives and brakes on every third frame: each onset is replayed to the recorded pose (the car
    moves, so a wrong replay would show) and driven on masked."""
    from yawil.agent import Agent
    from yawil.explain.attention import EpisodeVideo
    from yawil.sim.types import Control

    class EveryThird(Agent):
        def act(self, obs: Any) -> Control:
            c = super().act(obs)
            brake = obs.frame % 3 == 2
            return Control(steer=c.steer, throttle=0.0 if brake else 0.8, brake=0.5 if brake else 0.0)

    agent = EveryThird.from_checkpoint(tiny_checkpoint("yilratt").path)
    episode = EpisodeVideo(town="town02", weather="ClearNoon", vehicles=0, pedestrians=0, steps=9)
    record = fa.closed_loop_test(agent, episode, fa.ClosedLoopSettings(k=20, horizon=2, react=1, moments=2,
                                                                           min_speed=0.0))
    assert record["steps"] == 9 and record["map_source"] == "attention"
    assert [m["step"] for m in record["moments"]] == [2, 8]  # onsets 2, 5, 8: the first and the last of three
    assert record["moments"][1]["speed"] > 0
    for kind in ("top", "random"):
        s = record["summary"][kind]
        assert s["diverged"] == 0 and s["moments"] == 2 and s["still_brakes"] == 2 and s["share"] == 1.0
    paths = fa.write_closed_loop(record, tmp_path)
    assert json.loads(paths[0].read_text())["summary"] == json.loads(json.dumps(record["summary"]))
    assert "closed-loop test" in fa.format_closed_loop(record)
    with pytest.raises(ValueError, match="maps are layer 1, layer 2, layer 3, mean"):  # before any driving
        fa.closed_loop_test(agent, episode, fa.ClosedLoopSettings(layer="layer 4"))


def test_cli_states_the_settings_defaults() -> None:
    """`yawil explain` states the test's defaults itself (its --help imports nothing): keep the two the same."""
    import argparse

    from yawil.explain.cli import add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    base = ["explain", "--checkpoint", "c.pt", "--frames", "d", "--faithfulness", "--out", "o"]
    args = parser.parse_args(base)
    d, c = fa.DeletionSettings(), fa.ClosedLoopSettings()
    assert tuple(float(v) for v in args.ks.split(",")) == d.ks
    assert (args.fill, args.random, args.maps) == (d.fill, d.random, fa.SOURCES[0])
    assert (args.mask_k, args.mask_layer, args.horizon, args.moments) == (c.k, c.layer, c.horizon, c.moments)
    for option, values in (("--fill", fa.FILLS), ("--random", fa.RANDOMS), ("--maps", fa.SOURCES)):
        for v in values:
            assert parser.parse_args([*base, option, v]) is not None
