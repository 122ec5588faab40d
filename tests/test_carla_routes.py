"""The CARLA route generator, run offline on a real carla.Map built from OpenDRIVE (tests/fixtures/carla/grid.xodr)."""

from __future__ import annotations

import json
from pathlib import Path

import carla
import pytest

from yawil.bench.suites import parse_route
from yawil.sim.carla.routes import generate_routes, validate_routes, write_route_file
from yawil.sim.carla.routes.__main__ import main
from yawil.sim.carla.topology import CarlaTopology
from yawil.sim.types import Pose

FIX = Path(__file__).parent / "fixtures" / "carla"


@pytest.fixture(scope="module")
def grid() -> CarlaTopology:
    return CarlaTopology.from_carla_map(carla.Map("Town02", (FIX / "grid.xodr").read_text(encoding="utf-8")))


def test_generated_routes_follow_the_task_rules_and_are_seeded(grid: CarlaTopology, tmp_path: Path) -> None:
    path = write_route_file(grid, "town02", seed=0, folder=tmp_path, per_task=4)
    doc = json.loads(path.read_text(encoding="utf-8"))
    assert doc["format"] == "yawil-routes/1" and doc["town"] == "town02" and set(doc["routes"]) == {"straight", "one_turn", "navigation"}
    specs = {k: [parse_route(o, k) for o in v] for k, v in doc["routes"].items()}
    assert all(len(v) == 4 for v in specs.values())
    assert all(not {"LEFT", "RIGHT"} & set(s.turns) and s.length_m >= 60 for s in specs["straight"])
    assert all(sum(t in ("LEFT", "RIGHT") for t in s.turns) == 1 for s in specs["one_turn"])
    assert all(s.length_m >= 300 for s in specs["navigation"])
    validate_routes(grid, specs, "test")
    again = generate_routes(grid, "town02", seed=0, per_task=4)
    assert [s.to_json() for s in again["navigation"]] == doc["routes"]["navigation"]


def test_validation_names_a_start_off_the_lanes(grid: CarlaTopology) -> None:
    lists = generate_routes(grid, "town02", seed=1, per_task=1)
    spec = lists["straight"][0]
    moved = type(spec)(spec.id, Pose(spec.start.x + 30.0, spec.start.y + 30.0, spec.start.yaw), spec.goal, spec.length_m, spec.turns)
    with pytest.raises(ValueError, match=r"routes\.straight\[0\]\.start .* m from the nearest driving lane"):
        validate_routes(grid, {"straight": [moved]}, "file.json")
    with pytest.raises(ValueError, match="no route rules for CARLA town 'square'"):
        generate_routes(grid, "square")


def test_cli_without_a_server_exits_2_with_the_reason(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--host", "127.0.0.1", "--port", "2999", "--timeout", "0.5", "--town", "town01"]) == 2
    err = capsys.readouterr().err
    assert "no CARLA server answers at 127.0.0.1:2999" in err and "CarlaUE4.sh" in err
