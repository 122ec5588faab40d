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


def test_the_gpu_profile_is_the_papers_scale_on_one_gpu_node(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Resolved without running: every core collects and drives, YILRatt trains on CUDA with bf16, channels_last
    and the data on the GPU at the paper's batch and epochs, budgets in frames and epochs, agents on CUDA."""
    import torch

    from yawil.pipelines.reproduce import agent_spec, train_config

    monkeypatch.setattr("os.cpu_count", lambda: 16)
    p = PROFILES["gpu"]
    assert (p.frames, p.workers(p.collect_workers), p.workers(p.bench_workers), p.max_minutes) == (200_000, 16, 16, None)
    cfg = train_config(tmp_path, p, "yilratt", "yilratt", None)
    assert (cfg.device, cfg.precision, cfg.channels_last, cfg.data_on_device) == ("cuda", "bf16", "on", True)
    assert (cfg.batch_size, cfg.epochs, cfg.max_minutes, cfg.max_steps, cfg.workers) == (512, 100, None, None, 16)
    assert agent_spec(tmp_path, p, "yilratt").device == "cuda"
    assert agent_spec(tmp_path, p, "yilratt").agent == str(tmp_path / "runs" / "yilratt" / "best.pt")
    assert train_config(tmp_path, p, "cil", "cil", None, device="cpu").device == "cpu"  # --device overrides
    quick = train_config(tmp_path, PROFILES["quick"], "cil", "cil", None)  # the other profiles as they were
    assert (quick.device, quick.data_on_device, quick.workers, agent_spec(tmp_path, PROFILES["quick"], "cil").device) == (
        "auto", False, 1, "cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="--profile gpu trains or drives on CUDA, but torch sees no CUDA device"):
        main(["reproduce", "--profile", "gpu", "--out", str(tmp_path)])
    assert not (tmp_path / "stages").exists()
