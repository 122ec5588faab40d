"""The demo report from finished stages: a one-screen summary first, the zoo model's full provenance, no raw
markup in the HTML, captions under the figures, the budget of what ran."""

from __future__ import annotations

import json
import re
from pathlib import Path

from yawil.bench.records import PROTOCOL, EpisodeLog, check_run_info
from yawil.data.synthetic import write_synthetic_dataset
from yawil.pipelines.demo import DemoBudget, write_demo_report


def _results(folder: Path, label: str, oks: int, n: int = 4, task: str = "straight") -> None:
    check_run_info(folder, {"agent": label, "agent_options": {}, "label": label})
    with EpisodeLog(folder) as log:
        for cond in ("training", "new-town-weather"):
            for rid in range(n):
                ok = rid < oks
                log.append({"protocol": PROTOCOL, "suite": "corl2017", "task": task, "condition": cond,
                            "weather": "ClearNoon", "route_id": rid, "seed": 0, "success": ok,
                            "reason": None if ok else "collision_static", "km_driven": 0.2, "lane_opposite": 0,
                            "lane_offroad": 0, "red_lights": 0, "lights_passed": 1,
                            "trajectory": [[0, 0], [10, 0]], "route_xy": [[0, 0], [10, 0]]})


CARD = {"model_name": "yilratt", "steps_total": 1500, "commit": "0123456789abcdef", "eval100": {"successes": 89,
        "episodes": 100}, "drive": {"speed_control": "stop", "stop_release": 10.0}, "demo": {"successes": 8},
        "data": {"town": "town01", "weathers": "train", "frames": 20170, "seed": 0},
        "commands": ["yawil collect --out data/x", "yawil train --out runs/a", "yawil dagger --round0 runs/a/last.pt",
                     "yawil bench --preset eval100"]}


def demo_report(out: Path) -> tuple[DemoBudget, Path]:
    """A demo report of finished stages (synthetic data and records) in `out`: its budget and report.html."""
    budget = DemoBudget(tasks=("straight",))
    write_synthetic_dataset(out / "data" / "town01", episodes=2, frames=4, seed=0)
    _results(out / "results" / "expert", "expert", 4)
    _results(out / "results" / budget.baseline, budget.baseline, 3)
    _results(out / "results" / f"zoo-{budget.zoo_model}", f"zoo-{budget.zoo_model}", 4)
    _results(out / "results" / f"zoo-{budget.zoo_model}", f"zoo-{budget.zoo_model}", 1, 2, task="regular")
    report = write_demo_report(out, budget, {"collect": 60.0}, {budget.baseline: {"steps": 600, "epochs": 2,
                               "stopped_by": "max_steps"}}, CARD, "episode.gif", 100.0)
    return budget, report


def test_the_demo_report_says_what_ran_with_its_provenance(tmp_path: Path) -> None:
    budget, report = demo_report(tmp_path)
    card = CARD
    page = report.read_text(encoding="utf-8")
    text = re.sub(r"data:[^'\"]+", "", page)  # the images' bytes
    first = text.index("<table>")
    assert first < text.index("The whole loop")  # the summary comes first
    assert "<td>expert</td><td>the privileged expert</td><td>8</td><td>8</td>" in text
    assert f"<td>{budget.baseline}</td><td>trained in this run</td><td>6</td><td>8</td><td>ok</td>" in text
    # the zoo model's guard counts the card's episodes only; its traffic episodes are a row of their own
    assert f"<td>zoo-{budget.zoo_model}</td><td>zoo</td><td>8</td><td>8</td><td>ok</td>" in text
    assert f"<td>zoo-{budget.zoo_model}, in traffic (regular)</td><td>zoo</td><td>2</td><td>4</td>" in text
    for command in card["commands"]:  # every command of the zoo model, not only one
        assert command in text
    assert "**" not in text and "`" not in text  # no raw markdown in the HTML
    assert "--speed-control stop --stop-release 10.0" in text
    assert "<figcaption>Frames per road option and weather" in text  # figures carry captions
    assert "max_steps" not in text.split("<h2>Budget</h2>")[1].split("</table>")[0]  # no YILRatt trained here
    md = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert md.splitlines()[2].startswith("| agent |") and json.dumps(card["drive"]) not in md
