"""Does an episode's drive depend on what the same process drove before? (issue 38's history dependence)

    .venv/bin/python benchmarks/history_probe.py --agent zoo:yilratt-dagger-ego --engine openvino \
        --target dense/training/HardRainNoon/2/0 --before dense/training/ClearNoon/0/0 [--max-steps N] [--threads 1]

Drives the target episode in a fresh process (a new world and agent, nothing driven before), then, in this
process, the `--before` episodes and the target: the world and the agent reused as the benchmark's workers reuse
them. Compares the target's two drives step by step (the camera image's bytes, the ego's pose and speed, the
control) and their records (every field but wall_s), and prints the first step where they part. Exit status 0
when the drives are identical. (The fresh drive runs in its own process because what one drive leaves in a
process is what is being looked for: a fresh driver in a process that drove before is not fresh.)

That command, before the renderer drew each frame from an empty transform cache (`render_frame` in
yawil.sim.town.render.renderer): the drives parted at step 47 (the camera image, one sky pixel; pose equal), and
the episode ended in a rear-end at 252.9 s (2,529 steps) instead of a success at 360.3 s (3,603 steps), as the
2-worker selection run's record and a fresh `yawil trace` had disagreed. After it: identical, all 3,603 steps
(about 5 min on one core).

`--fresh COMPONENT` recreates one cached component before the second drive of the target, to bisect a
difference: `renderer` (the world's camera renderer), `world` (the whole world), `agent` (the agent).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from yawil.bench.runner import AgentSpec, EpisodeDriver, drive_options  # noqa: E402
from yawil.bench.suites import Episode, episodes  # noqa: E402


def find(key: str) -> Episode:
    task, condition, _weather, _route, _seed = key.split("/")
    for ep in episodes("nocrash" if task in ("empty", "regular", "dense") else "all", conditions=[condition],
                       tasks=[task], seeds=max(1, int(_seed) + 1), weather_rule="all"):
        if ep.key == key:
            return ep
    raise SystemExit(f"no episode {key!r}")


def drive(driver: EpisodeDriver, ep: Episode, max_steps: int | None) -> tuple[dict[str, Any], list[tuple]]:
    """One episode as `EpisodeDriver.drive_one` drives it, with a trace of every step."""
    live = driver._start(ep, 0)
    agent = driver._agent
    steps: list[tuple] = []
    while True:
        obs = live.obs
        control = agent.act(obs)  # type: ignore[union-attr]
        img = hashlib.sha1(obs.image.tobytes()).hexdigest()[:12] if obs.image is not None else "-"
        steps.append((obs.frame, img, (obs.pose.x, obs.pose.y, obs.pose.yaw, obs.speed),
                      (control.steer, control.throttle, control.brake)))
        if driver._step(live, control):
            break
        if max_steps is not None and len(steps) >= max_steps:  # cut: no record, only the steps
            return {"reason": f"cut after {max_steps} steps"}, steps
    rec = driver._finish(live)
    return {k: v for k, v in rec.items() if k != "wall_s"}, steps


def drive_fresh(spec: AgentSpec, ep: Episode, max_steps: int | None, threads: int) -> tuple[dict, list]:
    """The target alone in a new process (run in a spawned child)."""
    import torch

    torch.set_num_threads(threads)
    driver = EpisodeDriver(spec, camera=True)
    try:
        return drive(driver, ep, max_steps)
    finally:
        driver.close()


def compare(a: tuple[dict, list], b: tuple[dict, list]) -> bool:
    (ra, sa), (rb, sb) = a, b
    same = True
    for i, (x, y) in enumerate(zip(sa, sb, strict=False)):
        if x != y:
            parts = [n for n, u, v in zip(("frame", "image", "pose/speed", "control"), x, y, strict=True) if u != v]
            print(f"  first difference at step {i}: {', '.join(parts)}")
            print(f"    fresh : {x}")
            print(f"    reused: {y}")
            same = False
            break
    if len(sa) != len(sb):
        print(f"  steps: {len(sa)} fresh, {len(sb)} reused")
        same = False
    fields = [k for k in ra if ra[k] != rb.get(k)]
    if fields:
        print(f"  record fields that differ: {', '.join(fields)}")
        for k in fields:
            if k not in ("route_xy", "trajectory"):
                print(f"    {k}: {ra[k]!r} / {rb[k]!r}")
        same = False
    print(f"  {len(sa)} steps; outcome fresh {ra.get('reason')!r} reused {rb.get('reason')!r}; "
          f"{'IDENTICAL' if same else 'DIFFER'}")
    return same


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agent", default="expert")
    ap.add_argument("--engine", default="auto")
    ap.add_argument("--target", required=True)
    ap.add_argument("--before", default="", help="comma-separated episode keys driven before the second drive")
    ap.add_argument("--max-steps", type=int, default=None, help="cut every drive after this many steps")
    ap.add_argument("--before-steps", type=int, default=None, help="cut the --before episodes after this many")
    ap.add_argument("--fresh", default="", help="comma-separated: renderer, world, agent")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    if args.agent == "expert":
        spec = AgentSpec("expert")
    else:
        drive_opts = drive_options(argparse.Namespace(agent=args.agent, speed_control=False, stop_release=0.0))
        spec = AgentSpec(args.agent, engine=args.engine, **drive_opts)
    target = find(args.target)
    before = [find(k) for k in args.before.split(",") if k]
    t0 = time.perf_counter()
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        first = pool.submit(drive_fresh, spec, target, args.max_steps, args.threads).result()
    print(f"fresh drive of {target.key}: {len(first[1])} steps, {first[0]['reason']} "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)
    reused = EpisodeDriver(spec, camera=True)
    for ep in before:
        rec, steps = drive(reused, ep, args.before_steps)
        print(f"before: {ep.key}: {len(steps)} steps, {rec['reason']}", flush=True)
    for what in filter(None, args.fresh.split(",")):
        if what == "renderer":
            reused.world(0).close()
        elif what == "world":
            reused._drop_world(0)
        elif what == "agent":
            reused._agent = None
        else:
            raise SystemExit(f"--fresh {what!r}: expected renderer, world or agent")
    second = drive(reused, target, args.max_steps)
    reused.close()
    print(f"{target.key} after {len(before)} other episode(s), fresh: {args.fresh or 'nothing'}:")
    return 0 if compare(first, second) else 1


if __name__ == "__main__":
    raise SystemExit(main())
