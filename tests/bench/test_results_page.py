"""docs/results.md from a manifest of committed records: every cell with its interval, the paper beside ours,
claims judged by the interval of the difference, bad manifests refused in one line naming the field."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from yawil.bench.records import PROTOCOL, EpisodeLog, check_run_info
from yawil.cli import main


def _folder(path: Path, label: str, task: str, oks: int, n: int, cond: str = "new-town-weather",
            seed: int = 0) -> None:
    check_run_info(path, {"agent": label, "agent_options": {}, "label": label})
    with EpisodeLog(path) as log:
        for rid in range(n):
            ok = rid < oks
            log.append({"protocol": PROTOCOL, "suite": "nocrash", "task": task, "condition": cond,
                        "weather": "WetCloudyNoon", "route_id": rid, "seed": seed, "success": ok,
                        "reason": None if ok else "collision_vehicle", "km_driven": 1.0, "lane_opposite": 0,
                        "lane_offroad": 0, "red_lights": 0, "lights_passed": 2})


def _manifest(tmp_path: Path, rows: list[dict[str, object]]) -> Path:
    path = tmp_path / "records" / "results.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps({"rows": rows}))
    return path


def _row(label: str, model: str, folder: str, role: str = "test", column: str | None = None) -> dict[str, object]:
    """A manifest row; a test row is its own table column unless `column` names another ("": none)."""
    row: dict[str, object] = {"label": label, "model": model, "training_seeds": 1, "role": role, "folder": folder,
                              "command": f"yawil bench --agent {label}"}
    column = label if column is None and role == "test" else column
    return {**row, "column": column} if column else row


def test_the_page_and_the_readme_block_come_from_the_records(tmp_path: Path) -> None:
    rec = tmp_path / "records"
    _folder(rec / "y", "y", "dense", 40, 50)
    _folder(rec / "c", "c", "dense", 10, 50)
    _folder(rec / "c2", "c2", "dense", 24, 50)
    manifest = _manifest(tmp_path, [_row("Y", "yilratt", "y"), _row("C", "cilrs", "c"), _row("C2", "cil", "c2")])
    readme = tmp_path / "README.md"
    readme.write_text("intro\n<!-- yawil results: headline (made by `yawil results`; edit records/results.json) -->"
                      "\nold\n<!-- yawil results: end -->\nrest\n")
    out = tmp_path / "results.md"
    assert main(["results", str(manifest), "--out", str(out), "--readme", str(readme)]) == 0
    page = out.read_text()
    assert "| Y | Nav. (Dense) | New Town02 & Weather | 40/50 = 80 % [67-89] | 76 ± 3.27 |" in page
    assert "| C | Nav. (Dense) | New Town02 & Weather | 10/50 = 20 % [11-33] | 34 ± 4.32 |" in page
    # +60 points with an interval above zero: held; the level claim is inside the interval: held
    assert "- **held**: YILRatt beats CILRS in traffic" in page and "+60 points [+42, +72]" in page
    assert "- **held**: YILRatt drives Nav. (Dense) in New Town02 & Weather at the paper's level" in page
    assert "- **not tested**: Attention helps generalisation" in page
    text = readme.read_text()
    assert "old" not in text and text.startswith("intro\n") and text.endswith("rest\n")
    assert "| Y | **40/50 = 80 % [67-89]** | 76 ± 3.27 | 1 |" in text


def test_a_difference_inside_the_uncertainty_is_not_established(tmp_path: Path) -> None:
    from yawil.bench.results_page import CLAIMS, judge, read_results_manifest

    rec = tmp_path / "records"
    _folder(rec / "y", "y", "regular", 12, 25)
    _folder(rec / "c", "c", "regular", 10, 25)
    rows, _, _ = read_results_manifest(_manifest(tmp_path, [_row("Y", "yilratt", "y"), _row("C", "cilrs", "c")]))
    status, evidence = judge(CLAIMS[0], rows)
    assert status == "not established" and "Nav. (Regular)" in evidence[0]


@pytest.mark.parametrize("change, text", [
    ({"model": "resnet"}, "model 'resnet'"),
    ({"role": "final"}, "role 'final'"),
    ({"training_seeds": "one"}, "'training_seeds' must be a int"),
    ({"folder": "missing"}, "no episodes.jsonl"),
    ({"extra": 1}, "unknown field(s) extra"),
    ({"column": ""}, "field 'column' must be a non-empty str"),
    ({"role": "selection"}, "only test rows are table columns"),
    ({"training_seed": -1}, "field 'training_seed' must be an int >= 0"),
    ({"training_seed": 0, "training_seeds": 3}, "a row with training_seed is one model"),
])
def test_a_bad_manifest_is_one_line_naming_the_field(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     change: dict[str, object], text: str) -> None:
    _folder(tmp_path / "records" / "y", "y", "dense", 1, 2)
    manifest = _manifest(tmp_path, [{**_row("Y", "yilratt", "y"), **change}])
    assert main(["results", str(manifest), "--out", str(tmp_path / "r.md")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "rows[0]" in line and text in line and not (tmp_path / "r.md").exists()


def test_a_column_pools_one_agents_runs_and_rows_without_one_are_listed_only(tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "records"
    _folder(rec / "yd", "yd", "dense", 40, 50)
    _folder(rec / "yr", "yr", "regular", 45, 50)
    _folder(rec / "old", "old", "dense", 5, 50)
    _folder(rec / "c", "c", "dense", 10, 50)
    rows = [_row("Y dense", "yilratt", "yd", column="YILRatt"), _row("Y regular", "yilratt", "yr", column="YILRatt"),
            _row("Y earlier", "yilratt", "old", column=""), _row("C", "cilrs", "c")]
    readme = tmp_path / "README.md"
    readme.write_text("<!-- yawil results: headline (made by `yawil results`; edit records/results.json) -->\n"
                      "<!-- yawil results: end -->\n")
    out = tmp_path / "results.md"
    assert main(["results", str(_manifest(tmp_path, rows)), "--out", str(out), "--readme", str(readme)]) == 0
    page = out.read_text()
    tables = page[page.index("## Table III"):page.index("## Beside the paper")]
    assert tables.count("New Town02 & Weather: YILRatt |") == 2  # one column for both runs, in III and IV
    assert "Y earlier" not in tables and "Y dense" not in tables
    assert "| Y earlier | Nav. (Dense) | New Town02 & Weather | 5/50 = 10 % [4-21] |" in page  # still beside the paper
    claims = page[page.index("## The paper's claims"):]
    assert "YILRatt 40/50" in claims and "Y earlier" not in claims
    assert "YILRatt: 45/50 = 90 % [79-96] against the paper's 76.66" in claims  # the column's Regular run
    head = readme.read_text()
    assert "| YILRatt | **40/50 = 80 % [67-89]**" in head and "Y earlier" not in head
    # two runs of one column in one cell, or a column of two families: refused in one line
    for bad in ([*rows[:2], _row("Y again", "yilratt", "old", column="YILRatt")],
                [*rows[:2], _row("C in Y", "cilrs", "c", column="YILRatt")]):
        assert main(["results", str(_manifest(tmp_path, bad)), "--out", str(tmp_path / "bad.md")]) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert "column 'YILRatt'" in line and not (tmp_path / "bad.md").exists()


def test_a_column_of_several_training_seeds_pools_them_and_shows_their_spread(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "records"
    for seed, oks in ((0, 30), (1, 35), (2, 40)):
        _folder(rec / f"c{seed}", f"c{seed}", "dense", oks, 50)
    rows = [{**_row(f"C seed {k}", "cilrs", f"c{k}", column="CILRS"), "training_seed": k} for k in range(3)]
    out = tmp_path / "results.md"
    assert main(["results", str(_manifest(tmp_path, rows)), "--out", str(out)]) == 0
    page = out.read_text()
    assert "| CILRS | Nav. (Dense) | New Town02 & Weather | 3 | seed 0: 30/50, seed 1: 35/50, seed 2: 40/50 | " \
           "70.0 ± 8.2 |" in page
    assert "| Nav. (Dense) | 70 [62-77] (1 seed) |" in page  # Table III pools the three models' 150 episodes
    # a seed's cell twice, or a column naming training seeds on some rows only: refused in one line
    for bad in ([*rows, {**rows[0], "label": "C again"}], [*rows, _row("C unseeded", "cilrs", "c0", column="CILRS")]):
        assert main(["results", str(_manifest(tmp_path, bad)), "--out", str(tmp_path / "bad.md")]) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert "column 'CILRS'" in line and not (tmp_path / "bad.md").exists()


def test_the_committed_page_and_readme_block_are_what_the_records_say(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/results.md and README's headline block are regenerated by `yawil results --readme README.md`."""
    import shutil

    root = Path(__file__).resolve().parents[2]
    shutil.copy(root / "README.md", tmp_path / "README.md")
    monkeypatch.chdir(root)
    assert main(["results", "--out", str(tmp_path / "results.md"), "--readme", str(tmp_path / "README.md")]) == 0
    assert (tmp_path / "results.md").read_text() == (root / "docs" / "results.md").read_text(), \
        "docs/results.md is stale: run `yawil results --readme README.md`"
    assert (tmp_path / "README.md").read_text() == (root / "README.md").read_text(), \
        "README's headline block is stale: run `yawil results --readme README.md`"


