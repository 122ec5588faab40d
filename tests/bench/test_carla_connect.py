"""`yawil bench --backend carla` finds, makes and checks the town's route file on connect (FakeCarlaServer).

The stand-in server (tests/sim/test_carla_world.py) carries a REAL carla.Map built from
tests/fixtures/carla/grid.xodr under the name Town02 or Town01, so the topology the files are made from and
checked against is CARLA's own; town02's rules (60 m / 300 m) fit the grid, town01's 1 km navigation does not.
The `carla.Client` constructor is replaced by one that returns the stand-in: the command runs unchanged.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import carla
import pytest

import yawil.bench.carla_routes as carla_routes
from carla_fakes import VERSION, FakeCarlaServer
from yawil.bench.carla_routes import CARLA_ROUTES_DIR, generate_routes
from yawil.bench.carla_routes import connect as connect_mod
from yawil.bench.suites import load_routes
from yawil.cli import main
from yawil.sim.carla.topology import CarlaTopology

FIX = Path(__file__).parents[1] / "fixtures" / "carla"
RUN = ["bench", "--backend", "carla", "--suite", "corl2017", "--tasks", "straight", "--seeds", "1", "--no-progress",
       "--weather-rule", "cycle"]


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> FakeCarlaServer:
    """A stand-in server behind `carla.Client`, an empty user cache and an empty package folder."""
    fake = FakeCarlaServer(town="Town01")
    monkeypatch.setattr(carla, "Client", lambda host, port: fake)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    (tmp_path / "package").mkdir()
    monkeypatch.setattr(connect_mod, "CARLA_ROUTES_DIR", tmp_path / "package")  # as if nothing were committed
    return fake


def _episodes(out: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out / "episodes.jsonl").read_text(encoding="utf-8").splitlines()]


def test_first_run_makes_the_file_and_later_runs_reuse_it(server: FakeCarlaServer, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    cached = tmp_path / "cache" / "yawil" / "carla_routes" / "town02.json"
    assert main([*RUN, "--condition", "new-town-weather", "--routes", "0,1", "--out", str(tmp_path / "r1")]) == 0
    said = capsys.readouterr().out
    assert f"made one from the server's map Carla/Maps/Town02 at localhost:2000 (seed 0) and wrote {cached}" in said
    assert "commit it to" in said and f"{cached} fits the server's map" in said
    doc = json.loads(cached.read_text(encoding="utf-8"))
    assert doc["source"] == {"kind": "server", "map": "Carla/Maps/Town02", "address": "localhost:2000", "carla_client": VERSION}
    assert {k: len(v) for k, v in doc["routes"].items()} == {"straight": 25, "one_turn": 25, "navigation": 25}
    assert server.loads == ["Town02"]  # checked once, then driven on the same connection without reloading
    first = _episodes(tmp_path / "r1")
    assert len(first) == 2 and all(r["town"] == "town02" and r["success"] for r in first)
    for rec, spec in zip(first, doc["routes"]["straight"][:2], strict=True):
        assert rec["route_length_m"] == spec["length_m"] and abs(rec["planned_length_m"] - spec["length_m"]) < 1.0

    # a second run (a new process would do the same): the file is found, checked, and not made again
    made = cached.read_bytes()

    def no_generation(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the route file was generated again")

    monkeypatch.setattr(connect_mod, "write_route_file", no_generation)
    assert main([*RUN, "--condition", "new-town-weather", "--routes", "0,1", "--out", str(tmp_path / "r2")]) == 0
    said = capsys.readouterr().out
    assert "made one" not in said and f"{cached} fits the server's map Carla/Maps/Town02 (75 routes" in said
    assert cached.read_bytes() == made
    again = _episodes(tmp_path / "r2")
    assert [(r["route_id"], r["route_length_m"], r["route_xy"]) for r in again] == \
        [(r["route_id"], r["route_length_m"], r["route_xy"]) for r in first]


def test_routes_dir_is_searched_first_and_written_to(server: FakeCarlaServer, tmp_path: Path) -> None:
    mine = tmp_path / "mine"
    assert main([*RUN, "--condition", "new-town-weather", "--routes", "0", "--routes-dir", str(mine),
                 "--out", str(tmp_path / "r")]) == 0
    assert (mine / "town02.json").exists() and not (tmp_path / "cache").exists()


@pytest.mark.parametrize(("tamper", "message"), [
    (lambda d: d["routes"]["navigation"][3].update(length_m=d["routes"]["navigation"][3]["length_m"] + 50.0),
     r"routes\.navigation\[3\] is \d+\.\d m on this map, the file says \d+\.\d m"),
    (lambda d: d["routes"]["one_turn"][7]["start"].update(x=75.0, y=75.0),  # the middle of a block
     r"routes\.one_turn\[7\]\.start .* is \d+\.\d m from the nearest driving lane"),
])
def test_a_file_that_does_not_fit_the_server_is_refused_before_any_episode(
        server: FakeCarlaServer, tmp_path: Path, tamper: Any, message: str) -> None:
    mine = tmp_path / "mine"
    topo = CarlaTopology.from_carla_map(carla.Map("Town02", (FIX / "grid.xodr").read_text(encoding="utf-8")))
    carla_routes.write_route_file(topo, "town02", 0, mine, source={"kind": "server", "map": "Town02",
                                                                   "address": "elsewhere:2000", "carla_client": VERSION})
    path = mine / "town02.json"
    doc = json.loads(path.read_text(encoding="utf-8"))
    tamper(doc)
    path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(SystemExit, match=rf"{path}: {message}.*does not fit the map 'Carla/Maps/Town02' of the server "
                                         rf"at localhost:2000 \(file made from the server at elsewhere:2000"):
        main([*RUN, "--condition", "new-town-weather", "--routes-dir", str(mine), "--out", str(tmp_path / "r")])
    assert not (tmp_path / "r" / "episodes.jsonl").exists() or _episodes(tmp_path / "r") == []
    assert not any(a.type_id.startswith("vehicle.") for a in server.actors.values())  # no ego was ever spawned


def test_failed_generation_writes_nothing(server: FakeCarlaServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """town01's rules (80 m straight, 1 km navigation) hardly fit the 300 m grid: a clear error, no file."""
    monkeypatch.setattr(carla_routes, "MAX_ATTEMPTS", 150)
    with pytest.raises(SystemExit, match=r"no route file for town01 in .* and making one from the map 'Carla/Maps/Town01' "
                                         r"of the server at localhost:2000 failed \(nothing written\): could not draw 25 "
                                         r"\w+ routes of >= \d+ m .* in 150 attempts: got \d+, the longest"):
        main([*RUN, "--condition", "training", "--out", str(tmp_path / "r")])
    folder = tmp_path / "cache" / "yawil" / "carla_routes"
    assert not folder.exists() or list(folder.iterdir()) == []


