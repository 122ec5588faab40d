"""`yawil trace`: one benchmark episode, frame by frame, the agent's decision beside the expert's.

    yawil trace regular/training/HardRainNoon/6/0 --agent runs/x/last.pt --speed-control --out trace.csv

The agent drives exactly as `yawil bench` drives it (same world seed, same judge); on every frame the
privileged expert is asked what it would do in the same state, without driving. The CSV has, per frame: time,
speed, the agent's control and (models with an aux head) its target speed, the expert's control, target speed
and the reason that set it, and the lead vehicle the expert follows (distance to its stop point, speed); the
aux head's light probability (`agent_light_p`) beside the expert's label (`light_ahead`: a red or yellow stop line
within 30 m).
Why: a failure's cause is read off where the two columns part (a rear-end where the agent's target speed
stays at cruise while the expert's falls is a car the net did not see; one where both fall but too late is
a controller's lag). docs/experiments.md traces its rows' failures with it.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import sys
from dataclasses import dataclass
from typing import Any

from yawil.bench.metrics import EpisodeTracker
from yawil.bench.runner import AgentSpec, agent_device, drive_options
from yawil.bench.suites import Episode, episodes
from yawil.fileio import write_atomic
from yawil.policy.speed import add_engine_arguments, add_speed_control_arguments

COLUMNS = ("time", "speed", "steer", "throttle", "brake", "agent_target_speed", "agent_lead_stop_m", "agent_lead_speed",
           "expert_steer", "expert_throttle", "expert_brake", "expert_target_speed", "expert_reason", "lead_stop_m",
           "lead_speed", "agent_lead_stop_p", "agent_head_target_speed", "agent_light_p", "light_ahead")


@dataclass(frozen=True)
class TraceResult:
    frames: int
    success: bool
    reason: str | None
    time_s: float
    collisions: list[dict[str, Any]]


def find_episode(key: str, suite: str = "all") -> Episode:
    """The episode of a benchmark record key (task/condition/weather/route/seed), as `yawil bench` drives it."""
    parts = key.split("/")
    if len(parts) != 5 or not parts[3].isdigit() or not parts[4].isdigit():
        raise ValueError(f"episode {key!r}: expected task/condition/weather/route/seed, "
                         "e.g. regular/training/HardRainNoon/6/0 (the key of a record)")
    task, condition, _, route, seed = parts
    try:
        found = [e for e in episodes(suite, conditions=[condition], tasks=[task], routes=route, seeds=int(seed) + 1)
                 if e.key == key]
    except ValueError as err:  # the suite's words (--routes, --tasks) name options trace does not have
        raise ValueError(f"episode {key!r}: {str(err).replace('--routes', 'route').replace('--', '')}") from None
    if not found:
        raise ValueError(f"episode {key!r}: not an episode of suite {suite!r} (check the weather: it must be one "
                         "of the condition's)")
    return found[0]


def trace_episode(ep: Episode, spec: AgentSpec, out: str | os.PathLike[str], expert_args: tuple[str, ...] = (),
                  camera: bool = True, progress: bool = False) -> TraceResult:
    """Drive `ep` with `spec`'s agent, the expert (`expert_args`: its settings) shadowing every frame; write the
    CSV to `out` (through a temporary file, renamed when whole). `progress`: a bar of simulated seconds."""
    from tqdm import tqdm

    from yawil.data.episode import expert_labels
    from yawil.expert import Expert, ExpertConfig
    from yawil.sim import make_world

    world = make_world(backend="embedded")
    bar = tqdm(total=round(ep.timeout_s, 1), unit="sim s", disable=not progress, dynamic_ncols=True,
               bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} simulated s [{elapsed}]")
    try:
        obs = world.reset(ep.scenario(camera), seed=ep.world_seed)
        agent = spec.build(ep.world_seed)
        agent.reset()
        expert = Expert(ExpertConfig.from_items(expert_args))
        goal = obs.route.xy[-1]
        tracker = EpisodeTracker(goal_xy=(float(goal[0]), float(goal[1])), timeout_s=ep.timeout_s)
        tracker.start(obs)
        rows: list[list[Any]] = []
        while True:
            shadow = expert.act(obs)
            st = expert.state
            leads = [h for h in st.hazards if h.reason == "vehicle"]
            lead = min(leads, key=lambda h: h.distance) if leads else None
            control = agent.act(obs)
            last = getattr(agent, "last", None)
            target, a_lead, a_lead_v, a_stop, head, a_light = (getattr(last, k, None) for k in (
                "target_speed", "lead_distance", "lead_speed", "lead_stop", "head_target_speed", "light"))
            rows.append([
                round(obs.time, 2), round(obs.speed, 3), round(control.steer, 4), round(control.throttle, 4),
                round(control.brake, 4), "" if target is None else round(target, 3),
                "" if a_lead is None else round(a_lead, 2), "" if a_lead_v is None else round(a_lead_v, 2),
                round(shadow.steer, 4),
                round(shadow.throttle, 4), round(shadow.brake, 4), round(st.target_speed, 3), st.reason,
                "" if lead is None else round(lead.distance, 2), "" if lead is None else round(lead.speed, 2),
                "" if a_stop is None else round(a_stop, 3), "" if head is None else round(head, 3),
                "" if a_light is None else round(a_light, 3), expert_labels(st)["light_ahead"],
            ])
            obs = world.step(control)
            bar.update(round(obs.time, 1) - bar.n)
            if tracker.update(obs):
                break
    finally:
        bar.close()
        world.close()
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(COLUMNS)
    w.writerows(rows)
    write_atomic(out, text.getvalue())
    res = tracker.result()
    return TraceResult(len(rows), bool(res["success"]), res["reason"], float(res["time_s"]), list(res["collisions"]))


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "trace", help="one benchmark episode frame by frame: the agent's decision beside the expert's (CSV)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("episode", help="the record key task/condition/weather/route/seed, e.g. regular/training/WetNoon/1/0")
    p.add_argument("--agent", required=True, help="a checkpoint, zoo:NAME, or 'expert' (the expert shadowing itself)")
    p.add_argument("--out", required=True, help="the CSV file to write")
    p.add_argument("--force", action="store_true", help="replace an existing output file (never one inside a dataset, run, results or zoo folder)")
    p.add_argument("--suite", default="all", help="the suite the episode belongs to (default all)")
    add_speed_control_arguments(p, "as yawil bench: ")
    add_engine_arguments(p)
    p.add_argument("--expert-arg", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting of the shadowing expert's ExpertConfig (and of the agent, with --agent expert)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda", "auto"),
                   help="where a learned agent's model runs (default cpu), as yawil bench --device")
    p.add_argument("--tail", type=int, default=0, help="also print the last N rows")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (simulated seconds of the episode)")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.fileio import check_output_file

    if args.tail < 0:  # lines[-(-3):] would print all but the first 3 rows
        raise ValueError(f"--tail {args.tail}: expected a number of rows >= 0")
    check_output_file(args.out, "--out", args.force)  # before the episode is driven
    expert_args = tuple(args.expert_arg)
    spec = AgentSpec(args.agent, **drive_options(args),
                     expert_args=expert_args if args.agent == "expert" else (),
                     device=agent_device(args.device), engine=args.engine).validate()
    ep = find_episode(args.episode, args.suite)
    res = trace_episode(ep, spec, args.out, expert_args, progress=not args.no_progress)
    end = "success" if res.success else (res.reason or "unfinished")
    first = res.collisions[0] if res.collisions else None
    hit = "" if first is None else f"; hit {first.get('type')} at t={first.get('t')} s" + (
        " (rear-end)" if first.get("rear_end") else "")
    print(f"{args.out}: {res.frames} frames, {end} at {res.time_s:.1f} s{hit}")
    if args.tail > 0:
        with open(args.out) as fh:
            lines = fh.read().splitlines()
        sys.stdout.write("\n".join([lines[0], *lines[-args.tail:]]) + "\n")
    return 0