def test_the_heat_map_claims_follow_the_rules() -> None:
    """Held: lift's interval above 1 (and, for following a class, above the layer's prior); synthetic tables."""
    from yawil.bench.results_page import attention_claims

    def row(layer: str, situation: str, cells: dict[str, tuple[float, float, float, float]]) -> dict[str, object]:
        return {"layer": layer, "situation": situation, "lift": {c: v[0] for c, v in cells.items()},
                "lift_ci95": {c: [v[1], v[2]] for c, v in cells.items()}, "prior": {c: v[3] for c, v in cells.items()}}

    layers = ["attention layer 1", "attention layer 2", "attention layer 3"]
    detail = {c: (1.5, 1.2, 1.8, 1.0) for c in ("vehicle", "pedestrian", "pole", "lights")}
    doc = {"layers": layers, "rows": [
        row(layers[0], "all", {"passable": (2.0, 1.5, 2.5, 1.9)}),
        row(layers[1], "all", {"lane_marking": (0.9, 0.5, 1.3, 1.0)}),
        row(layers[2], "all", detail),
        row(layers[1], "brake_vehicle", {"vehicle": (2.0, 1.4, 2.6, 0.5)}),  # follows the obstacle
        row(layers[0], "brake_pedestrian", {"pedestrian": (3.0, 2.0, 4.0, 3.5)}),  # above 1, not above its prior
    ]}
    got = {text.split(" (")[0]: status for status, text, _ in attention_claims(doc)}
    assert got["Layer 1 attends to the passable area"] == "held"
    assert got["Layer 2 attends to lane lines"] == "not established"
    assert got["Layer 3 attends to details"] == "held"
    assert got["When the car brakes, the maps attend to the obstacle"] == "mixed (held, not held)"
    doc["rows"][2] = row(layers[2], "all", {**detail, "pole": (1.1, 1.05, 1.2, 1.3)})
    assert attention_claims(doc)[2][0] == "not held"


