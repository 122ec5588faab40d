"""`yawil explain` end to end on a tiny untrained checkpoint: frame figures, grid, episode video."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from yawil import video
from yawil.cli import main
from yawil.explain import attention, figures
from yawil.guidance import GuidanceConfig


def _checkpoint(tiny_checkpoint: Any, name: str, k: int) -> Path:
    """An untrained `name` whose guidance has k values (yilratt's input follows k)."""
    cfg = {"guidance_dim": k} if name == "yilratt" else {}
    return tiny_checkpoint(name, guidance=GuidanceConfig(count=k).to_dict(), **cfg).path


@pytest.mark.parametrize("name", ["yilratt", "cilrs"])
def test_explain_frames_writes_figures(tmp_path: Path, name: str, tiny_checkpoint: Any, tiny_dataset: Any) -> None:
    data = tiny_dataset(episodes=2, frames=5, k=15)
    ckpt = _checkpoint(tiny_checkpoint, name, 15)
    assert main(["explain", "--checkpoint", str(ckpt), "--frames", str(data), "--count", "2", "--out", str(tmp_path / "x")]) == 0
    assert (tmp_path / "x" / "frame_00.png").stat().st_size > 0
    assert (tmp_path / "x" / "grid.png").stat().st_size > 0


def test_explain_frames_refuses_data_of_another_guidance_reference(
    tmp_path: Path, tiny_checkpoint: Any, tiny_dataset: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """An `ego` model explained on the paper's `route` data would read guidance it never saw: one clear line."""
    data = tiny_dataset(episodes=1, frames=3, k=15)
    ego = tiny_checkpoint("yilratt", guidance=GuidanceConfig(count=15, reference="ego").to_dict(), guidance_dim=15)
    assert main(["explain", "--checkpoint", str(ego.path), "--frames", str(data), "--count", "1",
                 "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert ".h5" in err and "'reference': 'route'" in err and "--guidance-reference ego" in err
    assert not (tmp_path / "x" / "grid.png").exists()


def test_record_maps_are_probability_maps(tiny_checkpoint: Any, tiny_dataset: Any) -> None:
    from yawil.agent import Agent
    from yawil.data.reader import open_episode

    data = tiny_dataset(episodes=1, frames=3, k=15)
    agent = Agent.from_checkpoint(_checkpoint(tiny_checkpoint, "yilratt", 15))
    with open_episode(next(data.rglob("*.h5"))) as ep:
        item = attention.explain_record(agent, ep[0])
    assert len(item.maps) == 3
    for m in item.maps:
        assert np.all(m >= 0) and float(m.sum()) == pytest.approx(1.0, abs=1e-3)
    assert figures.overlay(item.image, item.maps[0]).shape == item.image.shape


def test_explain_episode_video_has_the_frames(tmp_path: Path, tiny_checkpoint: Any) -> None:
    ckpt = _checkpoint(tiny_checkpoint, "yilratt", 15)
    args = ["explain", "--checkpoint", str(ckpt), "--episode", "--town", "town02", "--weather", "ClearNoon",
            "--vehicles", "0", "--pedestrians", "0", "--steps", "6", "--every", "2", "--out", str(tmp_path / "v")]  # fmt: skip
    assert main(args) == 0
    videos = list((tmp_path / "v").glob("episode.*"))
    assert len(videos) == 1
    assert video.read_video_frames(videos[0]) == 3


def test_episode_flags_default_to_the_episode_video() -> None:
    """`yawil explain --episode` without options drives `EpisodeVideo()` (the CLI keeps only argparse at
    module level, so it states the defaults itself: this keeps the two the same)."""
    import argparse

    from yawil.explain.cli import add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(["explain", "--checkpoint", "c.pt", "--episode", "--out", "o"])
    for field in dataclasses.fields(attention.EpisodeVideo):
        assert getattr(args, field.name) == getattr(attention.EpisodeVideo(), field.name), field.name
    assert args.alpha == figures.DEFAULT_ALPHA
