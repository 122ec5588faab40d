"""How strong is the expert? Success on random navigation routes with dense traffic, per town and weather.

    .venv/bin/python benchmarks/expert.py --episodes 50 --workers 2

Each episode: a random route (>= 1.0 km in town01, >= 0.3 km in town02, as the benchmark's Navigation
task), 50 vehicles and 30 pedestrians, NoCrash's timeout, the camera off (the expert does not look).
Success = goal reached with no collision. Every collision is attributed: "ego" when the ego was moving
into the other, "other" when the ego was standing still or was hit from behind. Prints a table per
town and weather and the list of failures, so a failure caused by traffic can be reported precisely.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

TOWNS: dict[str, tuple[float, tuple[str, ...]]] = {  # min route length, weathers of the benchmark condition
    "town01": (1000.0, ("ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset")),
    "town02": (300.0, ("WetCloudyNoon", "SoftRainSunset")),
}


def attribute(ego: Any, speed: float, other: Any | None) -> str:
    """Who caused a collision: 'other' if the ego stood still or was struck from behind, else 'ego'."""
    if other is None:
        return "ego"  # a static object: only the ego moves into those
    if speed < 0.3:
        return "other"
    dx, dy = other.x - ego.x, other.y - ego.y
    along = dx * math.cos(ego.yaw) + dy * math.sin(ego.yaw)
    return "other" if along < -1.5 else "ego"


def run_episode(town: str, seed: int, weather: str, vehicles: int, pedestrians: int, min_length: float,
                max_steps: int | None = None) -> dict[str, Any]:
    from yawil.expert import Expert
    from yawil.sim import EventKind, Scenario, make_world

    world = make_world("embedded")
    expert = Expert()
    t0 = time.perf_counter()
    obs = world.reset(Scenario(town=town, weather=weather, vehicles=vehicles, pedestrians=pedestrians, camera=False,
                               min_route_length=min_length), seed)
    rec: dict[str, Any] = {"town": town, "seed": seed, "weather": weather, "route_m": round(obs.route.length, 1),
                           "collisions": [], "lane": 0, "red": 0, "lights": 0, "reasons": {}}
    steps = 0
    last_move, last_xy = 0.0, (obs.pose.x, obs.pose.y)
    agents_before = {a.id: a for a in obs.privileged.agents}
    while not obs.done and (max_steps is None or steps < max_steps):
        control = expert.act(obs)
        r = expert.state.reason
        rec["reasons"][r] = rec["reasons"].get(r, 0) + 1
        speed_before, pose_before = obs.speed, obs.pose
        obs = world.step(control)
        steps += 1
        for ev in obs.events:
            if ev.kind is EventKind.COLLISION:
                other = agents_before.get(ev.other_id) if ev.other_id is not None else None
                rec["collisions"].append({
                    "t": round(ev.time, 1), "with": ev.other_type, "id": ev.other_id,
                    "by": attribute(pose_before, speed_before, other), "ego_speed": round(speed_before, 2),
                    "other_speed": None if other is None else round(other.speed, 2),
                    "x": round(ev.x, 1), "y": round(ev.y, 1), "expert": r,
                })
            elif ev.kind is EventKind.LANE_INVASION:
                rec["lane"] += 1
            elif ev.kind is EventKind.RED_LIGHT:
                rec["red"] += 1
            elif ev.kind is EventKind.LIGHT_PASSED:
                rec["lights"] += 1
        agents_before = {a.id: a for a in obs.privileged.agents}
        if math.hypot(obs.pose.x - last_xy[0], obs.pose.y - last_xy[1]) > 1.0:
            last_move, last_xy = obs.time, (obs.pose.x, obs.pose.y)
        if rec["collisions"]:
            break  # the benchmark's rule: an episode ends at its first collision
    goal = any(ev.kind is EventKind.GOAL_REACHED for ev in obs.events)
    rec.update(steps=steps, sim_s=round(obs.time, 1), km=round(obs.distance_driven / 1000, 3),
               wall_s=round(time.perf_counter() - t0, 2), goal=goal, success=goal and not rec["collisions"])
    rec["stood_s"] = round(obs.time - last_move, 1)  # standing still at the end (a gridlock if long)
    hazard = expert.state.hazard
    rec["blocked_by"] = None if hazard is None else f"{hazard.reason}:{hazard.agent_id}"
    if rec["success"]:
        rec["failure"] = None
    elif rec["collisions"]:
        rec["failure"] = "collision_" + rec["collisions"][0]["by"]
    else:  # a timeout: standing for the last minute behind traffic is a gridlock, not slowness
        rec["failure"] = "timeout_blocked" if rec["stood_s"] > 60.0 else "timeout"
    world.close()
    return rec


def _job(args: tuple[str, int, str, int, int, float]) -> dict[str, Any]:
    return run_episode(*args)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--towns", default="town01,town02")
    p.add_argument("--episodes", type=int, default=50, help="random routes per town")
    p.add_argument("--vehicles", type=int, default=50)
    p.add_argument("--pedestrians", type=int, default=30)
    p.add_argument("--seed", type=int, default=0, help="route seeds are seed .. seed+episodes-1")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--jsonl", default=None, help="also write one JSON line per episode here")
    args = p.parse_args(argv)
    jobs = []
    for town in args.towns.split(","):
        min_len, weathers = TOWNS[town]
        for i in range(args.episodes):
            jobs.append((town, args.seed + i, weathers[i % len(weathers)], args.vehicles, args.pedestrians, min_len))
    t0 = time.perf_counter()
    records = []
    with ProcessPoolExecutor(max(args.workers, 1), mp_context=get_context("spawn")) as pool:
        for k, r in enumerate(pool.map(_job, jobs), 1):
            records.append(r)
            print(f"[{k}/{len(jobs)}] {r['town']} seed {r['seed']} {r['weather']}: "
                  f"{'ok' if r['success'] else r['failure']} ({r['wall_s']} s)", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    if args.jsonl:
        with open(args.jsonl, "w") as f:
            for r in records:
                f.write(json.dumps(r) + "\n")
    print(f"expert, {args.vehicles} vehicles + {args.pedestrians} pedestrians, {args.episodes} random routes per town "
          f"(seeds {args.seed}..{args.seed + args.episodes - 1}), wall {wall:.0f} s with {args.workers} workers")
    print("| town | weather | episodes | success | timeouts | collisions caused by ego | by other | km | lane inv./km | red lights |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["town"], r["weather"]), []).append(r)
        groups.setdefault((r["town"], "all"), []).append(r)
    for (town, weather), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] == "all", kv[0][1])):
        n = len(rs)
        ok = sum(r["success"] for r in rs)
        km = sum(r["km"] for r in rs)
        print(f"| {town} | {weather} | {n} | {ok}/{n} ({100 * ok / n:.0f}%) | "
              f"{sum(str(r['failure']).startswith('timeout') for r in rs)} "
              f"| {sum(r['failure'] == 'collision_ego' for r in rs)} | {sum(r['failure'] == 'collision_other' for r in rs)} "
              f"| {km:.1f} | {sum(r['lane'] for r in rs) / max(km, 1e-9):.2f} | {sum(r['red'] for r in rs)}/{sum(r['lights'] for r in rs)} |")
    failures = [r for r in records if not r["success"]]
    if failures:
        print("\nfailures:")
        for r in failures:
            print(f"  {r['town']} seed {r['seed']} {r['weather']}: {r['failure']} at {r['sim_s']} s, "
                  f"{r['km']} km of {r['route_m'] / 1000:.2f}; standing {r['stood_s']} s, last hazard {r['blocked_by']}; "
                  f"collisions {r['collisions']}; expert reasons {r['reasons']}")
    sim_steps = sum(r["steps"] for r in records)
    print(f"\n{sim_steps} steps in {sum(r['wall_s'] for r in records):.0f} s of episode wall time "
          f"({sim_steps / max(sum(r['wall_s'] for r in records), 1e-9):.0f} steps/s per worker, world + expert)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
