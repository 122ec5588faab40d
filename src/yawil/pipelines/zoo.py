"""`yawil reproduce --profile zoo`: remake the zoo's models from nothing, with the recipes their cards name.

Stages (each resumable at any kill: a marker per finished stage, and every stage resumes mid-way):
  1. collect town01's expert data (training weathers, 20,000 frames, seed 0), once per yaw-guidance reference
     the recipes ask for (`route`, the paper's: OUT/data/town01; `ego`: OUT/data/town01_ego, the same episodes);
  2. per zoo recipe: train it (`yawil dagger` or `yawil train`; a recipe with a `base` is a DAgger run whose
     round 0 is its base recipe's final checkpoint, so the base is made first), benchmark it on the fixed
     100-episode set (`--preset eval100`) and on the demo's episodes, driven as its card will say, then pack it
     with its card into OUT/zoo/NAME (`--install` packs into the repository's zoo instead, replacing the shipped
     model).

Budgets are frames and steps only, so any machine makes the same models (CPU or GPU: `--device`); only the
wall time differs, and the card records it with the machine. The commands in each card are the equivalent
single commands of its recipe (docs/training.md, "The model zoo").
"""

from __future__ import annotations

import json
import platform
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from yawil.guidance import GuidanceConfig

EXPERT_FRAMES = 20_000
EVAL_WORKERS = 2


@dataclass(frozen=True)
class ZooRecipe:
    """One zoo model: how it is trained (a DAgger run, or plain training), and how it is driven."""

    name: str
    summary: str
    model: str
    steps: int
    train_args: dict[str, Any] = field(default_factory=dict)  # TrainConfig settings
    dagger: dict[str, Any] | None = None  # DaggerConfig settings (None: plain `yawil train`)
    drive: dict[str, Any] = field(default_factory=dict)  # how it is driven (a card's `drive`: yawil.zoo.DRIVE_KEYS)
    guidance_reference: str = GuidanceConfig.reference  # of the expert data (`yawil collect --guidance-reference`)
    base: str | None = None  # a DAgger recipe whose final checkpoint is this DAgger run's round 0 (made first)

    def checkpoint(self, out: str) -> str:
        """Where the recipe's run folder `out` holds its final checkpoint."""
        from yawil.pipelines.dagger import DaggerRun

        folder = Path(out) if self.dagger is None else DaggerRun.round_folder(Path(out), self.dagger["rounds"])
        return str(folder / "last.pt")

    def train_command(self, data: str, out: str, seed: int = 0) -> str:
        """The one `yawil dagger` or `yawil train` command of this recipe's training (its base's not included), at
        training seed `seed` (the shipped models': 0, which a DAgger command leaves unsaid)."""
        from yawil.policy.speed import DRIVE_OPTIONS
        from yawil.zoo import drive_flags

        if self.dagger is not None:
            d = self.dagger
            flags = " ".join(f"--{k.replace('_', '-')} {_flag_value(v)}" for k, v in d.items() if k not in DRIVE_OPTIONS)
            targs = " ".join(f"--train-arg '{k}={json.dumps(v)}'" for k, v in self.train_args.items())
            round0 = f" --round0 {recipe(self.base).checkpoint(str(Path(out).parent / self.base))}" if self.base else ""
            learner = drive_flags({k: v for k, v in d.items() if k in DRIVE_OPTIONS})  # how the learner drives its rounds
            return (f"yawil dagger --out {out}{seed_flag(seed)} --expert-data {data} --model {self.model}{round0} {flags} "
                    f"--workers 2 --threads 2 {targs} {learner}").strip()
        margs = " ".join(f"--model-arg {k}={json.dumps(v)}" for k, v in self.train_args.get("model_args", {}).items())
        rest = " ".join(f"--{k.replace('_', '-')} {v}" for k, v in self.train_args.items() if k != "model_args")
        return (f"yawil train --model {self.model} --data {data} --out {out} --batch-size 64 --max-steps {self.steps} "
                f"{margs} {rest} --seed {seed}")

    def commands(self, data: str, out: str, seed: int = 0) -> list[str]:
        """The single commands this recipe equals (for the card): the collection, its base's training (where it
        has one, in the sibling folder of `out`), its own, and eval100 as its card drives it. A training seed
        other than 0 trains the whole chain with it; the expert data stay seed 0's, the same for every seed."""
        from yawil.zoo import drive_flags

        collect = f"yawil collect --town town01 --weathers train --frames {EXPERT_FRAMES} --out {data} --workers 2 --seed 0"
        if self.guidance_reference != GuidanceConfig.reference:
            collect += f" --guidance-reference {self.guidance_reference}"
        bases = [c.train_command(data, str(Path(out).parent / c.name), seed) for c in chain(self)[:-1]]
        bench = f"yawil bench --preset eval100 --agent {self.checkpoint(out)} --workers 2 {drive_flags(self.drive)}"
        return [collect, *bases, self.train_command(data, out, seed), bench.strip()]


