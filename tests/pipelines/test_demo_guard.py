"""The demo's regression guard (`make test-all`): the zoo models still drive their cards' share of the demo's
episodes, and the demo's recipe still teaches the small baseline to drive the easy routes. A change that
silently breaks learning, driving or preprocessing fails here, not in a user's report."""

from __future__ import annotations

from pathlib import Path

import pytest

from yawil.zoo import read_card, zoo_names


@pytest.mark.slow
@pytest.mark.parametrize("name", zoo_names())
def test_zoo_model_drives_its_cards_demo_share(name: str, tmp_path: Path) -> None:
    from yawil.bench.runner import run_benchmark
    from yawil.pipelines.demo import zoo_spec
    from yawil.pipelines.zoo import episode_set

    want = read_card(name)["demo"]
    s = run_benchmark(episode_set("demo"), zoo_spec(name).validate(), tmp_path / "r", workers=2, progress=False)
    assert s.total == want["episodes"] and s.successes >= want["successes"], (s.successes, want)


@pytest.mark.slow
def test_demo_recipe_teaches_the_baseline_the_easy_routes(tmp_path: Path) -> None:
    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.data.collect import collect
    from yawil.learn.config import TrainConfig
    from yawil.learn.loop import train
    from yawil.pipelines.demo import DemoBudget, demo_guidance
    from yawil.pipelines.zoo import episode_set

    b = DemoBudget()
    collect(tmp_path / "data", town="town01", weathers="train", frames=b.frames, workers=2, seed=0, progress=False,
            guidance=demo_guidance(read_card(b.zoo_model)))  # fmt: skip
    cfg = TrainConfig(model=b.baseline, data=[str(tmp_path / "data")], out=str(tmp_path / "run"), epochs=b.epochs,
                      batch_size=b.batch_size, lr=b.lr, lr_step_epochs=b.lr_step_epochs, max_steps=b.baseline_steps,
                      seed=0, workers=1, ema=b.baseline_ema, progress=False)
    train(cfg)
    s = run_benchmark(episode_set("demo"), AgentSpec(str(tmp_path / "run" / "last.pt")).validate(), tmp_path / "r",
                      workers=2, progress=False)
    assert s.successes >= b.baseline_expected * s.total, f"{s.successes}/{s.total}"
