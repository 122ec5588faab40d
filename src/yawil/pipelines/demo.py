"""`yawil demo` (what `make demo` runs): the whole loop at a small scale on the embedded simulator.

collect (town01, training weathers) -> train the small yaw-guided baseline -> benchmark it, the expert and the
zoo's YILRatt (trained by `yawil reproduce --profile zoo`, shipped in the repository) on a subset of routes in
both conditions -> the zoo YILRatt's attention heat maps and one episode video -> report.html / report.md.
The data's yaw guidance is measured against the reference the zoo model was trained on (its card's
`data.guidance_reference`: `ego` for the default, the car's own heading), so the heat maps are of inputs the
model knows and the baseline learns from the same kind of guidance.
The baseline (6.4 M parameters, ~8x faster per sample than YILRatt's ResNet34) learns to drive the easy tasks
within the demo's budget; YILRatt needs far more steps than a demo can give (docs/training.md), so the demo
drives the zoo's. `--yilratt-steps N` also trains the paper's YILRatt here for N steps.

Budgets are steps and frames, never minutes, so the same command gives the same checkpoints and tables on any
machine; `--max-minutes` is an explicit cap, off by default, and a stage it stops is named at the top of the
report. The report's guard line compares what the agents drove with what they are expected to drive.

Every stage writes its output under `--out` and marks itself done, so running the demo again after a stop
resumes where it was (collection and training resume mid-way; the benchmark resumes per episode).
The budget is the `DemoBudget` below, printed at the start and written into the report.
"""

from __future__ import annotations

import argparse
import base64
import html
import json
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from yawil.cliargs import seed
from yawil.stages import read_marker, write_marker


@dataclass(frozen=True)
class DemoBudget:
    """The demo's small scale (the paper's is in `yawil reproduce --profile paper`)."""

    frames: int = 6000  # collected in town01, training weathers, with the paper's steering noise
    collect_workers: int = 2
    model: str = "yilratt"
    batch_size: int = 64
    lr: float = 1e-3
    lr_step_epochs: int = 4
    epochs: int = 12
    max_steps: int = 0  # YILRatt trained here (0: none; the zoo's is driven and explained instead)
    max_minutes: float | None = None  # an explicit wall-time cap of each training (None: off; budgets are steps)
    baseline: str = "yaw-guided"  # the small network trained here
    baseline_steps: int = 600  # about 38k samples: enough for it to drive the straight and one-turn routes
    baseline_ema: float = 0.995  # the driven weights are the average (docs/experiments.md: the demo's robustness)
    zoo_model: str = "yilratt-dagger-dense3"  # the zoo's best YILRatt in traffic, driven as its card says
    baseline_expected: float = 0.5  # the guard: the share of the demo's episodes the fresh baseline must drive
    tasks: tuple[str, ...] = ("straight", "one_turn")
    routes: str = "0:3"  # route ids per task and condition
    expert_tasks: tuple[str, ...] = ("straight", "one_turn", "navigation", "regular")
    zoo_traffic_tasks: tuple[str, ...] = ("regular",)  # the zoo YILRatt also drives these, in traffic
    zoo_traffic_routes: str = "0:2"  # route ids of those per condition (NoCrash Regular: long routes)
    seeds: int = 1
    bench_workers: int = 2
    explain_frames: int = 6
    video_steps: int = 200

    def __post_init__(self) -> None:
        """Every option checked before the first stage: a typo used to surface at stage 4, after the
        collection and two trainings."""
        from yawil.bench.suites import parse_range

        for name in ("frames", "baseline_steps", "video_steps", "batch_size", "epochs", "seeds"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"demo: {name}={value!r}, expected an integer >= 1")
        if not isinstance(self.max_steps, int) or isinstance(self.max_steps, bool) or self.max_steps < 0:
            raise ValueError(f"demo: max_steps={self.max_steps!r}, expected an integer >= 0 (0: YILRatt from the zoo only)")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise ValueError(f"demo: max_minutes={self.max_minutes!r}, expected minutes > 0 (or none)")
        parse_range(self.routes, 25)  # the suites' 25 routes per task; names the bad --routes
        parse_range(self.zoo_traffic_routes, 25)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "demo",
        help="the whole loop at a small scale -> OUT/report.html",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--seed", type=seed, default=0, help="seed of collection, training and benchmark (default 0)")
    p.add_argument("--frames", type=int, default=DemoBudget.frames, help=f"frames to collect (default {DemoBudget.frames})")
    p.add_argument("--yilratt-steps", "--max-steps", dest="max_steps", type=int, default=DemoBudget.max_steps,
                   help="also train the paper's YILRatt here for this many steps (default 0: drive the zoo's only)")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="an explicit wall-time cap of each training (default: none; the budgets are steps)")
    p.add_argument("--baseline-steps", type=int, default=DemoBudget.baseline_steps,
                   help=f"training steps of the {DemoBudget.baseline} baseline (default {DemoBudget.baseline_steps})")
    p.add_argument("--routes", default=DemoBudget.routes, help=f"benchmark route ids per task (default {DemoBudget.routes})")
    p.add_argument("--video-steps", type=int, default=DemoBudget.video_steps, help="steps of the explained episode")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.fileio import check_pipeline_folder, claimed_output_folder

    budget = DemoBudget(
        frames=args.frames,
        max_steps=args.max_steps,
        max_minutes=args.max_minutes,
        baseline_steps=args.baseline_steps,
        routes=args.routes,
        video_steps=args.video_steps,
    )
    check_pipeline_folder(args.out, "--out", "demo", signature=("stages", "data"))
    with claimed_output_folder(args.out, "demo") as out:  # a refusal before the first stage leaves no folder
        run_demo(out, budget, seed=args.seed)
    return 0


