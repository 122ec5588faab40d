"""The CARLA route generator, run offline on a real carla.Map built from OpenDRIVE (tests/fixtures/carla/grid.xodr),
the `--xodr` source of the CLI, and the committed route files' checks that need no map."""

from __future__ import annotations

import hashlib
import json
from importlib.metadata import version
from pathlib import Path

import carla
import pytest

from yawil.bench.carla_routes import (
    CARLA_ROUTES_DIR,
    TOWNS,
    generate_routes,
    load_carla_routes,
    topology_from_xodr,
    validate_routes,
    write_route_file,
)
from yawil.bench.carla_routes.__main__ import main
from yawil.bench.suites import parse_route
from yawil.sim.carla.topology import CarlaTopology
from yawil.sim.types import Pose

FIX = Path(__file__).parents[1] / "fixtures" / "carla"


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


# ------------------------------------------------------------------------------ the offline source (--xodr)
@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder of a full route file made by the CLI from grid.xodr (standing in for CARLA's Town02.xodr)."""
    folder = tmp_path_factory.mktemp("made")
    assert main(["--xodr", str(FIX / "grid.xodr"), "--town", "town02", "--out", str(folder)]) == 0
    return folder


def _copy(made: Path, tmp_path: Path) -> Path:
    (tmp_path / "town02.json").write_bytes((made / "town02.json").read_bytes())
    return tmp_path / "town02.json"


def test_xodr_source_writes_a_full_file_with_its_provenance_and_checks_it(made: Path) -> None:
    xodr = FIX / "grid.xodr"
    doc = json.loads((made / "town02.json").read_text(encoding="utf-8"))
    assert doc["source"] == {"kind": "xodr", "map": "Town02", "xodr_file": "grid.xodr",
                             "xodr_sha256": hashlib.sha256(xodr.read_bytes()).hexdigest(),
                             "carla_client": version("carla")}
    assert doc["generated_by"] == "python -m yawil.bench.carla_routes --xodr grid.xodr --town town02 --seed 0"
    lists, src = load_carla_routes("town02", made)  # the protocol's 25 per task, kinds, lengths
    assert {k: len(v) for k, v in lists.items()} == {"straight": 25, "one_turn": 25, "navigation": 25}
    assert src["xodr_sha256"] == doc["source"]["xodr_sha256"]
    assert main(["--xodr", str(xodr), "--town", "town02", "--out", str(made), "--check", "--plot", str(made / "r.png")]) == 0
    assert (made / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # a picture of the routes over the map
    # the same seed on the same map gives the same file, bit for bit
    again = made / "again"
    assert main(["--xodr", str(xodr), "--town", "town02", "--out", str(again)]) == 0
    assert (again / "town02.json").read_bytes() == (made / "town02.json").read_bytes()


def test_check_against_the_xodr_names_a_route_whose_length_differs(made: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    xodr = FIX / "grid.xodr"
    path = _copy(made, tmp_path)
    doc = json.loads(path.read_text(encoding="utf-8"))
    doc["routes"]["navigation"][3]["length_m"] += 50.0
    path.write_text(json.dumps(doc), encoding="utf-8")
    capsys.readouterr()
    assert main(["--xodr", str(xodr), "--town", "town02", "--out", str(tmp_path), "--check"]) == 2
    assert "routes.navigation[3] is" in capsys.readouterr().err


@pytest.mark.parametrize(("args", "message"), [
    (["--xodr", "/nonexistent/Town01.xodr", "--town", "town01"], "cannot read the OpenDRIVE file"),
    (["--xodr", str(FIX / "grid.osm"), "--town", "town01"], "no <OpenDRIVE> element"),
    (["--xodr", str(FIX / "grid.xodr")], "give exactly one --town"),
])
def test_xodr_source_errors_name_the_file_and_the_fix(args: list[str], message: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main(args) == 2
    assert message in capsys.readouterr().err


def test_an_unparsable_xodr_is_a_value_error_naming_it(tmp_path: Path) -> None:
    bad = tmp_path / "Town01.xodr"
    bad.write_text("<OpenDRIVE><header/><road id='1'", encoding="utf-8")
    with pytest.raises(ValueError, match=r"Town01\.xodr: carla\.Map cannot build a map"):
        topology_from_xodr(bad, "town01")
    with pytest.raises(ValueError, match="no route rules for CARLA town 'town03'"):
        topology_from_xodr(FIX / "grid.xodr", "town03")


def test_route_file_provenance_is_checked_without_a_map(made: Path, tmp_path: Path) -> None:
    path = _copy(made, tmp_path)
    good = json.loads(path.read_text(encoding="utf-8"))
    for change, message in [
        (lambda d: d.pop("source"), "field 'source' must be an object"),
        (lambda d: d["source"].update(map="Town01"), "source.map is 'Town01', expected 'Town02'"),
        (lambda d: d["source"].update(xodr_sha256="abc"), "xodr_sha256 must be 64 lowercase hex"),
        (lambda d: d["routes"]["straight"][2].update(goal=d["routes"]["straight"][2]["start"]), r"straight\[2\] starts where it ends"),
    ]:
        doc = json.loads(json.dumps(good))
        change(doc)
        path.write_text(json.dumps(doc), encoding="utf-8")
        with pytest.raises(ValueError, match=message):
            load_carla_routes("town02", tmp_path)


@pytest.mark.parametrize("town", TOWNS)
def test_committed_route_files_are_valid_or_absent_with_the_recipe(town: str) -> None:
    """Town01/02 need CARLA's own .xodr (not in git, not on this machine): until a file is committed, asking for it
    must say how to make it; once committed, it must pass every check that needs no map."""
    path = CARLA_ROUTES_DIR / f"{town}.json"
    if not path.exists():
        with pytest.raises(ValueError, match=rf"python -m yawil\.bench\.carla_routes --xodr Town0\d\.xodr --town {town}"):
            load_carla_routes(town)
        return
    lists, src = load_carla_routes(town)
    assert set(lists) == {"straight", "one_turn", "navigation"} and all(len(v) == 25 for v in lists.values())
    assert src["kind"] in ("xodr", "server") and src["carla_client"]
    for specs in lists.values():
        assert len({(round(s.start.x), round(s.start.y), round(s.goal.x), round(s.goal.y)) for s in specs}) == 25