def seed_flag(seed: int) -> str:
    """` --seed K` for a training seed other than the shipped models' 0, which their commands leave unsaid."""
    return f" --seed {seed}" if seed else ""


def _flag_value(value: Any) -> str:
    """A DaggerConfig value as its command-line flag takes it (per-round traffic: LO-HI[,LO-HI...])."""
    if isinstance(value, tuple) and value and isinstance(value[0], tuple):
        return ",".join(f"{lo}-{hi}" for lo, hi in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


LEAD_STOP = {"aux": True, "lead_stop": True, "speed_input": False}
# the yilratt-dagger-stop recipe, shared by the recipes that train and drive that way
DAGGER_STOP_TRAIN = {"ema": 0.995, "model_args": LEAD_STOP, "aux_weight": 0.5}
DAGGER_STOP = {"round0_steps": 750, "rounds": 2, "round_frames": 6000, "round_steps": 375, "speed_control": "stop"}
STOP_DRIVE = {"speed_control": "stop", "stop_release": 10.0}
# three DAgger rounds in town01 traffic from yilratt-dagger-ego's model, the last two at New Town02's density per
# lane (docs/training.md, "Levers on the dense cell"), the learner driving with the lead-stop class and its release
DENSE_ROUNDS = {"round0_steps": 1500, "rounds": 3, "round_frames": 6000, "round_steps": 375, "round_lr": 3e-4,
                "round_vehicles": ((50, 60), (100, 130)), "round_pedestrians": ((30, 40), (50, 70)),
                "speed_control": "stop", "stop_release": 10.0}
DENSE_DRIVE = {"speed_control": "stop", "stop_release": 10.0, "stop_hold": 1.0, "stop_gate": 25.0, "light_hold": 40.0}
RECIPES: tuple[ZooRecipe, ...] = (
    ZooRecipe("yilratt-dagger-stop",
              "YILRatt (the paper's network) + speed-blind aux head with the lead-stop class, weight average, two DAgger "
              "rounds; driven by its target speed, stopping while the class fires, released after 10 s standing",
              "yilratt", 1500, train_args=DAGGER_STOP_TRAIN, dagger=DAGGER_STOP, drive=STOP_DRIVE),
    ZooRecipe("yaw-guided-ema",
              "the small yaw-guided baseline (CIL perception) + speed-blind aux head, weight average; driven by its "
              "predicted target speed", "yaw-guided", 750,
              train_args={"ema": 0.995, "model_args": {"aux": True, "speed_input": False}, "aux_weight": 0.5},
              drive={"speed_control": "target"}),
    ZooRecipe("yaw-guided-dagger-ego",
              "the small yaw-guided baseline with the yilratt-dagger-stop recipe (speed-blind aux head with the "
              "lead-stop class, weight average, two DAgger rounds) on expert data whose yaw guidance is measured "
              "against the car's own heading (`ego`, not the paper's `route`); driven as yilratt-dagger-stop",
              "yaw-guided", 1500, train_args=DAGGER_STOP_TRAIN, dagger=DAGGER_STOP, drive=STOP_DRIVE,
              guidance_reference="ego"),
    YILRATT_EGO := ZooRecipe(
        "yilratt-dagger-ego",
        "YILRatt (the paper's network) with the yilratt-dagger-stop recipe on expert data whose yaw guidance is "
        "measured against the car's own heading (`ego`, not the paper's `route`); driven as yilratt-dagger-stop",
        "yilratt", 1500, train_args=DAGGER_STOP_TRAIN, dagger=DAGGER_STOP, drive=STOP_DRIVE, guidance_reference="ego"),
    YILRATT_DENSE3 := ZooRecipe(
        "yilratt-dagger-dense3",
        "YILRatt: yilratt-dagger-ego fine-tuned by three DAgger rounds driven by the learner in town01 traffic, the "
        "last two at New Town02's density; driven by its target speed, stopping while its lead-stop class fires "
        "(held 1 s), the 10 s release counting only stands with the predicted lead at 25 m or farther, a stand the "
        "head made waiting up to 40 s while its light output fires",
        "yilratt", 2625, train_args=DAGGER_STOP_TRAIN, dagger=DENSE_ROUNDS, drive=DENSE_DRIVE, guidance_reference="ego",
        base="yilratt-dagger-ego"),
    # the paper's baselines with the shipped YILRatt's recipes, by construction (issue 41: its central comparison)
    *(r for model, what in (("cilrs", "CILRS (the paper's baseline: ResNet34, command branches, no yaw guidance)"),
                            ("cil", "CIL (the paper's other baseline: the small perception, command branches, no yaw "
                                    "guidance)"))
      for r in (replace(YILRATT_EGO, name=f"{model}-dagger-ego", model=model,
                        summary=f"{what} with the yilratt-dagger-ego recipe and data; driven as yilratt-dagger-stop"),
                replace(YILRATT_DENSE3, name=f"{model}-dagger-dense3", model=model, base=f"{model}-dagger-ego",
                        summary=f"{model.upper()} with yilratt-dagger-dense3's recipe: {model}-dagger-ego fine-tuned by "
                                "the same three DAgger rounds in town01 traffic; driven as yilratt-dagger-dense3"))),
    # YILRatt's attention and ResNet34 ablated: the same yaw guidance on CIL's small perception, the same dense rounds
    replace(YILRATT_DENSE3, name="yaw-guided-dagger-dense3", model="yaw-guided", base="yaw-guided-dagger-ego",
            summary="the small yaw-guided network (CIL's perception with yaw guidance, no attention) with "
                    "yilratt-dagger-dense3's recipe: yaw-guided-dagger-ego fine-tuned by the same three DAgger rounds "
                    "in town01 traffic; driven as yilratt-dagger-dense3"),
)


def recipe(name: str) -> ZooRecipe:
    for r in RECIPES:
        if r.name == name:
            return r
    raise ValueError(f"zoo recipe {name!r}: expected one of {', '.join(r.name for r in RECIPES)}")


def chain(r: ZooRecipe) -> list[ZooRecipe]:
    """The recipes a recipe is made from, its first base first, itself last."""
    out = [r]
    while out[0].base is not None:
        base = recipe(out[0].base)
        if base in out or base.dagger is None:
            raise ValueError(f"zoo recipe {out[0].name}: base {base.name} must be a DAgger recipe outside its own chain")
        out.insert(0, base)
    return out


def _suffix(reference: str) -> str:
    """The paper's `route` keeps the names runs made before references existed (so they resume); others add theirs."""
    return "" if reference == GuidanceConfig.reference else f"_{reference}"


def data_dir(out: Path, reference: str) -> Path:
    """The expert data of one guidance reference."""
    return out / "data" / f"town01{_suffix(reference)}"


def collect_stage_name(reference: str) -> str:
    return f"collect{_suffix(reference)}"


def machine() -> str:
    import os

    import torch

    return (f"{platform.machine()}, {os.cpu_count()} cores, {platform.processor() or 'cpu'}; torch {torch.__version__}"
            + (f", {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""))


def summary_of(results: Path) -> dict[str, Any]:
    """Successes and failures by reason of a benchmark folder (the card's figures)."""
    from yawil.bench.records import read_records

    recs = read_records(results / "episodes.jsonl")
    reasons = Counter(str(r.get("reason")) for r in recs if not r["success"])
    return {"episodes": len(recs), "successes": sum(bool(r["success"]) for r in recs), "failures": dict(reasons),
            "results": str(results)}


def episode_set(which: str) -> list[Any]:
    """eval100 (= `yawil bench --preset eval100`) or the demo's episodes (the card's `demo` figure, the guard)."""
    from yawil.bench.suites import episodes
    from yawil.pipelines.demo import DemoBudget

    if which == "eval100":
        return episodes("all", ["training", "new-town-weather"], routes="0:10", seeds=1, weather_rule="cycle")
    b = DemoBudget()
    return episodes("all", ["training", "new-town-weather"], list(b.tasks), routes=b.routes, seeds=b.seeds,
                    weather_rule="cycle")


def check_seed(out: Path, names: list[str], seed: int) -> None:
    """Refuse, before any stage, a folder whose finished trainings used another training seed: their markers
    would be taken for this seed's models (a marker without a seed is seed 0's, as every run before seeds were)."""
    from yawil.stages import read_marker

    for r in (c for n in names for c in chain(recipe(n))):
        marker = read_marker(out / "stages" / f"train_{r.name}.json")
        done = None if marker is None else int(marker.get("seed", 0))
        if done is not None and done != seed:
            raise ValueError(f"{out}: {r.name} was trained there with training seed {done}, "
                             f"not {seed}; give each training seed its own --out")


def stages(out: Path, names: list[str], device: str = "auto", install: bool = False,
           progress: bool = True, seed: int = 0) -> list[tuple[str, Callable[[], dict[str, Any]]]]:
    def collect_stage(reference: str) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.data.collect import collect

            s = collect(data_dir(out, reference), town="town01", weathers="train", frames=EXPERT_FRAMES, workers=2,
                        seed=0, guidance=GuidanceConfig(reference=reference), progress=progress)
            return {"frames": s.dataset_frames, "guidance_reference": reference}

        return fn

    def train_stage(r: ZooRecipe) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            t = time.perf_counter()
            run, data = out / "runs" / r.name, data_dir(out, r.guidance_reference)
            if r.dagger is not None:
                from yawil.pipelines.dagger import DaggerConfig, DaggerRun

                round0 = checkpoint_of(recipe(r.base)) if r.base else None
                dcfg = DaggerConfig(model=r.model, expert_data=str(data), workers=2, threads=0, round0=round0, seed=seed,
                                    train_args={**r.train_args, "device": device}, **r.dagger)
                ckpt = DaggerRun(run, dcfg, progress=progress).run()
            else:
                from yawil.learn.config import TrainConfig
                from yawil.learn.loop import train

                cfg = TrainConfig.from_dict({"model": r.model, "data": [str(data)], "out": str(run), "batch_size": 64,
                                             "max_steps": r.steps, "seed": seed, "device": device, "progress": progress,
                                             **r.train_args}, "zoo")
                train(cfg, resume=(run / "last.pt").is_file())
                ckpt = run / "last.pt"
            return {"checkpoint": str(ckpt), "wall_s": round(time.perf_counter() - t), "seed": seed}

        return fn

    def checkpoint_of(r: ZooRecipe) -> str:
        from yawil.stages import read_marker

        marker = read_marker(out / "stages" / f"train_{r.name}.json")
        if marker is None:
            raise ValueError(f"zoo {r.name}: its training stage has not finished")
        return str(marker["checkpoint"])

    def bench_stage(r: ZooRecipe, which: str) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.bench.runner import AgentSpec, run_benchmark

            spec = AgentSpec(checkpoint_of(r), **r.drive, device="cpu").validate()  # as its card will drive it
            eps = episode_set(which)
            t = time.perf_counter()
            run_benchmark(eps, spec, out / "results" / f"{r.name}_{which}", workers=EVAL_WORKERS, label=r.name,
                          progress=progress)
            return {**summary_of(out / "results" / f"{r.name}_{which}"), "wall_s": round(time.perf_counter() - t)}

        return fn

    def pack_stage(r: ZooRecipe) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.policy.checkpoint import load_checkpoint
            from yawil.provenance import git_commit
            from yawil.stages import read_marker
            from yawil.zoo import ZOO_DIR
            from yawil.zoo.pack import pack

            data = data_dir(out, r.guidance_reference)
            marks = {k: read_marker(out / "stages" / f"{k}_{r.name}.json") or {} for k in ("train", "eval100", "demo")}
            ckpt = checkpoint_of(r)
            metrics = load_checkpoint(ckpt)["metrics"]
            card = {"summary": r.summary + (f" (training seed {seed})" if seed else ""),
                    "commands": r.commands(str(data), str(out / "runs" / r.name), seed),
                    "made_by": f"yawil reproduce --profile zoo --out {out}{seed_flag(seed)}", "commit": git_commit(),
                    "data": {"path": str(data), "town": "town01", "weathers": "train", "frames": EXPERT_FRAMES, "seed": 0,
                             "guidance_reference": r.guidance_reference},
                    "wall_s": {"train": marks["train"].get("wall_s"), "eval100": marks["eval100"].get("wall_s")},
                    "machine": machine(),  # a metric not measured is NaN there: null in the card (a card holds finite numbers)
                    "validation": {k: None if v != v else v for k, v in (metrics[-1] if metrics else {}).items()},
                    "eval100": marks["eval100"], "demo": marks["demo"], "drive": r.drive}
            folder = pack(ckpt, r.name, data, card, root=None if install else out / "zoo")
            return {"folder": str(folder), "installed": install, "root": str(ZOO_DIR if install else out / "zoo")}

        return fn

    # a base before what is made from it, each once
    chosen = [recipe(n) for n in dict.fromkeys(c.name for n in names for c in chain(recipe(n)))]
    plan: list[tuple[str, Callable[[], dict[str, Any]]]] = [
        (collect_stage_name(ref), collect_stage(ref)) for ref in dict.fromkeys(r.guidance_reference for r in chosen)]
    for r in chosen:
        plan.append((f"train_{r.name}", train_stage(r)))
        plan.append((f"eval100_{r.name}", bench_stage(r, "eval100")))
        plan.append((f"demo_{r.name}", bench_stage(r, "demo")))
        plan.append((f"pack_{r.name}", pack_stage(r)))
    return plan
