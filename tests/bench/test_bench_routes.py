"""The committed route files: protocol rules, reachability with the current planner, episode lists."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from yawil.bench.routegen import classify, route_turns, validate_with_planner
from yawil.bench.suites import ROUTES_DIR, episodes, get_task, load_routes, parse_range
from yawil.sim.types import Route
from yawil.sim.weather import TEST_WEATHERS, TRAIN_WEATHERS


@pytest.mark.parametrize("town", ["town01", "town02", "square"])
def test_committed_routes_are_valid_and_reachable(town: str) -> None:
    lists = load_routes(town)  # protocol rules: counts, ids, minimum lengths, turn structure
    n = validate_with_planner(town)  # re-planned: reachable, same length and turns
    assert n == sum(len(v) for v in lists.values())


def test_protocol_lengths_and_structure() -> None:
    assert min(r.length_m for r in load_routes("town01")["navigation"]) >= 1000.0
    assert min(r.length_m for r in load_routes("town02")["navigation"]) >= 300.0
    for town in ("town01", "town02"):
        lists = load_routes(town)
        assert all(not {"LEFT", "RIGHT"} & set(r.turns) for r in lists["straight"])
        assert all(sum(t in ("LEFT", "RIGHT") for t in r.turns) == 1 for r in lists["one_turn"])
    square = load_routes("square")["square"]
    kinds = [r.kind.split(":")[0] for r in square]
    assert len(square) == 32 and (kinds.count("corner"), kinds.count("tjunction"), kinds.count("crossing")) == (8, 16, 8)


def _route(yaw: list[float], options: list[int]) -> Route:
    n = len(yaw)
    return Route(xy=np.stack([np.arange(n, dtype=float), np.zeros(n)], 1), options=np.array(options, np.int8),
                 lane_yaw=np.array(yaw))


def test_classify_rules() -> None:
    q = np.pi / 2
    assert classify(_route([0, 0, 0, 0], [4, 3, 3, 4])) == ("straight", ("STRAIGHT",))
    assert classify(_route([0, 0.2, q, q], [4, 1, 1, 4]))[0] == "one_turn"
    assert classify(_route([0, q / 2, q, q], [4, 4, 4, 4]))[0] is None  # a lane-follow corner is not straight
    assert classify(_route([0, q, q, 2 * q, 2 * q], [1, 1, 4, 1, 4]))[0] is None  # two turns
    assert classify(_route([0, q, q, 2 * q], [4, 1, 4, 4]))[0] is None  # a corner after the turn
    assert [t[0] for t in route_turns(_route([0] * 6, [3, 3, 4, 2, 2, 1]))] == ["STRAIGHT", "RIGHT", "LEFT"]


def _copy(tmp_path: Path) -> Path:
    for p in ROUTES_DIR.glob("*.json"):
        shutil.copy(p, tmp_path / p.name)
    return tmp_path


def test_bad_route_files_name_the_problem(tmp_path: Path) -> None:
    folder = _copy(tmp_path)
    path = folder / "town02.json"
    doc = json.loads(path.read_text())
    doc["routes"]["navigation"][3]["length_m"] = 120.0
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"navigation\[3\].*minimum 300"):
        load_routes("town02", folder)
    doc["routes"]["navigation"][3]["length_m"] = 400.0
    doc["routes"]["navigation"][3]["goal"] = {"x": 1.0, "y": "a", "yaw": 0}
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"goal\.y: expected a finite number"):
        load_routes("town02", folder)
    doc["routes"]["navigation"][3]["goal"] = {"x": 1.0, "y": 2.0, "yaw": 0}
    doc["routes"]["straight"] = doc["routes"]["straight"][:24]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="24 routes, the protocol needs 25"):
        load_routes("town02", folder)
    with pytest.raises(ValueError, match="no route file"):
        load_routes("town09", folder)


def test_validation_catches_a_route_the_planner_no_longer_matches(tmp_path: Path) -> None:
    folder = _copy(tmp_path)
    path = folder / "town01.json"
    doc = json.loads(path.read_text())
    doc["routes"]["one_turn"][0]["length_m"] += 25.0
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"one_turn\[0\]: planned length"):
        validate_with_planner("town01", folder)


def test_episode_lists_follow_the_protocol() -> None:
    eps = episodes("nocrash", conditions=["training"])
    # every route in each of the 4 training weathers: Empty static 25 x 4 x 5 seeds; Regular, Dense 25 x 4 x 3
    assert len(eps) == 25 * 4 * 5 + 2 * 25 * 4 * 3
    assert len({e.key for e in eps}) == len(eps)
    reg = [e for e in eps if e.task == "regular"]
    assert {(e.vehicles, e.pedestrians) for e in reg} == {(30, 10)}
    assert {(e.vehicles, e.pedestrians) for e in eps if e.task == "dense"} == {(50, 30)}
    assert [(e.route_id, e.weather) for e in reg[:5]] == [
        (0, "ClearNoon"), (0, "WetNoon"), (0, "HardRainNoon"), (0, "ClearSunset"), (1, "ClearNoon")]
    # the weathers of one route and seed share the world seed: weather is their only difference
    assert len({e.world_seed for e in reg[:4]}) == 1 and reg[4].world_seed != reg[0].world_seed
    nt = episodes("corl2017", conditions=["new-town-weather"], tasks=["straight"], routes="0:3", seeds=2)
    assert [(e.route_id, e.seed, e.weather, e.town) for e in nt][:3] == [
        (0, 0, "WetCloudyNoon", "town02"), (0, 0, "SoftRainSunset", "town02"), (1, 0, "WetCloudyNoon", "town02")]
    assert len(nt) == 12
    # each suite's own time budget: CoRL2017 10 km/h + 10 s, NoCrash 5 km/h + 20 s
    assert nt[0].timeout_s == pytest.approx(nt[0].route.length_m / 1000 / 10 * 3600 + 10)
    assert reg[0].timeout_s == pytest.approx(reg[0].route.length_m / 1000 / 5 * 3600 + 20)
    # the cycle rule (preset eval100): route i in weather i mod n, a quarter of the episodes
    cyc = episodes("corl2017", conditions=["new-town-weather"], tasks=["straight"], routes="0:3", seeds=2,
                   weather_rule="cycle")
    assert [(e.route_id, e.weather) for e in cyc][:3] == [
        (0, "WetCloudyNoon"), (1, "SoftRainSunset"), (2, "WetCloudyNoon")]
    assert get_task("nav").name == "navigation"
    with pytest.raises(ValueError, match="not in suite"):
        episodes("corl2017", tasks=["dense"])
    with pytest.raises(ValueError, match="unknown condition"):
        episodes("nocrash", conditions=["moon"])
    with pytest.raises(ValueError, match="unknown weather rule"):
        episodes("nocrash", weather_rule="some")


def test_published_suites_have_their_densities_and_conditions() -> None:
    """NoCrash as published (per-town densities, four conditions) and CoRL2017's Navigation Dynamic."""
    eps = episodes("nocrash-original", routes="0:1", seeds=1)
    traffic = {(e.task, e.condition): (e.vehicles, e.pedestrians) for e in eps}
    assert traffic[("nocrash_dense", "training")] == (100, 250)
    assert traffic[("nocrash_dense", "new-weather")] == (100, 250)
    assert traffic[("nocrash_dense", "new-town")] == (70, 150)
    assert traffic[("nocrash_regular", "new-town-weather")] == (15, 50)
    assert traffic[("empty", "new-town")] == (0, 0)
    assert {e.condition for e in eps} == {"training", "new-weather", "new-town", "new-town-weather"}
    assert {(e.condition, e.town, e.weather) for e in eps if e.task == "empty"} == {
        *(("training", "town01", w) for w in TRAIN_WEATHERS), *(("new-weather", "town01", w) for w in TEST_WEATHERS),
        *(("new-town", "town02", w) for w in TRAIN_WEATHERS),
        *(("new-town-weather", "town02", w) for w in TEST_WEATHERS)}
    dyn = episodes("corl2017", tasks=["nav_dynamic"], routes="0:1", seeds=1)
    assert {(e.town, e.vehicles, e.pedestrians) for e in dyn} == {("town01", 20, 50), ("town02", 15, 50)}
    assert all(e.timeout_s == pytest.approx(e.route.length_m / 1000 / 10 * 3600 + 10) for e in dyn)


