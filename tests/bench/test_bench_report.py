"""`yawil report` on synthetic results folders: tables shaped as the paper's, Markdown and HTML, summary.json
as numbers, what made the report, file modes."""

from __future__ import annotations

import json
import os
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from yawil import __version__
from yawil.bench.metrics import FAILURE_REASONS
from yawil.bench.records import PROTOCOL, EpisodeLog, check_run_info
from yawil.bench.report import (
    load_results,
    success_table,
    summary_table,
    violations_table,
    weather_table,
    write_report,
)
from yawil.cli import main
from yawil.fileio import default_file_mode, write_atomic
from yawil.provenance import git_commit, provenance


@pytest.fixture
def umask_022() -> Iterator[None]:
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


def _write(folder: Path, label: str, ok_by_seed: dict[str, list[int]]) -> None:
    check_run_info(folder, {"agent": label, "agent_options": {}, "label": label})
    with EpisodeLog(folder) as log:
        for cond in ("training", "new-town-weather"):
            for task, oks in ok_by_seed.items():
                for seed, n_ok in enumerate(oks):
                    for rid in range(4):
                        ok = rid < n_ok
                        log.append({
                            "protocol": PROTOCOL, "suite": "nocrash", "task": task, "condition": cond,
                            "weather": "ClearNoon", "route_id": rid, "seed": seed,
                            "success": ok, "reason": None if ok else "collision_vehicle", "km_driven": 0.5,
                            "lane_opposite": 1, "lane_offroad": 0, "red_lights": seed, "lights_passed": 4,
                            "trajectory": [[0, 0], [10, 0], [10, 10]], "route_xy": [[0, 0], [10, 0], [10, 12]],
                        })


def test_tables_and_files(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, "expert", {"straight": [4, 3, 4, 4, 4], "dense": [4, 3, 2]})
    _write(b, "yilratt", {"straight": [1, 2, 3, 2, 1], "dense": [0, 1, 2]})
    sets = [load_results(a), load_results(b)]
    t3 = success_table(sets)
    assert t3.header[1:] == [
        "Training Conditions: expert", "Training Conditions: yilratt",
        "New Town02 & Weather: expert", "New Town02 & Weather: yilratt",
    ]
    # best of 5 seeds, then the Wilson interval of the pooled episodes: 19 of 20 and 9 of 20
    assert t3.rows[0] == ["Straight", "100 [76-99]", "75 [26-66]", "100 [76-99]", "75 [26-66]"]
    assert t3.rows[1][0] == "Nav. (Dense)" and t3.rows[1][1] == "75.00 ± 20.41 [47-91]"  # 9 of 12
    t4 = violations_table(sets)
    lane_dense = [r for r in t4.rows if r[0].startswith("Lane") and r[1] == "Nav. (Dense)"][0]
    assert lane_dense[2] == "2.00 ± 0.00"  # 1 violation per 0.5 km, successful episodes only
    light_dense_b = [r for r in t4.rows if r[0].startswith("Traffic") and r[1] == "Nav. (Dense)"][0][3]
    assert light_dense_b == "0.38 ± 0.12"  # seed 0: no success, undefined; seeds 1, 2: 0.25, 0.5
    summ = summary_table(sets)
    # yilratt: 2 x (9 of 20 straight + 3 of 12 dense) = 24 of 64; its violations over the successful ones
    assert summ.rows[1][:3] == ["yilratt", "64", "24"] and summ.rows[1][-2] == "2.00"
    from yawil.bench.metrics import FAILURE_REASONS

    assert summ.rows[1][3 + FAILURE_REASONS.index("collision_vehicle")] == "40"  # every failure here is one
    paths = write_report([a, b], tmp_path / "rep")
    md = paths["report.md"].read_text()
    assert "Summary over all episodes" in md
    assert "Table III" in md and "Table IV" in md and "success.png" in md
    page = paths["report.html"].read_text()
    assert page.count("data:image/png;base64,") >= 2 and "<table>" in page and "src='success.png'" not in page
    assert (tmp_path / "rep" / "trajectories_training.png").stat().st_size > 1000


