"""`yawil reproduce`: the stages of the paper's experiments, in order, with and without pretrained weights."""

from __future__ import annotations

from pathlib import Path

import pytest

from yawil.cli import main
from yawil.pipelines.reproduce import PROFILES, stages


def test_stages_cover_every_table(tmp_path: Path) -> None:
    names = [n for n, _ in stages(tmp_path, PROFILES["paper"], None)]
    assert names[0] == "collect" and names[-1] == "report"
    assert {"train_cil", "train_cilrs", "train_yilratt", "bench_expert", "bench_yilratt", "explain", "experiments"} <= set(names)
    assert "train_yilratt_pretrained" not in names
    with_weights = [n for n, _ in stages(tmp_path, PROFILES["paper"], "w.pth")]
    assert "train_yilratt_pretrained" in with_weights and "bench_yilratt_pretrained" in with_weights


def test_dry_run_prints_the_plan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["reproduce", "--profile", "paper", "--out", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "profile paper" in out and "stage train_yilratt" in out
    assert not (tmp_path / "stages").exists()


def test_missing_pretrained_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="nope.pth"):
        main(["reproduce", "--pretrained", str(tmp_path / "nope.pth"), "--out", str(tmp_path), "--dry-run"])