def test_square_and_absent_servers_are_clear_before_anything_is_written(server: FakeCarlaServer, tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="CARLA's own maps"):
        main(["bench", "--backend", "carla", "--suite", "square", "--out", str(tmp_path / "r")])
    server.crashed = True  # answers nothing
    with pytest.raises(SystemExit, match=r"yawil bench: no CARLA server answers at localhost:2000 .*CarlaUE4\.sh"):
        main(["bench", "--backend", "carla", "--out", str(tmp_path / "r")])
    assert not (tmp_path / "r").exists() and not (tmp_path / "cache").exists()


def test_generation_gives_up_after_its_attempts_with_the_figures() -> None:
    grid = CarlaTopology.from_carla_map(carla.Map("Town01", (FIX / "grid.xodr").read_text(encoding="utf-8")))
    with pytest.raises(ValueError, match=r"could not draw 1 straight routes of >= 80 m on CARLA town01 \(map 'Town01'\) "
                                         r"in 40 attempts: got 0, the longest candidate as planned was \d+ m"):
        generate_routes(grid, "town01", seed=0, per_task=1, max_attempts=40)
    with pytest.raises(ValueError, match="max_attempts must be a positive integer"):
        generate_routes(grid, "town02", max_attempts=0)


def test_missing_file_in_the_carla_folder_names_the_carla_commands(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import yawil.bench.suites as suites

    assert suites._CARLA_ROUTES_DIR.resolve() == CARLA_ROUTES_DIR.resolve()  # the folder load_routes recognises
    monkeypatch.setattr(suites, "_CARLA_ROUTES_DIR", tmp_path / "carla")  # an empty one, whatever is committed
    with pytest.raises(ValueError, match=r"`yawil bench --backend carla` makes it from the server's map on first connect.*"
                                         r"python -m yawil\.bench\.carla_routes --xodr Town01\.xodr --town town01"):
        load_routes("town01", tmp_path / "carla")
    with pytest.raises(ValueError, match=r"yawil bench routes --town town01"):  # elsewhere: the embedded command
        load_routes("town01", tmp_path)


def test_timeout_reaches_the_client(server: FakeCarlaServer, tmp_path: Path) -> None:
    assert main([*RUN, "--condition", "new-town-weather", "--routes", "0", "--timeout", "3.5",
                 "--out", str(tmp_path / "r")]) == 0
    assert server.timeouts[0] == 3.5 and 3.5 in server.timeouts[-2:]  # the call timeout, map loads aside
    assert max(server.timeouts) >= 60.0  # the map load got its longer one
    with pytest.raises(SystemExit, match="yawil bench: timeout must be a positive number of seconds, got 0.0"):
        main([*RUN, "--condition", "new-town-weather", "--timeout", "0", "--out", str(tmp_path / "r0")])