def test_the_selection_set_has_the_test_towns_density_in_the_training_town() -> None:
    """`selection` drives town01 only, with Nav. (Dense)'s town02 traffic scaled by the towns' lane and walkway
    lengths: the test cell's density without its town (the figures in the task's comment are these)."""
    from yawil.sim.town.map.town import get_town

    eps = episodes("selection", routes="0:25", seeds=1, weather_rule="cycle")
    assert len(eps) == 25 and {(e.town, e.condition) for e in eps} == {("town01", "training")}
    road = {t: sum(lane.length for lane in get_town(t).lanes.lanes if lane.kind == "road") for t in ("town01", "town02")}
    walk = {t: sum(w.edge_length(e) for e in range(len(w.edge_list))) for t in ("town01", "town02")
            for w in [get_town(t).walkways]}
    dense = get_task("dense")
    assert {(e.vehicles, e.pedestrians) for e in eps} == {
        (round(dense.vehicles * road["town01"] / road["town02"]), round(dense.pedestrians * walk["town01"] / walk["town02"]))}
    with pytest.raises(ValueError, match="condition"):
        episodes("selection", ["new-town-weather"], routes="0:1", seeds=1)


def test_parse_range() -> None:
    assert parse_range("0:5", 25) == [0, 1, 2, 3, 4]
    assert parse_range("3,7", 25) == [3, 7]
    assert parse_range(None, 3) == [0, 1, 2]
    with pytest.raises(ValueError, match="outside"):
        parse_range("30", 25)
    with pytest.raises(ValueError, match="slice"):
        parse_range("a:b", 25)
    with pytest.raises(ValueError, match="selects no route"):
        parse_range("5:2", 25)
