"""Heat-map overlays and videos."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from yawil import video
from yawil.explain import figures


def _image(h: int = 88, w: int = 200) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 12), st.integers(1, 25)), elements=st.floats(0, 100)))
def test_normalised_map_sums_to_one(att: np.ndarray) -> None:
    p = figures.normalise_map(att)
    assert p.shape == att.shape
    assert np.all(p >= 0)
    assert p.sum() == pytest.approx(1.0)


def test_overlay_has_image_size_and_changes_pixels() -> None:
    img = _image()
    att = np.zeros((11, 25))
    att[5, 12] = 1.0
    out = figures.overlay(img, att)
    assert out.shape == img.shape and out.dtype == np.uint8
    assert not np.array_equal(out, img)
    # alpha 0 leaves the image as it is
    assert np.array_equal(figures.overlay(img, att, alpha=0.0), img)


def test_upsample_keeps_constant_maps_constant() -> None:
    up = figures.upsample(np.full((3, 7), 2.0), 88, 200)
    assert up.shape == (88, 200)
    assert np.allclose(up, 2.0)


def test_peak_lands_where_the_map_peaks() -> None:
    att = np.zeros((4, 10))
    att[3, 9] = 1.0  # bottom-right cell
    up = figures.upsample(figures.normalise_map(att), 88, 200)
    y, x = np.unravel_index(np.argmax(up), up.shape)
    assert y > 66 and x > 180


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="2-D"):
        figures.normalise_map(np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="NaN"):
        figures.normalise_map(np.array([[np.nan, 1.0]]))
    with pytest.raises(ValueError, match="uint8"):
        figures.overlay(np.zeros((4, 4, 3), dtype=np.float32), np.ones((2, 2)))
    with pytest.raises(ValueError, match="alpha"):
        figures.overlay(_image(), np.ones((2, 2)), alpha=2.0)


def test_figures_and_video(tmp_path: Path) -> None:
    item = figures.Explained(
        image=_image(), maps=[np.ones((22, 50)), np.ones((11, 25)), np.ones((6, 13))], steer=0.1, throttle=0.5, brake=0.0, speed=5.0
    )
    fig = figures.frame_figure(item, path=tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 0
    frames = [video.figure_to_array(fig) for _ in range(5)]
    figures.grid_figure([item, item], path=tmp_path / "grid.png")
    assert (tmp_path / "grid.png").stat().st_size > 0
    path = video.write_video(frames, tmp_path / "ep.mp4", fps=5)
    assert path.exists()
    assert video.read_video_frames(path) == 5
