"""`yawil reproduce`: every experiment of the paper with the same code, at the chosen size.

Stages (each resumable: it is skipped when its marker exists, and the stages themselves resume mid-way):
  1. collect the town01 dataset (training weathers) with the expert;
  2. train CIL, CILRS, YILRatt and, when `--pretrained` gives ImageNet ResNet34 weights, YILRatt (pretrained);
  3. benchmark the expert and every model on corl2017 + nocrash in both conditions (Tables III and IV);
  4. attention heat maps (Figures 8 and 9), the square experiment (Table I) and the noise experiment (Table II);
  5. one report over all result folders.

Expected time (measured parts in docs/performance.md; the rest extrapolated from them):
  paper profile, this 2-core CPU: collection of 200k frames about 35 min (2 workers, ~100 frames/s);
  training about 100 epochs x 200k samples / ~40 samples/s = ~140 h per ResNet34 model (CIL ~4x faster):
  weeks for the four models; benchmarks about 15 min per condition for the expert and, for a learned agent
  at ~40 steps/s per worker, about 10 h per condition. On one modern GPU the training is about 100x faster
  (a day for all models) and the benchmark is then CPU-bound (render + simulation, a few hours).
  quick profile: 200 steps of 128 per model (a budget in steps: the same models on any machine), about 1 h
  on this CPU with bf16 (several hours without it).
  gpu profile (one GPU node, docs/scale.md): the paper's sizes; collection and benchmarks on every core, training
  on CUDA with bf16 autocast, channels_last and the dataset held on the GPU (`--data-on-device`), the learned
  agents' models on CUDA. Not measured yet (no GPU here); benchmarks/gpu_check.sh measures its parts.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from yawil.cliargs import seed


@dataclass(frozen=True)
class ReproduceProfile:
    name: str
    frames: int
    collect_workers: int  # 0: one per core (os.cpu_count())
    epochs: int
    batch_size: int
    max_minutes: float | None  # per model: an explicit cap (None in every profile: budgets are epochs and steps)
    routes: str | None  # benchmark route ids per task (None: all 25)
    seeds: int | None  # None: the protocol's (5 static, 3 dynamic)
    bench_workers: int  # 0: one per core
    experiments_profile: str  # profile of `yawil experiment square|noise`
    weather_rule: str = "all"  # the protocol's every route in every weather; quick: route i in weather i mod n
    # How the models train and drive (TrainConfig's fields; `--device` overrides train_device):
    train_device: str = "auto"
    precision: str = "auto"
    channels_last: str = "auto"
    data_on_device: bool = False
    bench_device: str = "cpu"  # the learned agents' models in the benchmarks (AgentSpec.device)
    max_steps: int | None = None  # per model, besides the epochs (the quick profile's budget)

    def workers(self, n: int) -> int:
        """A worker count of the profile: 0 means one per core of the machine it runs on."""
        return n or (os.cpu_count() or 1)


PROFILES: dict[str, ReproduceProfile] = {
    "quick": ReproduceProfile("quick", frames=20_000, collect_workers=2, epochs=3, batch_size=128, max_minutes=None,
                              max_steps=200,
                              routes="0:5", seeds=1, bench_workers=2, experiments_profile="quick", weather_rule="cycle"),
    "paper": ReproduceProfile("paper", frames=200_000, collect_workers=2, epochs=100, batch_size=512, max_minutes=None,
                              routes=None, seeds=None, bench_workers=2, experiments_profile="paper"),
    # The paper's sizes on one GPU node: budgets in frames and epochs, none in minutes.
    "gpu": ReproduceProfile("gpu", frames=200_000, collect_workers=0, epochs=100, batch_size=512, max_minutes=None,
                            routes=None, seeds=None, bench_workers=0, experiments_profile="paper",
                            train_device="cuda", precision="bf16", channels_last="on", data_on_device=True,
                            bench_device="cuda"),
}  # fmt: skip

MODELS: tuple[tuple[str, str], ...] = (("cil", "cil"), ("cilrs", "cilrs"), ("yilratt", "yilratt"))


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "reproduce",
        help="every experiment of the paper (Tables I-IV, heat maps) at a chosen size",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--profile", default="quick", choices=(*PROFILES, "zoo"),
                   help="size (default quick); zoo: remake the model zoo's models (yawil.pipelines.zoo)")
    p.add_argument("--out", default="runs/reproduce", help="output folder (default runs/reproduce)")
    p.add_argument("--pretrained", default=None, help="local torchvision ResNet34 ImageNet weights (.pth), "
                   "for the 'YILRatt (pretrained)' column; omitted: that column is skipped")  # fmt: skip
    p.add_argument("--seed", type=seed, default=0, help="seed of collection and training (default 0); --profile "
                   "zoo: the recipes' training seed (their expert data stay seed 0's)")
    p.add_argument("--device", default=None, choices=("auto", "cpu", "cuda"),
                   help="training device (default: the profile's; gpu: cuda, the others: auto)")
    p.add_argument("--dry-run", action="store_true", help="print the stages and their settings, run nothing")
    p.add_argument("--zoo-models", default=None, help="--profile zoo: comma-separated recipe names (default all)")
    p.add_argument("--install", action="store_true",
                   help="--profile zoo: pack into the repository's zoo (replacing the shipped models), not OUT/zoo")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.fileio import check_pipeline_folder, claimed_output_folder
    from yawil.stages import run_stage

    try:  # a user's folder or a dataset is refused before any stage (the stages resume by reading it)
        check_pipeline_folder(args.out, "--out", "reproduce", signature=("stages", "data"))
    except ValueError as err:
        raise SystemExit(f"yawil reproduce: {err}") from None
    if args.profile == "zoo":
        return run_zoo(args)
    for flag, given in (("--install", args.install), ("--zoo-models", args.zoo_models is not None)):
        if given:  # only the zoo profile packs zoo models: without it the option did nothing
            raise SystemExit(f"yawil reproduce: {flag} applies to --profile zoo only (the zoo's models); "
                             f"--profile {args.profile} makes none")
    profile = PROFILES[args.profile]
    if args.pretrained:  # read now, not at the training stage after the collection and two trainings
        from yawil.models.resnet import build_resnet34, load_imagenet_weights

        try:
            load_imagenet_weights(build_resnet34(), args.pretrained)
        except (ValueError, FileNotFoundError) as err:
            raise SystemExit(f"yawil reproduce: --pretrained: {err}") from None
    plan = stages(Path(args.out), profile, args.pretrained, seed=args.seed, device=args.device)
    print(f"profile {profile.name}: {json.dumps(asdict(profile))}")
    for name, _ in plan:
        print(f"  stage {name}")
    if args.dry_run:
        return 0
    if "cuda" in (args.device or profile.train_device, profile.bench_device):
        import torch

        if not torch.cuda.is_available():
            raise SystemExit(f"yawil reproduce: --profile {profile.name} trains or drives on CUDA, but torch sees no "
                             "CUDA device here; use --profile quick or paper")
    def say(msg: str) -> None:
        print(f"[reproduce] {msg}", flush=True)

    with claimed_output_folder(args.out, "reproduce"):  # marked as reproduce's: an interrupted run resumes
        for name, fn in plan:
            run_stage(Path(args.out) / "stages" / f"{name}.json", fn, say, name)
    print(f"[reproduce] report: {Path(args.out) / 'report' / 'report.html'}")
    return 0


def run_zoo(args: argparse.Namespace) -> int:
    from yawil.fileio import claimed_output_folder
    from yawil.pipelines import zoo
    from yawil.stages import run_stage

    names = [n.strip() for n in args.zoo_models.split(",")] if args.zoo_models else [r.name for r in zoo.RECIPES]
    for n in names:
        zoo.recipe(n)  # an unknown name fails before any stage
    out = Path(args.out)
    if args.install and args.seed:  # the zoo ships each recipe's seed 0; another seed's figures go in its card
        raise SystemExit(f"yawil reproduce: --install with --seed {args.seed}: the zoo ships each recipe's model of "
                         "training seed 0 (docs/training.md, \"The model zoo\"); without --install the model packs "
                         "into OUT/zoo")
    try:
        zoo.check_seed(out, names, args.seed)
    except ValueError as err:
        raise SystemExit(f"yawil reproduce: {err}") from None
    plan = zoo.stages(out, names, device=args.device or "auto", install=args.install, seed=args.seed)
    for name, _ in plan:
        print(f"  stage {name}")
    if args.dry_run:
        return 0
    with claimed_output_folder(out, "reproduce"):
        for name, fn in plan:
            run_stage(out / "stages" / f"{name}.json", fn, lambda m: print(f"[reproduce zoo] {m}", flush=True), name)
    print(f"[reproduce zoo] models in {'the repository zoo' if args.install else out / 'zoo'}")
    return 0


def models_to_train(pretrained: str | None) -> list[tuple[str, str, str | None]]:
    """(run name, registry name, pretrained weights) of the paper's Table III columns."""
    runs: list[tuple[str, str, str | None]] = [(n, m, None) for n, m in MODELS]
    if pretrained:
        runs.append(("yilratt_pretrained", "yilratt", pretrained))
    return runs