def _say(msg: str) -> None:
    print(f"[demo {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _stage(out: Path, name: str) -> Path:
    return out / "stages" / f"{name}.json"


def _done(out: Path, name: str) -> dict[str, Any] | None:
    return read_marker(_stage(out, name))


def _mark(out: Path, name: str, info: dict[str, Any]) -> None:
    write_marker(_stage(out, name), info)


def _train(out: Path, stage: str, what: str, model: str, data: Path, run_dir: Path, max_steps: int,
           budget: DemoBudget, seed: int, ema: float = 0.0) -> dict[str, Any]:
    """One resumable training stage of the demo; returns its marker (steps, epochs, best_val, seconds)."""
    info = _done(out, stage)
    if info is not None:
        return info
    from yawil.learn.config import TrainConfig
    from yawil.learn.loop import train

    cap = f" / {budget.max_minutes} min" if budget.max_minutes else ""
    _say(f"{what} for {max_steps} steps{cap} -> {run_dir}")
    t = time.perf_counter()
    cfg = TrainConfig(
        model=model, data=[str(data)], out=str(run_dir), epochs=budget.epochs, batch_size=budget.batch_size,
        lr=budget.lr, lr_step_epochs=budget.lr_step_epochs, max_steps=max_steps, max_minutes=budget.max_minutes,
        seed=seed, workers=1, ema=ema,
    )  # fmt: skip
    result = train(cfg, resume=(run_dir / "last.pt").is_file())
    info = {"seconds": time.perf_counter() - t, "steps": result.steps, "epochs": result.epochs_done,
            "best_val": result.best_val, "stopped_by": result.stopped_by}  # fmt: skip
    _mark(out, stage, info)
    return info


def demo_guidance(card: dict[str, Any]) -> Any:
    """The guidance the demo collects with: the zoo model's data reference (`explain` refuses frames of another),
    the paper's `route` for a card that names none."""
    from yawil.guidance import GuidanceConfig

    data = card.get("data") or {}
    return GuidanceConfig(reference=data.get("guidance_reference") or GuidanceConfig.reference)


def zoo_spec(name: str) -> Any:
    """The zoo model as its card drives it."""
    from yawil.bench.runner import AgentSpec
    from yawil.zoo import card_drive

    return AgentSpec(f"zoo:{name}", **card_drive(f"zoo:{name}"))


def run_demo(out: Path, budget: DemoBudget, seed: int = 0) -> Path:
    from yawil.fileio import make_folder
    from yawil.guidance import GuidanceConfig
    from yawil.zoo import read_card

    make_folder(out, "demo")
    t0 = time.perf_counter()
    _say(f"budget: {json.dumps(asdict(budget))}")
    card = read_card(budget.zoo_model)  # a missing zoo model fails before any stage
    guidance = demo_guidance(card)
    data = out / "data" / "town01"
    run_dir = out / "yilratt"
    base_dir = out / budget.baseline
    timings: dict[str, float] = {}

    # 1. collect
    info = _done(out, "collect")
    # a marker from before the reference was recorded names none: that demo collected the default (route)
    had = None if info is None else info.get("guidance_reference", GuidanceConfig.reference)
    if had is not None and had != guidance.reference:
        raise ValueError(f"{data}: collected by an earlier demo with the {had!r} yaw reference, but "
                         f"zoo:{budget.zoo_model} needs {guidance.reference!r}; remove {out} or give another --out")
    if info is None:
        from yawil.data.collect import collect

        _say(f"1/5 collecting {budget.frames} expert frames in town01 (training weathers, "
             f"{guidance.reference!r} yaw reference) -> {data}")
        t = time.perf_counter()
        summary = collect(data, town="town01", weathers="train", frames=budget.frames,
                          workers=budget.collect_workers, seed=seed, guidance=guidance)  # fmt: skip
        info = {"seconds": time.perf_counter() - t, "frames": summary.dataset_frames,
                "guidance_reference": guidance.reference}  # fmt: skip
        _mark(out, "collect", info)
    timings["collect"] = info["seconds"]

    # 2. train the small baseline (and YILRatt when asked) on that data
    trained = {budget.baseline: _train(out, "train_baseline", f"2/5 training {budget.baseline}", budget.baseline,
                                       data, base_dir, budget.baseline_steps, budget, seed, budget.baseline_ema)}
    timings["train_baseline"] = trained[budget.baseline]["seconds"]
    if budget.max_steps:
        trained["yilratt"] = _train(out, "train", f"2/5 training {budget.model}", budget.model, data, run_dir,
                                    budget.max_steps, budget, seed)
        timings["train"] = trained["yilratt"]["seconds"]

    # 3. benchmark the expert, the trained agents and the zoo's YILRatt on a subset of routes, both conditions
    info = _done(out, "bench")
    if info is None:
        from yawil.bench.runner import AgentSpec, run_benchmark
        from yawil.bench.suites import episodes

        t = time.perf_counter()
        conds = ["training", "new-town-weather"]
        zoo = f"zoo-{budget.zoo_model}"
        drivers = [("expert", AgentSpec("expert"), budget.expert_tasks, budget.routes),
                   (budget.baseline, AgentSpec(str(base_dir / "last.pt")), budget.tasks, budget.routes),
                   (zoo, zoo_spec(budget.zoo_model), budget.tasks, budget.routes)]
        if budget.zoo_traffic_tasks:  # the zoo model in traffic too, into its own results folder's other cells
            drivers.append((zoo, zoo_spec(budget.zoo_model), budget.zoo_traffic_tasks, budget.zoo_traffic_routes))
        if budget.max_steps:
            drivers.append(("yilratt", AgentSpec(str(run_dir / "best.pt")), budget.tasks, budget.routes))
        for label, spec, tasks, routes in drivers:
            # a subset of the protocol: route i in weather i mod n (`weather_rule` cycle), like the preset eval100
            eps = episodes("all", conds, list(tasks), routes=routes, seeds=budget.seeds, weather_rule="cycle")
            _say(f"3/5 benchmark: {label} on {len(eps)} episodes ({', '.join(tasks)}; routes {routes})")
            run_benchmark(eps, spec.validate(), out / "results" / label, workers=budget.bench_workers, label=label)
        info = {"seconds": time.perf_counter() - t}
        _mark(out, "bench", info)
    timings["bench"] = info["seconds"]

    # 4. the zoo YILRatt's heat maps and a video
    info = _done(out, "explain")
    if info is None:
        from yawil.agent import Agent
        from yawil.explain.attention import EpisodeVideo, explain_episode, explain_frames

        t = time.perf_counter()
        _say(f"4/5 attention heat maps of zoo:{budget.zoo_model} on dataset frames and one town02 episode video")
        spec = zoo_spec(budget.zoo_model)
        agent = Agent.from_checkpoint(f"zoo:{budget.zoo_model}", **spec.drive())
        explain_frames(agent, data, out / "explain", budget.explain_frames, seed, 0.5)
        episode = EpisodeVideo(route="one_turn:0", condition="new-town-weather", town="town02",
                               weather="SoftRainSunset", vehicles=0, pedestrians=0, seed=seed,
                               steps=budget.video_steps, every=2)  # fmt: skip
        video = explain_episode(agent, out / "explain", episode, alpha=0.5)
        info = {"seconds": time.perf_counter() - t, "video": video.name}
        _mark(out, "explain", info)
    timings["explain"] = info["seconds"]
    video_name = info["video"]

    # 5. report
    _say("5/5 report")
    report = write_demo_report(out, budget, timings, trained, card, video_name, time.perf_counter() - t0)
    _say(f"done: {report} (this invocation {time.perf_counter() - t0:.0f} s)")
    return report


def guard(out: Path, budget: DemoBudget, card: dict[str, Any]) -> list[tuple[str, int, int, int | None, bool]]:
    """(agent, successes, episodes, expected, ok) of the fresh baseline and the zoo YILRatt on the demo's
    episodes: a change that silently breaks learning or preprocessing shows here (and in `make test-all`).
    The zoo model is expected to drive what its card says of the default demo episodes (None: other episodes)."""
    from yawil.bench.records import read_records

    rows: list[tuple[str, int, int, int | None, bool]] = []
    demo = card.get("demo") or {}
    default = (budget.tasks, budget.routes, budget.seeds) == (DemoBudget.tasks, DemoBudget.routes, DemoBudget.seeds)
    for label, expected in ((budget.baseline, None), (f"zoo-{budget.zoo_model}", demo.get("successes"))):
        recs = [r for r in read_records(out / "results" / label / "episodes.jsonl") if r["task"] in budget.tasks]
        n, ok = len(recs), sum(bool(r["success"]) for r in recs)
        if label == budget.baseline:
            want: int | None = int(-(-budget.baseline_expected * n // 1))
        else:
            want = int(expected) if expected is not None and default else None
        rows.append((label, ok, n, want, want is None or ok >= want))
    return rows


def _counts(results: Path, tasks: tuple[str, ...] | None = None) -> tuple[int, int]:
    """(successes, episodes) of a results folder (of `tasks` only, when given)."""
    from yawil.bench.records import read_records

    recs = [r for r in read_records(results / "episodes.jsonl") if tasks is None or r["task"] in tasks]
    return sum(bool(r["success"]) for r in recs), len(recs)


def data_text(data: Any) -> str:
    if not isinstance(data, dict):
        return str(data)
    return f"{data.get('town')} {data.get('weathers')} weathers, {data.get('frames')} frames, seed {data.get('seed')}"


def write_demo_report(out: Path, budget: DemoBudget, timings: dict[str, float], train_info: dict[str, dict[str, Any]],
                      card: dict[str, Any], video_name: str, wall_s: float) -> Path:
    from yawil.bench.report import write_report
    from yawil.data.stats import write_stats
    from yawil.zoo import drive_flags

    first = f"{budget.tasks[-1]}/{int(budget.routes.split(':')[0] or 0)}/0"  # an episode both drove (Figure 6)
    names = ["expert", budget.baseline, f"zoo-{budget.zoo_model}", "yilratt"]
    results = [out / "results" / name for name in names]
    bench = write_report([r for r in results if r.is_dir()], out / "bench_report",
                         trajectories={"training": first, "new-town-weather": first})  # fmt: skip
    stats_png = write_stats(out / "data" / "town01", out / "data_stats.png")
    bench_md = bench["report.md"].read_text(encoding="utf-8").split("\n", 1)[1]
    bench_md = re.sub(r"\]\(([^)/]+\.png)\)", r"](bench_report/\1)", bench_md)  # its pictures live there
    pictures = [("Dataset (the paper's Figure 7)", stats_png,
                 "Frames per road option and weather, and the steer, throttle and brake histograms of the data."),
                (f"Loss curve ({budget.baseline})", out / budget.baseline / "loss.png",
                 "Training and validation loss per epoch of the baseline trained in this run (log scale)."),
                ("Loss curve (YILRatt trained here)", out / "yilratt" / "loss.png",
                 "Training and validation loss per epoch of the YILRatt trained in this run (log scale)."),
                (f"Attention heat maps of zoo:{budget.zoo_model} on dataset frames (Figure 8)",
                 out / "explain" / "grid.png",
                 "One row per frame: the camera, then the attention of each of YILRatt's attention layers over it "
                 "(brighter: more weight). Each row's label gives the network's outputs on that frame: s = steer, "
                 "t = throttle, b = brake, v = predicted speed (km/h).")]  # fmt: skip
    # the budget rows of what ran: the YILRatt training fields only when one was trained here
    skipped = () if budget.max_steps else ("model", "batch_size", "lr", "lr_step_epochs", "epochs", "max_steps")
    shown = {k: v for k, v in asdict(budget).items() if k not in skipped}
    budget_rows = "\n".join(f"| {k} | {v} |" for k, v in shown.items())
    time_rows = "\n".join(f"| {k} | {v:.0f} |" for k, v in timings.items())
    capped = [n for n, i in train_info.items() if i.get("stopped_by") == "max_minutes"]
    ev = card.get("eval100") or {}
    zoo_line = (f"zoo:{budget.zoo_model}: {card.get('model_name')}, {card.get('steps_total', card.get('step'))} steps, "
                f"commit {str(card.get('commit', '?'))[:10]}, data {data_text(card.get('data'))}, eval100 "
                f"{ev.get('successes', '?')}/{ev.get('episodes', '?')}, driven with "
                f"{drive_flags(card.get('drive') or {}) or 'its own throttle and brake'}. Made by these commands:")
    commands = [str(c) for c in card.get("commands") or []]
    trained = ", ".join(f"{n} ({i.get('steps')} steps, {i.get('epochs')} epochs, stopped by {i.get('stopped_by')})"
                        for n, i in train_info.items())
    provenance = (f"From the zoo: {zoo_line}\n\n" + "\n".join(f"    {c}" for c in commands)
                  + f"\n\nTrained in this run: {trained}.")
    checks = guard(out, budget, card)
    summary_rows = [("expert", "the privileged expert", *_counts(out / "results" / "expert"), "")] + [
        (label, "zoo" if label.startswith("zoo-") else "trained in this run", ok, n,
         "ok" if fine else "BELOW EXPECTATION") for label, ok, n, _, fine in checks]
    zoo_dir = out / "results" / f"zoo-{budget.zoo_model}"
    traffic = _counts(zoo_dir, budget.zoo_traffic_tasks) if budget.zoo_traffic_tasks and zoo_dir.is_dir() else (0, 0)
    if traffic[1]:
        summary_rows.append((f"zoo-{budget.zoo_model}, in traffic ({', '.join(budget.zoo_traffic_tasks)})",
                             "zoo", *traffic, "not guarded"))
    guard_line = "Guard: " + "; ".join(
        f"{label} drove {ok}/{n} " + (f"(expected at least {want}): {'ok' if fine else 'BELOW EXPECTATION'}"
                                      if want is not None else "(its card has no figure for these episodes)")
        for label, ok, n, want, fine in checks) + "."
    intro = ("The whole loop at a small scale on the embedded simulator: expert data in town01 (training weathers, "
             f"the {demo_guidance(card).reference!r} yaw reference of the zoo model's data), "
             f"the small {budget.baseline} baseline trained on it, the expert, that baseline and the zoo's YILRatt "
             "benchmarked on a subset of routes in both conditions (the zoo's YILRatt also in traffic: "
             f"{', '.join(budget.zoo_traffic_tasks) or 'none'}, routes {budget.zoo_traffic_routes}), the zoo "
             "YILRatt's attention heat maps. These "
             "are honest small-budget numbers, not the paper's: see the budget below.")
    cap_note = (f"Stopped by the --max-minutes cap: {', '.join(capped)} (its figures depend on the machine's "
                "speed)." if capped else "")
    md = [
        "# yawil demo report",
        "",
        "| agent | where it comes from | successes | episodes | guard |",
        "| --- | --- | --- | --- | --- |",
        *[f"| {a} | {src} | {ok} | {n} | {g} |" for a, src, ok, n, g in summary_rows],
        "",
        intro,
        "",
        provenance + (f" **{cap_note}**" if cap_note else ""),
        "",
        guard_line,
        "",
        bench_md,
        "## Budget",
        "",
        "| setting | value |",
        "| --- | --- |",
        budget_rows,
        "",
        "## Wall time per stage (seconds, first run of each stage)",
        "",
        "| stage | seconds |",
        "| --- | --- |",
        time_rows,
        "",
        f"Episode video with heat maps: [explain/{video_name}](explain/{video_name})",
        "",
    ]
    for title, path, caption in pictures:
        if Path(path).is_file():
            md.append(f"![{title}]({Path(path).relative_to(out)})\n\n*{caption}*\n")
    _write(out / "report.md", "\n".join(md))

    e = html.escape
    bench_html = bench["report.html"].read_text(encoding="utf-8")
    body = bench_html.split("<body>", 1)[1].rsplit("</body>", 1)[0].replace("<h1>Benchmark report</h1>", "<h2>Benchmark</h2>")
    style = bench_html.split("<style>", 1)[1].split("</style>", 1)[0] if "<style>" in bench_html else ""
    parts = [
        "<h1>yawil demo report</h1>",
        "<table><tr><th>agent</th><th>where it comes from</th><th>successes</th><th>episodes</th><th>guard</th></tr>"
        + "".join(f"<tr><td>{e(a)}</td><td>{e(src)}</td><td>{ok}</td><td>{n}</td><td>{e(g)}</td></tr>"
                  for a, src, ok, n, g in summary_rows) + "</table>",
        f"<p>{e(intro)}</p>",
        f"<p>From the zoo: {e(zoo_line)}</p><pre>{e(chr(10).join(commands))}</pre>",
        f"<p>Trained in this run: {e(trained)}.{(' <strong>' + e(cap_note) + '</strong>') if cap_note else ''}</p>",
        f"<p>{e(guard_line)}</p>",
        body,
        "<h2>Budget</h2><table><tr><th>setting</th><th>value</th></tr>"
        + "".join(f"<tr><td>{e(k)}</td><td>{e(str(v))}</td></tr>" for k, v in shown.items())
        + "</table>",
        "<h2>Wall time per stage (seconds)</h2><table><tr><th>stage</th><th>seconds</th></tr>"
        + "".join(f"<tr><td>{e(k)}</td><td>{v:.0f}</td></tr>" for k, v in timings.items())
        + "</table>",
    ]
    for title, path, caption in pictures:
        if Path(path).is_file():
            b64 = base64.b64encode(Path(path).read_bytes()).decode("ascii")
            parts.append(f"<figure><h3>{e(title)}</h3><img alt='{e(title)}' src='data:image/png;base64,{b64}'>"
                         f"<figcaption>{e(caption)}</figcaption></figure>")
    video = out / "explain" / video_name
    if video.is_file():
        mime = "video/mp4" if video.suffix == ".mp4" else "image/gif"
        b64 = base64.b64encode(video.read_bytes()).decode("ascii")
        tag = (f"<video controls loop src='data:{mime};base64,{b64}'></video>" if mime == "video/mp4"
               else f"<img alt='episode' src='data:{mime};base64,{b64}'>")  # fmt: skip
        parts.append(f"<h3>A town02 episode with the attention heat maps (Figure 9)</h3>{tag}")
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>yawil demo report</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")  # fmt: skip
    _write(out / "report.html", page)
    return out / "report.html"


def _write(path: Path, text: str) -> None:
    from yawil.fileio import write_atomic

    write_atomic(path, text)
