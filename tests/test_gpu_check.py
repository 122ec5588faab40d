"""benchmarks/gpu_check.py, the GPU recipe's prepared check: refused in one line without CUDA, and its CPU run
at toy sizes goes end to end (collect, train with --data-on-device, a benchmark slice) and prints its table."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "gpu_check.py"


def _script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gpu_check", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_without_cuda_it_says_so_in_one_line(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert _script().main([]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("gpu_check: --device cuda: torch sees no CUDA device") and "\n" not in err


@pytest.mark.slow
def test_the_tiny_cpu_run_goes_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    assert _script().main(["--device", "cpu", "--tiny", "--keep", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and not line.startswith("| step")]
    assert [r.split(" ")[1] for r in rows] == ["collect", "train", "bench"]
    assert "samples/s" in rows[1] and "episodes/s" in rows[2] and "1 episode in" in rows[2]
    assert (tmp_path / "run" / "best.pt").is_file() and (tmp_path / "results" / "episodes.jsonl").is_file()
