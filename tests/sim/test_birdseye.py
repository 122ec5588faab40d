"""Bird's-eye map: the PNG is written atomically and shows the route, agents and trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_render import crossing_town

from yawil.sim.town.map.geometry import ActorView
from yawil.sim.town.render.birdseye import draw_birdseye
from yawil.sim.types import Pose

ROUTE = np.column_stack([np.linspace(-60, -2, 59), np.full(59, -1.75)])
ROUTE = np.vstack([ROUTE, np.column_stack([np.full(58, 1.75), np.linspace(1, 58, 58)])])  # then turn north


def _route_pixels(png: Path) -> int:
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    target = np.array([0x1F, 0x5F, 0xFF])
    return int((np.abs(img - target).sum(axis=2) < 60).sum())


def test_png_written_with_route(tmp_path: Path) -> None:
    town = crossing_town()
    actors = [ActorView(1, "vehicle", 20.0, 1.75, 3.14, 4.5, 1.9, 1.5, (0.8, 0.1, 0.1)),
              ActorView(2, "pedestrian", -10.0, 5.0, 0.0, 0.4, 0.5, 1.7, (0.1, 0.2, 0.9))]
    with_route = tmp_path / "maps" / "with.png"
    fig = draw_birdseye(town, route_xy=ROUTE, actors=actors, ego=Pose(-40.0, -1.75, 0.0),
                        light_states={0: "red", 1: "green"}, path=with_route,
                        trajectories={"yaw-guided": ROUTE + 0.3, "cil": ROUTE[:40] - 0.3})
    assert with_route.stat().st_size > 1000
    assert Image.open(with_route).format == "PNG"
    assert [ln.get_label() for ln in fig.axes[0].lines if ln.get_label() == "route"] == ["route"]
    without = tmp_path / "without.png"
    draw_birdseye(town, path=without)
    assert _route_pixels(with_route) > 200 > _route_pixels(without)
    assert not list(tmp_path.rglob("*.tmp"))  # no temporary file left behind


def test_draws_into_given_axes_and_rejects_bad_input(tmp_path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot(1, 2, 2)
    assert draw_birdseye(crossing_town(), route_xy=ROUTE, ax=ax) is fig
    with pytest.raises(ValueError, match="route_xy"):
        draw_birdseye(crossing_town(), route_xy=np.zeros((5, 3, 1)))
    with pytest.raises(ValueError, match="trajectories\\['bad'\\]"):
        draw_birdseye(crossing_town(), trajectories={"bad": np.array([[0.0, np.nan]])})