def train_config(out: Path, p: ReproduceProfile, run_name: str, model: str, weights: str | None, seed: int = 0,
                 device: str | None = None) -> Any:
    """The TrainConfig of one model's run in the profile (`device`: the command's --device, else the profile's)."""
    from yawil.learn.config import TrainConfig

    return TrainConfig(model=model, data=[str(out / "data" / "town01")], out=str(out / "runs" / run_name),
                       epochs=p.epochs, batch_size=p.batch_size, max_minutes=p.max_minutes, max_steps=p.max_steps,
                       pretrained=weights,
                       seed=seed, device=device or p.train_device, precision=p.precision,
                       channels_last=p.channels_last, data_on_device=p.data_on_device,
                       workers=p.workers(0) if p.data_on_device else 1)  # fmt: skip


def agent_spec(out: Path, p: ReproduceProfile, agent: str) -> Any:
    """The benchmark's AgentSpec of 'expert' or a trained run's best.pt, on the profile's device."""
    from yawil.bench.runner import AgentSpec

    path = agent if agent == "expert" else str(out / "runs" / agent / "best.pt")
    return AgentSpec(path, device=p.bench_device)


def stages(out: Path, p: ReproduceProfile, pretrained: str | None, seed: int = 0,
           device: str | None = None) -> list[tuple[str, Callable[[], dict[str, Any]]]]:
    """The stages in order, each (name, a function of no arguments returning its marker's content)."""
    data = out / "data" / "town01"

    def collect_stage() -> dict[str, Any]:
        from yawil.data.collect import collect

        s = collect(data, town="town01", weathers="train", frames=p.frames, workers=p.workers(p.collect_workers),
                    seed=seed)
        return {"frames": s.dataset_frames}

    def train_stage(run_name: str, model: str, weights: str | None) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.learn.loop import train

            cfg = train_config(out, p, run_name, model, weights, seed, device)
            r = train(cfg, resume=(Path(cfg.out) / "last.pt").is_file())
            return {"steps": r.steps, "epochs": r.epochs_done, "best_val": r.best_val, "stopped_by": r.stopped_by}

        return fn

    def bench_stage(label: str, agent: str) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.bench.runner import run_benchmark
            from yawil.bench.suites import episodes

            eps = episodes("all", routes=p.routes, seeds=p.seeds, weather_rule=p.weather_rule)
            s = run_benchmark(eps, agent_spec(out, p, agent), out / "results" / label,
                              workers=p.workers(p.bench_workers), label=label)
            return {"episodes": s.total, "successes": s.successes}

        return fn

    def experiments_stage() -> dict[str, Any]:
        from yawil.bench.experiments import noise_experiment, square_experiment

        t1 = square_experiment(out / "square", profile=p.experiments_profile, seed=seed)
        t2 = noise_experiment(out / "square", profile=p.experiments_profile)
        return {"table1": str(t1), "table2": str(t2)}

    def explain_stage() -> dict[str, Any]:
        from yawil.agent import Agent
        from yawil.explain.attention import EpisodeVideo, explain_episode, explain_frames

        agent = Agent.from_checkpoint(out / "runs" / "yilratt" / "best.pt")
        explain_frames(agent, data, out / "explain", 8, seed, 0.5)
        ep = EpisodeVideo(route="dense:0", condition="new-town-weather", town="town02", weather="SoftRainSunset",
                          vehicles=50, pedestrians=30, seed=seed, steps=600, every=2)  # fmt: skip
        return {"video": str(explain_episode(agent, out / "explain", ep, alpha=0.5))}

    def report_stage() -> dict[str, Any]:
        from yawil.bench.report import write_report

        folders = [out / "results" / "expert"] + [out / "results" / n for n, _, _ in models_to_train(pretrained)]
        paths = write_report(folders, out / "report")
        return {"report": str(paths["report.html"])}

    plan: list[tuple[str, Callable[[], dict[str, Any]]]] = [("collect", collect_stage)]
    for run_name, model, weights in models_to_train(pretrained):
        plan.append((f"train_{run_name}", train_stage(run_name, model, weights)))
    plan.append(("bench_expert", bench_stage("expert", "expert")))
    for run_name, _, _ in models_to_train(pretrained):
        plan.append((f"bench_{run_name}", bench_stage(run_name, run_name)))
    plan += [("explain", explain_stage), ("experiments", experiments_stage), ("report", report_stage)]
    return plan
