"""Choosing a checkpoint by driving (closed-loop validation), beside the paper's lowest-validation-loss rule.

Offline loss is a poor proxy for driving (Codevilla et al. 2018, "On Offline Evaluation of Vision-based
Driving Models"; measured here: a 2e-7 change of the blur augmentation moved `best.pt` of the demo's
baseline from a 425-step model that drove 10 of 12 episodes to an 85-step one that drove 1). So each
candidate drives a small validation set in the training town, on routes and world seeds the benchmark never
uses, and the one with the most successes wins (ties: fewer collisions, then the later checkpoint).

    yawil select runs/x/step_000375.pt runs/x/step_000750.pt runs/x/last.pt --out results/x-select
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from yawil.bench.suites import TASKS, Episode, RouteSpec, load_routes
from yawil.policy.speed import add_engine_arguments, add_speed_control_arguments, given_drive
from yawil.sim.weather import TRAIN_WEATHERS

VALIDATION_ROUTE_SEED = 101  # route draw of the validation set (the committed benchmark routes use seed 0)
VALIDATION_SEED = 1000  # Episode.seed of validation episodes: world seeds 1000 * 1000 + id, above the benchmark's
VALIDATION_TASKS: tuple[str, ...] = ("one_turn", "navigation", "regular", "dense")
SAME_ROUTE_M = 10.0  # a route whose start and goal both lie this close to a benchmark route's is that route


class BenchmarkRoutes:
    """Recognises a benchmark route of a town (same start and goal within SAME_ROUTE_M), so that data
    collection (DAgger) and checkpoint selection never drive one."""

    def __init__(self, town: str) -> None:
        try:
            tasks = load_routes(town)
        except (FileNotFoundError, ValueError):
            tasks = {}  # a town without benchmark routes (a custom layout) has nothing to avoid
        ends = [(r.start.x, r.start.y, r.goal.x, r.goal.y) for routes in tasks.values() for r in routes]
        self.ends = np.asarray(ends, dtype=np.float64).reshape(-1, 4)

    def matches(self, start_xy: Sequence[float], goal_xy: Sequence[float]) -> bool:
        if not len(self.ends):
            return False
        d_start = np.hypot(self.ends[:, 0] - start_xy[0], self.ends[:, 1] - start_xy[1])
        d_goal = np.hypot(self.ends[:, 2] - goal_xy[0], self.ends[:, 3] - goal_xy[1])
        return bool(np.any((d_start < SAME_ROUTE_M) & (d_goal < SAME_ROUTE_M)))

    def __call__(self, route: Any) -> bool:
        """True for a planned Route (or anything with `xy`) that is a benchmark route."""
        xy = np.asarray(route.xy, dtype=np.float64)
        return self.matches(xy[0], xy[-1])


def validation_episodes(town: str = "town01", tasks: Sequence[str] = VALIDATION_TASKS, routes: int = 3) -> list[Episode]:
    """`routes` episodes per task: freshly drawn routes of the task's kind, none of them a benchmark route,
    in the training weathers, with the task's traffic and world seeds above the benchmark's."""
    from yawil.bench.routegen import generate_routes

    if routes < 1:
        raise ValueError(f"validation routes per task must be >= 1, got {routes}")
    lists = generate_routes(town, seed=VALIDATION_ROUTE_SEED)
    bench = BenchmarkRoutes(town)
    out: list[Episode] = []
    for name in tasks:
        task = TASKS[name]
        fresh = [r for r in lists[task.routes] if not bench.matches((r.start.x, r.start.y), (r.goal.x, r.goal.y))]
        if len(fresh) < routes:
            raise ValueError(f"only {len(fresh)} validation {task.routes} routes on {town}, {routes} asked for")
        for spec in fresh[:routes]:
            spec = RouteSpec(spec.id, spec.start, spec.goal, spec.length_m, spec.turns, spec.kind)
            out.append(Episode("validation", name, "validation", spec, VALIDATION_SEED, town,
                               TRAIN_WEATHERS[spec.id % len(TRAIN_WEATHERS)], task.vehicles, task.pedestrians))
    return out


def candidate_label(path: Path) -> str:
    return f"{path.resolve().parent.name}_{path.stem}"


def select_checkpoint(checkpoints: Sequence[Path], out: Path, routes: int = 3, workers: int = 1,
                      progress: bool = True, drive: Mapping[str, Any] | None = None, engine: str = "auto",
                      episodes_per_worker: int | None = None) -> dict[str, Any]:
    """Drive every candidate on the validation set (resumable per episode), write OUT/selection.json. `drive`:
    how every candidate is driven (keyword options of `AgentSpec`: speed_control, stop_release, ...)."""
    from yawil.bench.records import read_records
    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.fileio import write_json_atomic
    from yawil.policy.checkpoint import load_checkpoint

    if not checkpoints:
        raise ValueError("select: give at least one checkpoint")
    labels = [candidate_label(Path(c)) for c in checkpoints]
    if len(set(labels)) != len(labels):
        raise ValueError(f"select: candidates must differ in folder or file name, got {labels}")
    eps = validation_episodes(routes=routes)
    # every candidate read and its agent built before any is driven: a bad last one fails in seconds, not hours
    specs = [AgentSpec(str(path), engine=engine, **(drive or {})).validate() for path in checkpoints]
    rows: list[dict[str, Any]] = []
    for path, label, spec in zip(checkpoints, labels, specs, strict=True):
        ck = load_checkpoint(path, map_location="cpu")
        run_benchmark(eps, spec, out / label, workers=workers, progress=progress, label=label,
                      episodes_per_worker=episodes_per_worker)
        recs = read_records(out / label / "episodes.jsonl")
        metrics = ck.get("metrics") or []
        rows.append({
            "checkpoint": str(path), "label": label, "step": int(ck.get("step", 0)),
            "val_loss": metrics[-1]["val_loss"] if metrics else None,
            "episodes": len(recs), "successes": sum(bool(r["success"]) for r in recs),
            "collisions": sum(bool(r.get("collisions")) for r in recs),
            "km_driven": round(sum(float(r["km_driven"]) for r in recs), 3),
        })
    best = max(rows, key=lambda r: (r["successes"], -r["collisions"], r["step"]))
    result = {"rule": "most validation successes; ties: fewer collisions, then the later step",
              "episodes": len(eps), "tasks": list(VALIDATION_TASKS), "routes_per_task": routes,
              "selected": best["checkpoint"], "candidates": rows}
    write_json_atomic(out / "selection.json", result)
    return result


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "select", help="choose a checkpoint by driving validation episodes (closed-loop selection)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("checkpoints", nargs="+",
                   help="candidate checkpoints (e.g. step_*.pt, best.pt, last.pt, or zoo:NAME)")
    p.add_argument("--out", required=True, help="results folder: one sub-folder per candidate, selection.json")
    p.add_argument("--routes", type=int, default=3, help=f"routes per task of {', '.join(VALIDATION_TASKS)} (default 3)")
    p.add_argument("--workers", type=int, default=1, help="processes driving episodes (default 1)")
    add_speed_control_arguments(p, "as yawil bench: ")
    add_engine_arguments(p, batched=True)
    p.add_argument("--link", default=None, help="also make this path a hard link of the selected checkpoint")
    p.add_argument("--force", action="store_true", help="let --link replace an existing file (never one inside a "
                   "dataset, run, results or zoo folder)")
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args: argparse.Namespace) -> int:
    try:
        from yawil.zoo import resolve_checkpoint

        paths = [resolve_checkpoint(c) for c in args.checkpoints]  # zoo:NAME: a zoo model as a candidate
        for p in paths:
            if not p.is_file():
                raise ValueError(f"{p}: no such checkpoint file")
        from yawil.fileio import check_output_file, check_pipeline_folder, claimed_output_folder

        # a folder from before the mark: its selection.json, or a candidate's results folder (stopped while driving)
        check_pipeline_folder(args.out, "--out", "select",
                              signature=("selection.json", *(candidate_label(p) for p in paths)))
        if args.link:
            check_output_file(args.link, "--link", args.force)  # before any candidate is driven
        with claimed_output_folder(args.out, "select") as out:  # a refused candidate leaves no folder
            result = select_checkpoint(paths, out, args.routes, args.workers, not args.no_progress,
                                       given_drive(args), args.engine, args.episodes_per_worker)
        if args.link:
            from yawil.learn.artifacts import link_or_copy

            link_or_copy(Path(result["selected"]), Path(args.link))
    except (ValueError, OSError) as err:
        print(f"yawil select: {err}", file=sys.stderr)
        return 2
    for row in result["candidates"]:
        print(f"{row['label']}: {row['successes']}/{row['episodes']} successes, {row['collisions']} collisions, "
              f"step {row['step']}, val_loss {row['val_loss']}")
    print(f"selected {result['selected']} ({json.dumps(result['rule'])})")
    return 0
