"""`yawil sim` sub-commands, and one camera episode through the real renderer."""

from __future__ import annotations

import argparse
import sys
import types
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pytest

import yawil.sim.cli as sim_cli
from yawil.sim import Control, Scenario
from yawil.sim.town.world import EmbeddedWorld

matplotlib.use("Agg")


def main(argv: list[str]) -> int:
    """`yawil sim ...` through this command's own parser (the full CLI imports every command module)."""
    parser = argparse.ArgumentParser(prog="yawil")
    sim_cli.add_parser(parser.add_subparsers(dest="command"))
    return sim_cli.run(parser.parse_args(argv))


def test_routes_and_tasks(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "routes", "--town", "town02", "--count", "3", "--min-length", "300"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and all(int(line.split("length=")[1].split()[0]) >= 300 for line in lines)
    assert main(["sim", "tasks"]) == 0
    assert capsys.readouterr().out.strip().endswith("32 tasks")
    with pytest.raises(ValueError, match="town01"):
        main(["sim", "routes", "--town", "nowhere"])


def test_view_writes_camera_frames_and_birdseye(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The real camera renderer; the bird's-eye drawing is replaced by a recorder of its documented API."""
    import matplotlib.pyplot as plt

    calls: list[dict[str, Any]] = []

    def draw_birdseye(geometry: Any, route_xy: Any = None, actors: Any = (), ego: Any = None,
                      light_states: Any = None, path: Any = None, ax: Any = None) -> Any:
        calls.append({"geometry": geometry, "route_xy": route_xy, "actors": actors, "ego": ego, "lights": light_states})
        fig, _ = plt.subplots()
        return fig

    fake = types.ModuleType("yawil.sim.town.render.birdseye")
    fake.draw_birdseye = draw_birdseye  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "yawil.sim.town.render.birdseye", fake)
    out = tmp_path / "view"
    assert main(["sim", "view", "--town", "square", "--steps", "4", "--frames", "2", "--vehicles", "3",
                 "--pedestrians", "3", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [".yawil-output", "birdseye.png", "camera_0000.png", "camera_0004.png"]
    (call,) = calls
    assert call["geometry"].name == "square" and call["route_xy"].shape[1] == 2
    assert {a.kind for a in call["actors"]} == {"vehicle", "pedestrian"} and call["ego"].id == 0
    assert set(call["lights"].values()) <= {"red", "yellow", "green"} and len(call["lights"]) == 16


def test_camera_observation_is_deterministic() -> None:
    sc = Scenario(town="square", vehicles=2, pedestrians=2, camera=True)
    images = []
    for _ in range(2):
        w = EmbeddedWorld()
        obs = w.reset(sc, seed=1)
        obs = w.step(Control(throttle=0.5))
        w.close()
        assert obs.image is not None and obs.image.shape == (88, 200, 3) and obs.image.dtype == np.uint8
        images.append(obs.image)
    assert np.array_equal(images[0], images[1]) and images[0].std() > 5