def test_the_page_replaces_only_its_own_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _folder(tmp_path / "records" / "y", "y", "dense", 1, 2)
    manifest = _manifest(tmp_path, [_row("Y", "yilratt", "y")])
    (tmp_path / "notes.md").write_text("a user's notes")
    assert main(["results", str(manifest), "--out", str(tmp_path / "notes.md")]) == 2
    assert "--force" in capsys.readouterr().err and (tmp_path / "notes.md").read_text() == "a user's notes"
    (tmp_path / "records" / "y" / ".yawil.lock").write_text("")  # a results folder as `yawil bench` leaves it
    (tmp_path / "records" / "y" / "page.md").write_text("x")
    assert main(["results", str(manifest), "--out", str(tmp_path / "records" / "y" / "page.md"), "--force"]) == 2
    assert main(["results", str(manifest), "--out", str(tmp_path / "page.md")]) == 0
    assert main(["results", str(manifest), "--out", str(tmp_path / "page.md")]) == 0  # its own page, regenerated


def test_a_claim_compares_the_episodes_both_rows_drove(tmp_path: Path) -> None:
    """A row that also drove more seeds of an easy task must not win on them: only shared episodes count."""
    from yawil.bench.results_page import CLAIMS, judge, read_results_manifest, shared_episodes

    rec = tmp_path / "records"
    _folder(rec / "c", "c", "regular", 10, 25)
    _folder(rec / "r", "r", "regular", 10, 25)
    _folder(rec / "c", "c", "regular", 25, 25, seed=1)  # 25 more episodes, all successful, only in CIL's run
    rows, _, _ = read_results_manifest(_manifest(tmp_path, [_row("C", "cil", "c"), _row("R", "cilrs", "r")]))
    assert shared_episodes(rows[0], rows[1], "regular", "new-town-weather") == ((10, 25), (10, 25))
    claim = next(c for c in CLAIMS if (c.a, c.b) == ("cil", "cilrs"))
    status, evidence = judge(claim, rows)  # pooled, CIL would read 35/50 against 10/25 and be "held"
    assert status == "not established" and "10/25" in evidence[0] and "35/50" not in evidence[0]
