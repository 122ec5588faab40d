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
  quick profile: about 1 h on this CPU.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class ReproduceProfile:
    name: str
    frames: int
    collect_workers: int
    epochs: int
    batch_size: int
    max_minutes: float | None  # per model
    routes: str | None  # benchmark route ids per task (None: all 25)
    seeds: int | None  # None: the protocol's (5 static, 3 dynamic)
    bench_workers: int
    experiments_profile: str  # profile of `yawil experiment square|noise`
    weather_rule: str = "all"  # the protocol's every route in every weather; quick: route i in weather i mod n


PROFILES: dict[str, ReproduceProfile] = {
    "quick": ReproduceProfile("quick", frames=20_000, collect_workers=2, epochs=3, batch_size=128, max_minutes=8.0,
                              routes="0:5", seeds=1, bench_workers=2, experiments_profile="quick", weather_rule="cycle"),
    "paper": ReproduceProfile("paper", frames=200_000, collect_workers=2, epochs=100, batch_size=512, max_minutes=None,
                              routes=None, seeds=None, bench_workers=2, experiments_profile="paper"),
}  # fmt: skip

MODELS: tuple[tuple[str, str], ...] = (("cil", "cil"), ("cilrs", "cilrs"), ("yilratt", "yilratt"))


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "reproduce",
        help="every experiment of the paper (Tables I-IV, heat maps) at a chosen size",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--profile", default="quick", choices=tuple(PROFILES), help="size (default quick)")
    p.add_argument("--out", default="runs/reproduce", help="output folder (default runs/reproduce)")
    p.add_argument("--pretrained", default=None, help="local torchvision ResNet34 ImageNet weights (.pth), "
                   "for the 'YILRatt (pretrained)' column; omitted: that column is skipped")  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="training device: auto | cpu | cuda")
    p.add_argument("--dry-run", action="store_true", help="print the stages and their settings, run nothing")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.stages import run_stage

    profile = PROFILES[args.profile]
    if args.pretrained and not Path(args.pretrained).is_file():
        raise SystemExit(f"yawil reproduce: --pretrained {args.pretrained}: no such file")
    plan = stages(Path(args.out), profile, args.pretrained, seed=args.seed, device=args.device)
    print(f"profile {profile.name}: {json.dumps(asdict(profile))}")
    for name, _ in plan:
        print(f"  stage {name}")
    if args.dry_run:
        return 0
    def say(msg: str) -> None:
        print(f"[reproduce] {msg}", flush=True)

    for name, fn in plan:
        run_stage(Path(args.out) / "stages" / f"{name}.json", fn, say, name)
    print(f"[reproduce] report: {Path(args.out) / 'report' / 'report.html'}")
    return 0


def models_to_train(pretrained: str | None) -> list[tuple[str, str, str | None]]:
    """(run name, registry name, pretrained weights) of the paper's Table III columns."""
    runs: list[tuple[str, str, str | None]] = [(n, m, None) for n, m in MODELS]
    if pretrained:
        runs.append(("yilratt_pretrained", "yilratt", pretrained))
    return runs


def stages(out: Path, p: ReproduceProfile, pretrained: str | None, seed: int = 0,
           device: str = "auto") -> list[tuple[str, Callable[[], dict[str, Any]]]]:
    """The stages in order, each (name, a function of no arguments returning its marker's content)."""
    data = out / "data" / "town01"

    def collect_stage() -> dict[str, Any]:
        from yawil.data.collect import collect

        s = collect(data, town="town01", weathers="train", frames=p.frames, workers=p.collect_workers, seed=seed)
        return {"frames": s.dataset_frames}

    def train_stage(run_name: str, model: str, weights: str | None) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.learn.config import TrainConfig
            from yawil.learn.loop import train

            run_dir = out / "runs" / run_name
            cfg = TrainConfig(model=model, data=[str(data)], out=str(run_dir), epochs=p.epochs,
                              batch_size=p.batch_size, max_minutes=p.max_minutes, pretrained=weights,
                              seed=seed, device=device, workers=1)  # fmt: skip
            r = train(cfg, resume=(run_dir / "last.pt").is_file())
            return {"steps": r.steps, "epochs": r.epochs_done, "best_val": r.best_val, "stopped_by": r.stopped_by}

        return fn

    def bench_stage(label: str, agent: str) -> Callable[[], dict[str, Any]]:
        def fn() -> dict[str, Any]:
            from yawil.bench.runner import AgentSpec, run_benchmark
            from yawil.bench.suites import episodes

            eps = episodes("all", routes=p.routes, seeds=p.seeds, weather_rule=p.weather_rule)
            path = agent if agent == "expert" else str(out / "runs" / agent / "best.pt")
            s = run_benchmark(eps, AgentSpec(path), out / "results" / label, workers=p.bench_workers, label=label)
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
