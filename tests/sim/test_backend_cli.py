"""`--backend carla` reaches the CARLA backend from the collect and bench commands (no server here:
the clear error of an absent server proves the wiring), and the runner retries simulator errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from yawil.bench.runner import AgentSpec, run_benchmark
from yawil.bench.suites import episodes
from yawil.cli import main
from yawil.sim import SimulatorError, make_world


def test_collect_with_carla_backend_names_the_absent_server(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Checked before any folder is made (it was a worker's traceback after the dataset folder existed)."""
    assert main(["collect", "--backend", "carla", "--host", "127.0.0.1", "--port", "2999", "--timeout", "2",
                 "--episodes", "1", "--out", str(tmp_path / "d"), "--quiet"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "127.0.0.1:2999" in line and not (tmp_path / "d").exists()
    assert main(["collect", "--backend", "carla", "--town", "square", "--episodes", "1",
                 "--out", str(tmp_path / "d")]) == 2
    assert "embedded backend" in capsys.readouterr().err and not (tmp_path / "d").exists()


def test_carla_backend_needs_one_server_per_worker(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="--workers 2: give one server per worker with --carla-servers"):
        main(["collect", "--backend", "carla", "--workers", "2", "--episodes", "1", "--out", str(tmp_path / "d")])
    with pytest.raises(SystemExit, match="--workers 2: give one server per worker with --carla-servers"):
        main(["bench", "--backend", "carla", "--workers", "2", "--out", str(tmp_path / "r")])


class FlakyWorld:
    """The embedded world, except that its first episode's simulator dies after a few steps."""

    failures = 0

    def __init__(self) -> None:
        self.world = make_world("embedded")
        self.steps = 0

    def reset(self, scenario: Any, seed: int) -> Any:
        return self.world.reset(scenario, seed)

    def step(self, control: Any) -> Any:
        self.steps += 1
        if FlakyWorld.failures == 0 and self.steps == 5:
            FlakyWorld.failures += 1
            raise SimulatorError("connection lost (test)")
        return self.world.step(control)

    def close(self) -> None:
        self.world.close()


def test_runner_retries_a_simulator_error_on_a_fresh_world(tmp_path: Path) -> None:
    made: list[FlakyWorld] = []

    def factory() -> FlakyWorld:
        made.append(FlakyWorld())
        return made[-1]

    eps = episodes("all", ["new-town-weather"], ["straight"], routes="19", seeds=1, weather_rule="cycle")
    run = run_benchmark(eps, AgentSpec("expert"), tmp_path / "r", progress=False, world_factory=factory)
    assert FlakyWorld.failures == 1 and len(made) == 2
    assert run.ran == 1 and run.records[0]["success"]
