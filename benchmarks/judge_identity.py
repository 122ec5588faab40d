"""Behaviour-identity check of the episode judge (issue 15 item 3): same events in the same order, same observations.

Two parts, each run on the code before a change and after it, then compared:

1. Benchmark records: the expert on the 250 single-seed benchmark episodes, camera off (run from a
   `git worktree add /tmp/judge_base <old commit>` checkout with `PYTHONPATH=/tmp/judge_base/src` for "before"):

       yawil bench --suite all --condition training,new-town-weather --seeds 1 --weather-rule cycle \\
           --agent expert --workers 2 --no-camera --no-progress --out /tmp/judge_before   # and /tmp/judge_after
       .venv/bin/python benchmarks/judge_identity.py records /tmp/judge_before /tmp/judge_after

   compares every field of every record but `wall_s`, matched on (task, condition, weather, route_id, seed).

2. Step traces: the expert drives fixed embedded scenarios with traffic (collisions, lane invasions, lights),
   and every observation's fields but the image (events in order, pose, speed, route index, command, done,
   distance driven, time, frame, privileged) go into one digest per episode, with the episode's event list:

       PYTHONPATH=/tmp/judge_base/src .venv/bin/python benchmarks/judge_identity.py trace /tmp/trace_before.jsonl
       .venv/bin/python benchmarks/judge_identity.py trace /tmp/trace_after.jsonl
       .venv/bin/python benchmarks/judge_identity.py traces /tmp/trace_before.jsonl /tmp/trace_after.jsonl

Each comparison prints how many records it compared and the differences, and exits 1 on any difference.
Only the public `World` interface is used, so the script runs on old and new code alike.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

KEY = ("task", "condition", "weather", "route_id", "seed")
IGNORED = ("wall_s",)
# (town, vehicles, pedestrians, seed, min route length, timeout_s, driving): "drift" is the expert steered hard
# left for 2.5 s in every 15 s (lane invasions, collisions); "reckless" its steering at full throttle, never
# braking (red lights, collisions); "expert" the expert alone (lights passed, the goal). Between them every
# kind of event happens.
TRACE_SCENARIOS: tuple[tuple[str, int, int, int, float, float | None, str], ...] = (
    ("town01", 60, 60, 0, 300.0, None, "drift"), ("town01", 60, 60, 1, 300.0, None, "reckless"),
    ("town02", 40, 60, 2, 300.0, None, "drift"), ("town02", 40, 60, 3, 300.0, None, "reckless"),
    ("square", 30, 40, 4, 100.0, None, "drift"), ("square", 0, 0, 5, 100.0, None, "reckless"),
    ("town01", 20, 20, 6, 150.0, None, "expert"), ("town02", 20, 20, 7, 100.0, 25.0, "expert"),
)
TRACE_STEPS = 700
DRIFT_EVERY = 150  # steps


def _records(folder: Path) -> dict[tuple[Any, ...], dict[str, Any]]:
    out: dict[tuple[Any, ...], dict[str, Any]] = {}
    with (folder / "episodes.jsonl").open() as f:
        for line in f:
            rec = json.loads(line)
            key = tuple(rec[k] for k in KEY)
            if key in out:
                raise SystemExit(f"{folder}: two records for {key}")
            out[key] = rec
    return out


def compare_records(before: Path, after: Path) -> int:
    a, b = _records(before), _records(after)
    diffs: list[str] = []
    for key in sorted(set(a) | set(b), key=repr):
        if key not in a or key not in b:
            diffs.append(f"{key}: only in {'after' if key not in a else 'before'}")
            continue
        ra, rb = a[key], b[key]
        for field in sorted((set(ra) | set(rb)) - set(IGNORED)):
            if ra.get(field, "<absent>") != rb.get(field, "<absent>"):
                diffs.append(f"{key}: {field}: {str(ra.get(field, '<absent>'))[:80]} != {str(rb.get(field, '<absent>'))[:80]}")
    for d in diffs[:50]:
        print(d)
    print(f"records: {len(a)} before, {len(b)} after, {len(set(a) & set(b))} compared, {len(diffs)} differences")
    return 1 if diffs else 0


def _observation_fields(obs: Any) -> list[Any]:
    p = obs.privileged
    return [
        [(e.kind.value, e.time, e.x, e.y, e.other_id, e.other_type, e.detail) for e in obs.events],
        [obs.pose.x, obs.pose.y, obs.pose.yaw], obs.speed, obs.route_index, int(obs.command), obs.done,
        obs.distance_driven, obs.time, obs.frame, obs.town, list(obs.bounds), obs.weather,
        [(li.id, li.state, li.x, li.y, li.yaw) for li in p.lights],
        [(ag.id, ag.kind, ag.x, ag.y, ag.yaw, ag.speed, ag.length, ag.width) for ag in p.agents], p.ego_lane_yaw,
    ]


def trace(out: Path) -> int:
    from yawil.expert import Expert
    from yawil.sim.town.world import EmbeddedWorld
    from yawil.sim.types import Control, Scenario

    world, expert = EmbeddedWorld(), Expert()
    lines = []
    for town, vehicles, pedestrians, seed, length, timeout, driving in TRACE_SCENARIOS:
        sc = Scenario(town=town, vehicles=vehicles, pedestrians=pedestrians, camera=False, min_route_length=length,
                      timeout_s=timeout)
        obs = world.reset(sc, seed)
        expert.reset()
        digest = hashlib.sha256(repr(_observation_fields(obs)).encode())
        events: list[list[Any]] = []
        steps = 0
        while not obs.done and steps < TRACE_STEPS:
            control = expert.act(obs)
            if driving == "drift" and steps % DRIFT_EVERY >= DRIFT_EVERY - 25:  # hard left at speed
                control = Control(steer=-0.6, throttle=0.6, brake=0.0)
            elif driving == "reckless":
                control = Control(steer=control.steer, throttle=1.0, brake=0.0)
            obs = world.step(control)
            steps += 1
            fields = _observation_fields(obs)
            digest.update(repr(fields).encode())
            events += [[steps, *e] for e in fields[0]]
        lines.append({"town": town, "vehicles": vehicles, "pedestrians": pedestrians, "seed": seed, "steps": steps,
                      "done": obs.done, "sha256": digest.hexdigest(), "events": events})
        print(f"{town} seed {seed} ({driving}): {steps} steps, {len(events)} events, "
              f"kinds {sorted({e[1] for e in events})}", flush=True)
    world.close()
    out.write_text("".join(json.dumps(line) + "\n" for line in lines))
    return 0


def compare_traces(before: Path, after: Path) -> int:
    a = [json.loads(x) for x in before.read_text().splitlines()]
    b = [json.loads(x) for x in after.read_text().splitlines()]
    diffs = [f"{x['town']} seed {x['seed']}: differs" for x, y in zip(a, b, strict=False) if x != y]
    if len(a) != len(b):
        diffs.append(f"{len(a)} episodes before, {len(b)} after")
    for d in diffs:
        print(d)
    steps = sum(x["steps"] for x in a)
    print(f"traces: {len(a)} episodes, {steps} steps, {sum(len(x['events']) for x in a)} events compared, "
          f"{len(diffs)} differences")
    return 1 if diffs else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("records", help="compare two `yawil bench` output folders (all fields but wall_s)")
    r.add_argument("before", type=Path)
    r.add_argument("after", type=Path)
    t = sub.add_parser("trace", help="drive the fixed scenarios and write their digests")
    t.add_argument("out", type=Path)
    c = sub.add_parser("traces", help="compare two trace files")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "records":
        return compare_records(args.before, args.after)
    if args.cmd == "trace":
        return trace(args.out)
    return compare_traces(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
