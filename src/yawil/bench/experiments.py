"""The square experiments of the paper: Table I (road-option methods x datasets) and Table II (noise).

`square_experiment(out, profile)` runs every stage and skips a stage whose output exists, so it resumes:
    collect (expert on the square, no traffic) -> subsets (1) road-option turns, (2) lane-follow turns,
    (3) both -> train 4 methods x 3 datasets = 12 models -> drive the 32 turning tasks -> Table I.
`noise_experiment(out, profile)` drives again the models that passed all 32 tasks: guided models with yaw
noise sigma 10/20/30 deg, CIL with wrong commands (5 frames) at 3/5/10 %, 5 seeds, mean +- std -> Table II.

Profiles (`PROFILES`): `paper` follows the paper (full training settings); `standard` is the budget of a
2-core laptop (about an hour for Table I: 16k frames, 600 steps of 64 per model, two models trained side by
side on one thread each), whose numbers are the ones in docs/benchmark.md; `quick` is a minutes-scale smoke
run of the same pipeline on tiny budgets, whose numbers mean nothing beyond "the loop works".
Budgets are in optimiser steps, not minutes, so that a profile gives the same models on any machine.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from yawil.bench.metrics import mean_std
from yawil.bench.records import episode_key, iter_results
from yawil.fileio import make_folder, write_json_atomic
from yawil.stages import read_marker, write_marker

METHODS: tuple[tuple[str, str], ...] = (
    ("xy-guided", "XY-guided"),
    ("yaw-guided", "Yaw-guided"),
    ("cil", "CIL"),
    ("simyaw-guided", "Sim-yaw IL"),
)
DATASETS: tuple[tuple[str, str, str], ...] = (
    # (folder, `yawil data subset --only` value, table row)
    ("subset1", "road-option-turns", "Subset (1): road-option turns"),
    ("subset2", "lane-follow-turns", "Subset (2): lane-follow turns"),
    ("full", "all", "Full dataset"),
)
YAW_SIGMAS = (10.0, 20.0, 30.0)
COMMAND_PS = (0.03, 0.05, 0.10)
NOISE_SEEDS = 5
GUIDED_YAW = ("yaw-guided", "simyaw-guided")  # yaw noise applies to yaw guidance (not to XY coordinates)


@dataclass(frozen=True)
class Profile:
    name: str
    frames: int  # expert frames collected on the square (full dataset)
    collect_workers: int
    epochs: int
    batch_size: int
    max_steps: int | None  # per model
    max_minutes: float | None  # per model
    routes: str | None  # which of the 32 tasks are driven (None: all)
    noise_seeds: int
    drive_workers: int
    train_workers: int = 1  # models trained side by side (processes)
    train_threads: int = 0  # torch threads per training process (0: the trainer's default)


PROFILES: dict[str, Profile] = {
    "quick": Profile("quick", frames=6000, collect_workers=2, epochs=2, batch_size=64, max_steps=40,
                     max_minutes=None, routes="0:32:4", noise_seeds=2, drive_workers=2),
    "standard": Profile("standard", frames=16000, collect_workers=2, epochs=100, batch_size=64, max_steps=600,
                        max_minutes=None, routes=None, noise_seeds=NOISE_SEEDS, drive_workers=2,
                        train_workers=2, train_threads=1),
    "paper": Profile("paper", frames=60000, collect_workers=2, epochs=100, batch_size=512, max_steps=None,
                     max_minutes=None, routes=None, noise_seeds=NOISE_SEEDS, drive_workers=2),
}


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}; choose one of {', '.join(PROFILES)}")
    return PROFILES[name]


Log = Callable[[str], None]


def _done(path: Path) -> bool:
    return read_marker(path / ".done") is not None


def _mark(path: Path, info: dict[str, Any]) -> None:
    write_marker(path / ".done", info)


def collect_stage(out: Path, p: Profile, seed: int, log: Log) -> Path:
    data = out / "data" / "full"
    if _done(data):
        log(f"collect: {data} done, skipped")
        return data
    from yawil.data.collect import CollectConfig, collect

    log(f"collect: {p.frames} expert frames on the square -> {data}")
    summary = collect(data, town="square", weathers="ClearNoon", frames=p.frames, workers=p.collect_workers,
                      seed=seed, config=CollectConfig(vehicles=(0, 0), pedestrians=(0, 0)))  # fmt: skip
    log(f"collect: wrote {summary.episodes_written} episodes, {summary.frames_written} frames; "
        f"dataset now {summary.dataset_frames} frames")
    _mark(data, {"frames": p.frames, "seed": seed})
    return data


def subset_stage(out: Path, full: Path, log: Log) -> dict[str, Path]:
    paths = {"full": full}
    for folder, only, _ in DATASETS:
        if folder == "full":
            continue
        dst = out / "data" / folder
        if _done(dst):
            log(f"subset: {dst} done, skipped")
        else:
            from yawil.data.subset import write_subset

            log(f"subset: {only} -> {dst}")
            write_subset(full, dst, only, quiet=False)
            _mark(dst, {"only": only})
        paths[folder] = dst
    return paths


def _trained(out: Path, dataset: str, model: str) -> Path | None:
    """The best.pt of a finished training stage, or None."""
    run = out / "models" / dataset / model
    return run / "best.pt" if _done(run) and (run / "best.pt").exists() else None


def train_stage(out: Path, data: Path, dataset: str, model: str, p: Profile, seed: int, log: Log) -> Path:
    from yawil.learn.config import TrainConfig
    from yawil.learn.loop import train

    run = out / "models" / dataset / model
    best = run / "best.pt"
    if _trained(out, dataset, model):
        log(f"train: {run} done, skipped")
        return best
    cfg = TrainConfig(model=model, data=[str(data)], out=str(run), epochs=p.epochs, batch_size=p.batch_size,
                      max_steps=p.max_steps, max_minutes=p.max_minutes, seed=seed, progress=False,
                      threads=p.train_threads)
    resume = (run / "last.pt").exists()
    log(f"train: {model} on {dataset} -> {run}{' (resumed)' if resume else ''}")
    result = train(cfg, resume=resume)
    if not best.exists():
        raise RuntimeError(f"training {run} ended ({result.stopped_by}) without a best.pt")
    _mark(run, {"epochs": result.epochs_done, "steps": result.steps, "best_val": result.best_val})
    return best


def train_all(root: Path, data: dict[str, Path], jobs: Sequence[tuple[str, str]], p: Profile, seed: int,
              log: Log) -> dict[tuple[str, str], Path]:
    """Train every (dataset, method), `p.train_workers` at a time in separate processes.

    Side by side on one thread each beats one run on two threads on a small CPU (docs/performance.md).
    Each run is still deterministic given its seed; a failed run raises after the others have finished.
    """
    if p.train_workers <= 1:
        return {(d, m): train_stage(root, data[d], d, m, p, seed, log) for d, m in jobs}
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    out: dict[tuple[str, str], Path] = {}
    todo = []
    for d, m in jobs:
        if _trained(root, d, m):
            out[(d, m)] = train_stage(root, data[d], d, m, p, seed, log)  # logs the skip
        else:
            todo.append((d, m))
    with ProcessPoolExecutor(p.train_workers, mp_context=get_context("spawn")) as pool:
        futures = {(d, m): pool.submit(train_stage, root, data[d], d, m, p, seed, print) for d, m in todo}
        errors = []
        for key, fut in futures.items():
            try:
                out[key] = fut.result()
            except Exception as err:  # noqa: BLE001 - reported together below
                errors.append(f"{key[0]}/{key[1]}: {err}")
    if errors:
        raise RuntimeError("training failed: " + "; ".join(errors))
    return out


def drive(ckpt: Path, results: Path, p: Profile, seeds: int, log: Log, yaw_noise_deg: float = 0.0,
          command_noise_p: float = 0.0, yaw_noise_mode: str = "raw",
          command_noise_mode: str = "burst-start") -> list[dict[str, Any]]:
    """Drive the square tasks with one agent (resumable); returns its records."""
    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.bench.suites import episodes

    eps = episodes("square", routes=p.routes, seeds=seeds)
    spec = AgentSpec(str(ckpt), yaw_noise_deg, command_noise_p, yaw_noise_mode=yaw_noise_mode,
                     command_noise_mode=command_noise_mode)
    summary = run_benchmark(eps, spec, results, workers=p.drive_workers, progress=False)
    log(f"drive: {results.name}: {summary.ran} run, {summary.skipped} resumed")
    keys = {e.key for e in eps}
    return [r for r in iter_results(results) if episode_key(r) in keys]


def _n_tasks(p: Profile) -> int:
    from yawil.bench.suites import SQUARE_TASKS, parse_range

    return len(parse_range(p.routes, SQUARE_TASKS))


def table1_markdown(cells: dict[tuple[str, str], int], n_tasks: int, profile: str) -> str:
    """Table I: successes out of the tasks driven, datasets x methods."""
    head = "| Dataset | " + " | ".join(t for _, t in METHODS) + " |"
    lines = ["### Table I: number of successes on the square's turning tasks", "", head, "|---" * (len(METHODS) + 1) + "|"]
    for folder, _, title in DATASETS:
        row = [str(cells[(folder, m)]) if (folder, m) in cells else "—" for m, _ in METHODS]
        lines.append(f"| {title} | " + " | ".join(row) + " |")
    lines += ["", f"Successes out of {n_tasks} turning tasks (profile `{profile}`, seed 0)."]
    return "\n".join(lines) + "\n"


def square_experiment(out: str | Path, profile: str = "quick", seed: int = 0, log: Log = print) -> Path:
    """Every stage of Table I; returns the path of table1.md."""
    p = get_profile(profile)
    root = make_folder(out, "experiment")
    write_json_atomic(root / "profile.json", asdict(p))
    full = collect_stage(root, p, seed, log)
    data = subset_stage(root, full, log)
    jobs = [(folder, model) for folder, _, _ in DATASETS for model, _ in METHODS]
    ckpts = train_all(root, data, jobs, p, seed, log)
    cells: dict[tuple[str, str], int] = {}
    for folder, model in jobs:
        recs = drive(ckpts[(folder, model)], root / "results" / f"{folder}-{model}", p, 1, log)
        cells[(folder, model)] = sum(bool(r["success"]) for r in recs)
    n = _n_tasks(p)
    write_json_atomic(root / "table1.json", {"n_tasks": n, "profile": profile,
                                             "cells": {f"{d}/{m}": v for (d, m), v in cells.items()}})
    table = root / "table1.md"
    table.write_text(table1_markdown(cells, n, profile), encoding="utf-8")
    log(table.read_text(encoding="utf-8"))
    return table


def noise_candidates(root: Path, models: Sequence[str] | None = None) -> tuple[list[tuple[str, str]], str]:
    """(dataset folder, model) pairs to test with noise: those that passed every task of Table I.

    If none did (typical of the quick profile), the full-dataset models of the noise-relevant methods are
    used instead and the returned note says so.
    """
    path = root / "table1.json"
    if not path.exists():
        raise ValueError(f"{path} not found: run `yawil experiment square --out {root}` first")
    doc = json.loads(path.read_text(encoding="utf-8"))
    n = int(doc["n_tasks"])
    wanted = set(models) if models else {*GUIDED_YAW, "cil"}
    passed = [tuple(k.split("/")) for k, v in doc["cells"].items() if int(v) == n]
    chosen = [(d, m) for d, m in passed if m in wanted]
    if chosen:
        return [(str(d), str(m)) for d, m in chosen], f"models with {n}/{n} successes in Table I"
    return [("full", m) for m in sorted(wanted)], f"no model passed all {n} tasks: full-dataset models used instead"


_NOISE_TEXT: dict[str, str] = {
    "raw": "Yaw noise: Gaussian on each waypoint's raw heading every frame, before the reference is subtracted.",
    "independent": "Yaw noise: Gaussian on each component of the guidance vector every frame, after the "
                   "reference is subtracted.",
    "burst-start": "CIL: a wrong command for 5 consecutive frames, started with probability p on each frame "
                   "without a burst.",
    "frame-share": "CIL: a share p of the frames carry a wrong command, in bursts of 5 consecutive frames.",
}


def noise_experiment(out: str | Path, profile: str = "quick", models: Sequence[str] | None = None,
                     log: Log = print, seeds: int | None = None, yaw_noise_mode: str = "raw",
                     command_noise_mode: str = "burst-start") -> Path:
    """Table II from the Table I models; returns the path of table2.md. `seeds` overrides the profile's.

    The readings of the two noises (`yawil.guidance`): the defaults raw / burst-start write table2.md and
    noise/<tag>; any other pair writes table2_<yaw>_<command>.md and noise/<tag>_<reading>, beside them.
    """
    from yawil.guidance import COMMAND_NOISE_MODES, YAW_NOISE_MODES

    if yaw_noise_mode not in YAW_NOISE_MODES or command_noise_mode not in COMMAND_NOISE_MODES:
        raise ValueError(f"noise readings {yaw_noise_mode!r} / {command_noise_mode!r}: expected one of "
                         f"{', '.join(YAW_NOISE_MODES)} / {', '.join(COMMAND_NOISE_MODES)}")
    default = (yaw_noise_mode, command_noise_mode) == ("raw", "burst-start")
    p = get_profile(profile)
    if seeds is not None:
        if seeds < 1:
            raise ValueError(f"noise seeds must be >= 1, got {seeds}")
        p = replace(p, noise_seeds=seeds)
    root = Path(out)
    chosen, note = noise_candidates(root, models)
    n = _n_tasks(p)
    rows: list[str] = []
    data: dict[str, Any] = {"note": note, "n_tasks": n, "seeds": p.noise_seeds, "rows": {}}
    for dataset, model in chosen:
        ckpt = root / "models" / dataset / model / "best.pt"
        if not ckpt.exists():
            raise ValueError(f"{ckpt} not found: the square experiment did not train {model} on {dataset}")
        if model == "cil":
            levels, kind = COMMAND_PS, "command"
        elif model in GUIDED_YAW:
            levels, kind = YAW_SIGMAS, "yaw"
        else:
            log(f"noise: {model} takes XY coordinates, yaw noise does not apply; skipped")
            continue
        cells = []
        reading = yaw_noise_mode if kind == "yaw" else command_noise_mode
        for level in levels:
            tag = f"{dataset}-{model}-{kind}{level:g}" + ("" if reading in ("raw", "burst-start") else f"_{reading}")
            recs = drive(ckpt, root / "noise" / tag, p, p.noise_seeds, log,
                         yaw_noise_deg=level if kind == "yaw" else 0.0,
                         command_noise_p=level if kind == "command" else 0.0,
                         yaw_noise_mode=yaw_noise_mode, command_noise_mode=command_noise_mode)
            per_seed = [sum(bool(r["success"]) for r in recs if r["seed"] == s) for s in range(p.noise_seeds)]
            st = mean_std(per_seed)
            cells.append(st.format(2))
            data["rows"][tag] = {"per_seed": per_seed, "mean": st.value, "std": st.std}
        label = dict(METHODS)[model] + ("" if dataset == "full" else f" ({dataset})")
        head = "N(0, σ²), σ = " + " / ".join(f"{s:g}°" for s in YAW_SIGMAS) if kind == "yaw" else \
            "wrong command p = " + " / ".join(f"{q:.0%}" for q in COMMAND_PS)
        rows.append(f"| {label} | {head} | " + " | ".join(cells) + " |")
    lines = ["### Table II: number of successes with noise", "",
             "| Model | Noise | low | middle | high |", "|---|---|---|---|---|", *rows, "",
             f"Mean ± population std over {p.noise_seeds} seeds of the successes out of {n} tasks; {note}. "
             + _NOISE_TEXT[yaw_noise_mode] + " " + _NOISE_TEXT[command_noise_mode]]
    data["readings"] = {"yaw": yaw_noise_mode, "command": command_noise_mode}
    stem = "table2" if default else f"table2_{yaw_noise_mode}_{command_noise_mode}"
    write_json_atomic(root / f"{stem}.json", data)
    table = root / f"{stem}.md"
    table.write_text("\n".join(lines) + "\n", encoding="utf-8")
    log(table.read_text(encoding="utf-8"))
    return table
