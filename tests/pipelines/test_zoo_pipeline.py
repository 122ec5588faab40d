"""`yawil reproduce --profile zoo` at a tiny scale: collect, train, benchmark, pack; the packed model passes its
probe check and its card holds the figures the stages measured; a rerun resumes without work. And the plan: one
expert collection per guidance reference the chosen recipes need."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from yawil.pipelines import zoo as zp


@pytest.mark.slow
def test_zoo_pipeline_makes_a_checked_model_with_its_card(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from yawil.bench.suites import episodes
    from yawil.cli import main
    from yawil.policy.checkpoint import load_checkpoint
    from yawil.zoo import read_card, zoo_dir
    from yawil.zoo.pack import check_zoo_model

    tiny = zp.ZooRecipe("tiny", "a tiny net", "yaw-guided", 3, drive={"speed_control": "target"},
                        train_args={"ema": 0.9, "model_args": {"aux": True}, "aux_weight": 0.5, "threads": 1},
                        guidance_reference="ego")
    monkeypatch.setattr(zp, "RECIPES", (tiny,))
    monkeypatch.setattr(zp, "EXPERT_FRAMES", 150)
    monkeypatch.setattr(zp, "EVAL_WORKERS", 1)
    one = episodes("all", ["new-town-weather"], ["straight"], routes="0:1", seeds=1, weather_rule="cycle")
    monkeypatch.setattr(zp, "episode_set", lambda which: one)
    out = tmp_path / "zoo_run"
    assert main(["reproduce", "--profile", "zoo", "--out", str(out)]) == 0
    card = read_card("tiny", out / "zoo")
    assert card["eval100"]["episodes"] == 1 and card["demo"]["episodes"] == 1 and card["step"] == 3
    assert card["drive"] == {"speed_control": "target"} and card["commands"][1].startswith("yawil train --model yaw-guided")
    assert card["data"]["frames"] == 150 and "cores" in card["machine"] and card["validation"]
    assert check_zoo_model("tiny", out / "zoo") <= 1e-3
    assert card["data"]["guidance_reference"] == "ego" and "--guidance-reference ego" in card["commands"][0]
    packed = load_checkpoint(zoo_dir("tiny", out / "zoo") / "model.pt")
    assert packed["guidance_config"]["reference"] == "ego"
    assert main(["reproduce", "--profile", "zoo", "--out", str(out)]) == 0  # every stage done: nothing runs again
    assert main(["reproduce", "--profile", "zoo", "--out", str(out), "--zoo-models", "nope"]) == 2


def test_plan_collects_once_per_guidance_reference_and_commands_name_it(tmp_path: Path) -> None:
    route = [r.name for r in zp.RECIPES if r.guidance_reference == "route"]
    ego = [r.name for r in zp.RECIPES if r.guidance_reference == "ego"]
    assert route and ego  # the shipped recipes use both
    plan = [name for name, _ in zp.stages(tmp_path, route + ego)]
    assert plan[:2] == ["collect", "collect_ego"] and plan.count("collect") == 1 and plan.count("collect_ego") == 1
    assert [name for name, _ in zp.stages(tmp_path, ego)][0] == "collect_ego"
    assert "collect" not in [name for name, _ in zp.stages(tmp_path, ego)]
    assert zp.data_dir(tmp_path, "route") == tmp_path / "data" / "town01"  # the folder earlier runs resume in
    assert zp.data_dir(tmp_path, "ego") == tmp_path / "data" / "town01_ego"
    r = zp.recipe(ego[0])
    collect, train, bench = r.commands("data/e", "runs/e")
    assert collect.endswith("--guidance-reference ego") and "--expert-data data/e" in train
    assert zp.recipe(route[0]).commands("data/r", "runs/r")[0].endswith("--seed 0")  # the paper's: no flag


def test_a_chained_recipe_makes_its_base_first_and_its_commands_name_the_base_checkpoint(tmp_path: Path) -> None:
    from yawil.zoo import read_card

    dense = zp.recipe("yilratt-dagger-dense3")
    assert [r.name for r in zp.chain(dense)] == ["yilratt-dagger-ego", "yilratt-dagger-dense3"]
    plan = [name for name, _ in zp.stages(tmp_path, ["yilratt-dagger-dense3"])]
    assert plan[:3] == ["collect_ego", "train_yilratt-dagger-ego", "eval100_yilratt-dagger-ego"]
    assert plan.index("train_yilratt-dagger-dense3") > plan.index("pack_yilratt-dagger-ego")
    both = [name for name, _ in zp.stages(tmp_path, ["yilratt-dagger-dense3", "yilratt-dagger-ego"])]
    assert both.count("train_yilratt-dagger-ego") == 1  # a base asked for by name as well is made once
    collect, base, train, bench = dense.commands("data/e", "runs/yilratt-dagger-dense3")
    assert base == zp.recipe("yilratt-dagger-ego").train_command("data/e", "runs/yilratt-dagger-ego")
    assert "--round0 runs/yilratt-dagger-ego/train/round_02/last.pt" in train
    assert "--round-vehicles 50-60,100-130 --round-pedestrians 30-40,50-70" in train and "--round-lr 0.0003" in train
    assert train.endswith("--speed-control stop --stop-release 10.0")  # the learner's drive in its rounds
    assert bench.startswith("yawil bench --preset eval100 --agent runs/yilratt-dagger-dense3/train/round_03/last.pt")
    # the recipe drives as the shipped model's card does, and its steps are the card's
    card = read_card("yilratt-dagger-dense3")
    assert dense.drive == card["drive"] and dense.steps == card["steps_total"]
    assert "--light-hold 40.0" in bench


def test_every_recipe_names_a_drive_its_model_takes(tiny_checkpoint: Any) -> None:
    from yawil.bench.runner import AgentSpec
    from yawil.guidance import GuidanceConfig
    from yawil.zoo import DRIVE_KEYS, ZOO_DIR

    for r in zp.RECIPES:  # the drive must suit the outputs of the model the recipe trains (shipped or not yet)
        assert set(r.drive) <= set(DRIVE_KEYS), r.name
        ckpt = tiny_checkpoint(r.model, guidance=GuidanceConfig(reference=r.guidance_reference).to_dict(),
                               **r.train_args.get("model_args", {})).path
        AgentSpec(str(ckpt), **r.drive).validate(build=True)
        if (ZOO_DIR / r.name / "model.pt").is_file():
            AgentSpec(f"zoo:{r.name}", **r.drive).validate(build=False)


def test_a_training_seed_trains_the_whole_chain_and_a_folder_holds_one_seed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from yawil.cli import main

    dense = zp.recipe("cilrs-dagger-dense3")
    collect, base, train, _ = dense.commands("data/e", "runs/cilrs-dagger-dense3", seed=2)
    assert collect.endswith("--seed 0 --guidance-reference ego")  # the expert data are every seed's
    assert base.startswith("yawil dagger --out runs/cilrs-dagger-ego --seed 2 ")
    assert train.startswith("yawil dagger --out runs/cilrs-dagger-dense3 --seed 2 ")
    assert "--seed" not in dense.commands("data/e", "runs/x")[2]  # seed 0: the shipped cards' commands, unchanged
    plain = zp.recipe("yaw-guided-ema")
    assert plain.train_command("d", "o", seed=3).endswith("--seed 3")
    # a folder whose base was trained with seed 0 (a marker without a seed: every run before seeds) is refused
    out = tmp_path / "z"
    (out / "stages").mkdir(parents=True)
    (out / "stages" / "train_cilrs-dagger-ego.json").write_text(json.dumps({"checkpoint": "x.pt"}))
    zp.check_seed(out, ["cilrs-dagger-dense3"], 0)
    with pytest.raises(ValueError, match="trained there with training seed 0, not 1; give each training seed its own"):
        zp.check_seed(out, ["cilrs-dagger-dense3"], 1)
    for extra, text in ((["--seed", "1"], "training seed 0, not 1"), (["--seed", "1", "--install"], "ships each recipe")):
        with pytest.raises(SystemExit, match=text):
            main(["reproduce", "--profile", "zoo", "--out", str(out), "--zoo-models", "cilrs-dagger-dense3",
                  "--dry-run", *extra])