def test_weather_table_splits_each_condition_by_weather(tmp_path: Path) -> None:
    folder = tmp_path / "a"
    check_run_info(folder, {"agent": "yilratt", "agent_options": {}, "label": "yilratt"})
    with EpisodeLog(folder) as log:
        # training: 3 of 4 at ClearNoon, 1 of 4 at ClearSunset (3 static collisions); new town: one weather
        for weather, cond, oks in (("ClearSunset", "training", [1, 0, 0, 0]), ("ClearNoon", "training", [1, 1, 1, 0]),
                                   ("SoftRainSunset", "new-town-weather", [0, 1])):
            for rid, ok in enumerate(oks):
                log.append({"protocol": PROTOCOL, "suite": "nocrash", "task": "straight", "condition": cond,
                            "weather": weather, "route_id": rid, "seed": 0, "success": bool(ok),
                            "reason": None if ok else "collision_static", "km_driven": 0.2,
                            "lane_opposite": 0, "lane_offroad": 0, "red_lights": 0, "lights_passed": 0})
    table = weather_table([load_results(folder)])
    static = 6 + FAILURE_REASONS.index("collision_static")
    rows = [(r[0], r[1], r[3], r[4], r[5], r[static]) for r in table.rows]
    assert rows == [  # the condition's own weather order (ClearNoon first), then the new town
        ("Training Conditions", "ClearNoon", "4", "3", "75.0", "1"),
        ("Training Conditions", "ClearSunset", "4", "1", "25.0", "3"),
        ("New Town02 & Weather", "SoftRainSunset", "2", "1", "50.0", "1"),
    ]
    assert table.records[1] == {"condition": "training", "weather": "ClearSunset", "agent": "yilratt", "episodes": 4,
                                "success": 1, "failures": {k: 3 * (k == "collision_static") for k in FAILURE_REASONS}}
    summary = json.loads(write_report([folder], tmp_path / "rep")["summary.json"].read_text(encoding="utf-8"))
    assert [r["weather"] for r in summary["weathers"]["rows"]] == ["ClearNoon", "ClearSunset", "SoftRainSunset"]


def test_summary_json_holds_numbers(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, "expert", {"straight": [4, 3, 4, 4, 4], "dense": [4, 3, 2]})
    _write(b, "yilratt", {"straight": [1, 2, 3, 2, 1], "dense": [0, 1, 2]})
    paths = write_report([a, b], tmp_path / "rep")
    text = paths["summary.json"].read_text(encoding="utf-8")
    assert "NaN" not in text  # strict JSON: an undefined figure is null
    summary = json.loads(text)
    rows = json.dumps([summary[k]["rows"] for k in ("success", "violations", "outcomes", "summary")])
    assert "±" not in rows and "n/a" not in rows  # numbers, not the formatted cells
    assert summary["results"] == [
        {"agent": "expert", "folder": str(a), "episodes": 64},
        {"agent": "yilratt", "folder": str(b), "episodes": 64},
    ]
    cells = {(r["task"], r["condition"], r["agent"]): r for r in summary["success"]["rows"]}
    straight = cells["straight", "training", "expert"]
    assert straight["over_seeds"] == "best" and straight["success_pct"]["value"] == 100.0
    assert straight["success_pct"]["std"] is None and straight["success_pct"]["n_seeds"] == 5
    dense = cells["dense", "new-town-weather", "expert"]["success_pct"]
    assert dense["value"] == pytest.approx(75.0) and dense["std"] == pytest.approx(20.412, abs=1e-3)
    assert dense["per_seed"] == [100.0, 75.0, 50.0]
    viol = {(r["task"], r["condition"], r["agent"]): r for r in summary["violations"]["rows"]}
    lights = viol["dense", "training", "yilratt"]["red_light_ratio"]
    assert lights["per_seed"][0] is None  # seed 0: no successful episode, undefined (null, not NaN)
    assert lights["value"] == pytest.approx(0.375)
    assert viol["dense", "training", "expert"]["lane_violations_per_km"]["value"] == pytest.approx(2.0)
    yil = summary["summary"]["rows"][1]
    assert yil["agent"] == "yilratt" and yil["episodes"] == 64 and yil["success"] == 24
    assert yil["failures"]["collision_vehicle"] == 40 and yil["lane_violations_per_km"] == pytest.approx(2.0)
    outcome = summary["outcomes"]["rows"][0]
    assert isinstance(outcome["episodes"], int) and outcome["km_driven"] == pytest.approx(outcome["episodes"] * 0.5)
    assert summary["plots"][0] == "success.png"
    assert "Table III" in summary["success"]["title"] and summary["success"]["note"]


def test_reports_say_what_made_them(tmp_path: Path) -> None:
    a = tmp_path / "a"
    _write(a, "expert", {"regular": [4, 4, 2]})
    command = "yawil report a --out 'r e p'"
    paths = write_report([a], tmp_path / "rep", command=command)
    prov = json.loads(paths["summary.json"].read_text())["provenance"]
    assert prov["yawil_version"] == __version__ and prov["command"] == command
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", prov["date_utc"])
    assert prov["git_commit"] == git_commit()
    date = prov["date_utc"].replace("T", " ").rstrip("Z")
    md = paths["report.md"].read_text()
    assert f"Made by yawil {__version__} (commit {prov['git_commit']}) on {date} UTC with `{command}`." in md
    page = paths["report.html"].read_text()
    assert f"yawil {__version__}" in page and f"{date} UTC" in page and prov["git_commit"] in page
    assert "<code>yawil report a --out &#39;r e p&#39;</code>" in page  # escaped by the template


