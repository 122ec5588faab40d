"""`yawil report` on synthetic results folders: tables shaped as the paper's, Markdown and HTML."""

from __future__ import annotations

import json
from pathlib import Path

from yawil.bench.records import EpisodeLog, check_run_info
from yawil.bench.report import load_results, success_table, summary_table, violations_table, write_report
from yawil.cli import main


def _write(folder: Path, label: str, ok_by_seed: dict[str, list[int]]) -> None:
    check_run_info(folder, {"agent": label, "agent_options": {}, "label": label})
    with EpisodeLog(folder) as log:
        for cond in ("training", "new-town-weather"):
            for task, oks in ok_by_seed.items():
                for seed, n_ok in enumerate(oks):
                    for rid in range(4):
                        ok = rid < n_ok
                        log.append({
                            "suite": "nocrash", "task": task, "condition": cond, "route_id": rid, "seed": seed,
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
    assert t3.rows[0] == ["Straight", "100", "75", "100", "75"]  # best of 5 seeds
    assert t3.rows[1][0] == "Nav. (Dense)" and t3.rows[1][1] == "75.00 ± 20.41"
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
    summary = json.loads(paths["summary.json"].read_text())
    assert summary["tables"][0]["rows"][0][0] == "Straight"
    assert (tmp_path / "rep" / "trajectories_training.png").stat().st_size > 1000


def test_cli_report(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    a = tmp_path / "a"
    _write(a, "expert", {"regular": [4, 4, 2]})
    assert main(["report", str(a), "--out", str(tmp_path / "r"), "--trajectory", "training=regular/1/0"]) == 0
    assert "Nav. (Regular)" in capsys.readouterr().out
    assert (tmp_path / "r" / "report.html").exists()
