"""Stage markers of the long jobs: a finished stage is skipped, an unfinished or broken one is not taken as done."""

from __future__ import annotations

from pathlib import Path

import pytest

from yawil.stages import read_marker, run_stage


def test_stage_runs_once_and_records_its_result(tmp_path: Path) -> None:
    calls: list[int] = []
    logs: list[str] = []
    marker = tmp_path / "stages" / "train.json"

    def work() -> dict[str, int]:
        calls.append(1)
        return {"steps": 5}

    first = run_stage(marker, work, logs.append, "train")
    again = run_stage(marker, work, logs.append, "train")
    assert calls == [1] and first == again and first["steps"] == 5 and first["seconds"] >= 0
    assert logs == ["train ...", "train: done before, skipped"]
    assert not [p for p in marker.parent.iterdir() if p.name != "train.json"]  # no temporary file left


def test_failed_stage_leaves_no_marker(tmp_path: Path) -> None:
    marker = tmp_path / "collect.json"

    def boom() -> None:
        raise RuntimeError("crashed half-way")

    with pytest.raises(RuntimeError):
        run_stage(marker, boom, print, "collect")
    assert read_marker(marker) is None
    assert run_stage(marker, lambda: None, print, "collect")["seconds"] >= 0  # runs again, now done


def test_broken_marker_is_named(tmp_path: Path) -> None:
    marker = tmp_path / "bench.json"
    marker.write_text("{not json")
    with pytest.raises(ValueError, match="bench.json.*delete it"):
        read_marker(marker)
    marker.write_text("[1, 2]")
    with pytest.raises(ValueError, match="JSON object"):
        read_marker(marker)