def test_html_has_no_markdown_and_escapes(tmp_path: Path) -> None:
    a = tmp_path / "a"
    _write(a, "<b>agent</b> & co", {"regular": [4, 4, 2]})
    page = write_report([a], tmp_path / "rep", command="yawil report a")["report.html"].read_text()
    assert "`" not in page
    assert "<b>agent</b>" not in page and "&lt;b&gt;agent&lt;/b&gt; &amp; co" in page
    assert f"<code>{a}</code>" in page
    assert page.startswith("<!DOCTYPE html>") and page.count("<table>") == 5


def test_git_commit(tmp_path: Path) -> None:
    commit = git_commit()
    assert commit == "unknown" or re.fullmatch(r"[0-9a-f]{40}(-dirty)?", commit)
    (tmp_path / "__init__.py").write_text("")
    assert git_commit(tmp_path) == "unknown"  # not a git checkout
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    try:
        subprocess.run([*git, "init", "-q"], check=True, capture_output=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("no usable git")
    assert git_commit(tmp_path) == "unknown"  # __init__.py not tracked: not run from this checkout
    subprocess.run([*git, "add", "__init__.py"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "x"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    assert git_commit(tmp_path) == head
    (tmp_path / "__init__.py").write_text("x = 1\n")
    assert git_commit(tmp_path) == f"{head}-dirty"


def test_provenance_command_default() -> None:
    prov = provenance()
    assert prov["command"] and prov["command"] != "unknown"


def test_outputs_readable_by_others(tmp_path: Path, umask_022: None) -> None:
    a = tmp_path / "a"
    _write(a, "expert", {"regular": [4, 4, 2]})
    paths = write_report([a], tmp_path / "rep", command="yawil report a")
    assert {"report.md", "report.html", "summary.json", "success.png"} <= set(paths)
    for p in paths.values():
        assert p.stat().st_mode & 0o777 == 0o644, p
    assert not [p for p in (tmp_path / "rep").iterdir() if p.name.startswith(".")]  # no temporary left


def test_write_atomic_mode(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        assert default_file_mode() == 0o640
        p = write_atomic(tmp_path / "sub" / "f.txt", "é")
        assert p.read_bytes() == "é".encode() and p.stat().st_mode & 0o777 == 0o640
        os.umask(0o022)
        assert default_file_mode() == 0o644
        write_atomic(p, b"\x00")
        assert p.read_bytes() == b"\x00" and p.stat().st_mode & 0o777 == 0o644
    finally:
        os.umask(old)


def test_cli_report(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    a = tmp_path / "a"
    _write(a, "expert", {"regular": [4, 4, 2]})
    assert main(["report", str(a), "--out", str(tmp_path / "r"), "--trajectory", "training=regular/1/0"]) == 0
    assert "Nav. (Regular)" in capsys.readouterr().out
    assert (tmp_path / "r" / "report.html").exists()


def test_trajectory_episode_names_its_weather() -> None:
    """Every route is driven in every weather: the plotted episode is one weather's, chosen or the first."""
    from yawil.bench.report import HARDEST_FIRST, choose_episodes
    from yawil.bench.suites import TASKS

    assert set(HARDEST_FIRST) == set(TASKS)  # a folder of any task gets its trajectory plot
    assert choose_episodes([], "training", "dense/WetNoon/3/0") == ("dense", "WetNoon", 3, 0)
    assert choose_episodes([], "training", "dense/3/0") == ("dense", None, 3, 0)
    with pytest.raises(ValueError, match="task/weather/route/seed"):
        choose_episodes([], "training", "dense/3")


def test_short_seeds_names_a_seed_stopped_part_way() -> None:
    """A protocol cell whose seed holds fewer episodes than the protocol drives says so, per model of a pooled
    column (a model that drove none of a seed the others drove counts 0); a whole seed is not named."""
    from yawil.bench.report import short_seeds
    from yawil.bench.suites import episodes

    full = len(episodes("nocrash", ["new-town-weather"], ["dense"], seeds=1))
    assert full == 50  # 25 routes in the condition's 2 weathers

    def recs(agent: str, counts: dict[int, int]) -> list[dict[str, object]]:
        return [{"suite": "nocrash", "task": "dense", "condition": "new-town-weather", "seed": s, "agent": agent}
                for s, n in counts.items() for _ in range(n)]

    assert short_seeds(recs("runs/x/a/train/round_03/last.pt", {0: 50, 1: 50})) == []
    assert short_seeds(recs("runs/x/a/train/round_03/last.pt", {0: 50, 1: 48})) == ["seed 1: 48 of 50"]
    pooled = recs("runs/x/a/train/round_03/last.pt", {0: 50, 1: 50, 2: 50}) + recs("runs/x/b/train/round_03/last.pt",
                                                                                  {0: 50, 1: 48})
    assert short_seeds(pooled) == ["seed 1 of b: 48 of 50", "seed 2 of b: 0 of 50"]
    zoo = recs("zoo:m", {0: 50}) + recs("runs/y/last.pt", {0: 10})
    assert short_seeds(zoo) == ["seed 0 of y: 10 of 50"]
    assert short_seeds([{"suite": "nosuch", "task": "dense", "condition": "training", "seed": 0}]) == []
