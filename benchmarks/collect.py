"""Collection speed: frames/s of one worker with the camera on and dense traffic, and where the time goes.

    .venv/bin/python benchmarks/collect.py --frames 3000

Runs the real collection loop (`yawil.data.collect.run_episode`: world with camera, expert, guidance, HDF5
writer) in one process on town01 with 50 vehicles and 30 pedestrians, into a temporary dataset, and prints
steps/s, stored frames/s, bytes per stored frame and the split world / expert / guidance+writer. The
target is >= 150 frames/s per worker. With --workers N it also times `collect(..., workers=N)` end to end.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


class TimedWorld:
    """Wraps a world and accumulates the wall time spent in reset/step."""

    def __init__(self, world: Any) -> None:
        self.world, self.seconds, self.reset_seconds = world, 0.0, 0.0

    def reset(self, scenario: Any, seed: int) -> Any:
        t = time.perf_counter()
        obs = self.world.reset(scenario, seed)
        self.reset_seconds += time.perf_counter() - t
        return obs

    def step(self, control: Any) -> Any:
        t = time.perf_counter()
        obs = self.world.step(control)
        self.seconds += time.perf_counter() - t
        return obs

    def close(self) -> None:
        self.world.close()


TIMERS = {"expert": 0.0, "guidance": 0.0}


def _instrument() -> None:
    """Time the expert and the guidance inside the real loop (the episode loop looks them up at call time)."""
    import yawil.data.episode as c

    base_expert, base_guidance = c.Expert, c.compute_guidance

    class TimedExpert(base_expert):  # type: ignore[misc, valid-type]
        def act(self, obs: Any) -> Any:
            t = time.perf_counter()
            out = super().act(obs)
            TIMERS["expert"] += time.perf_counter() - t
            return out

    def timed_guidance(*args: Any, **kwargs: Any) -> Any:
        t = time.perf_counter()
        out = base_guidance(*args, **kwargs)
        TIMERS["guidance"] += time.perf_counter() - t
        return out

    c.Expert = TimedExpert  # type: ignore[misc]
    c.compute_guidance = timed_guidance


def main(argv: list[str] | None = None) -> int:
    from yawil.data.collect import CollectConfig, collect, dataset_config, plan_episode, run_episode
    from yawil.data.writer import DatasetWriter
    from yawil.expert import ExpertConfig
    from yawil.guidance import GuidanceConfig
    from yawil.sim import make_world

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=3000, help="steps to run (split over episodes of <= 1500 steps)")
    p.add_argument("--town", default="town01")
    p.add_argument("--vehicles", type=int, default=50)
    p.add_argument("--pedestrians", type=int, default=30)
    p.add_argument("--workers", type=int, default=0, help="also time collect() with this many workers")
    args = p.parse_args(argv)

    _instrument()
    per_episode = min(args.frames, 1500)
    cfg = CollectConfig(town=args.town, weathers=("ClearNoon", "HardRainNoon"), vehicles=(args.vehicles, args.vehicles),
                        pedestrians=(args.pedestrians, args.pedestrians), min_route_length=1000.0,
                        max_episode_frames=per_episode)
    world = TimedWorld(make_world("embedded"))
    steps = kept = 0
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        writer = DatasetWriter(tmp, dataset_config(cfg, GuidanceConfig(), ExpertConfig()))
        index = 0
        while steps < args.frames:
            r = run_episode(world, plan_episode(cfg, 0, index), cfg, writer)
            steps, kept, index = steps + r.frames_run, kept + r.frames_kept, index + 1
        total = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in Path(tmp, "episodes").glob("*.h5"))
    world.close()

    expert_ms = 1000 * TIMERS["expert"] / steps
    guidance_ms = 1000 * TIMERS["guidance"] / steps
    world_ms = 1000 * world.seconds / steps
    total_ms = 1000 * (total - world.reset_seconds) / steps
    print(f"collection, one worker, {args.town}, camera 200x88, {args.vehicles} vehicles + {args.pedestrians} pedestrians, "
          f"{steps} steps in {index} episodes")
    print("| figure | value |")
    print("|---|---|")
    run = total - world.reset_seconds
    print(f"| episode starts (world reset; the first builds the renderer) | {world.reset_seconds:.1f} s for {index} |")
    print(f"| steps/s (every simulated frame, resets excluded) | {steps / run:.0f} |")
    print(f"| stored frames/s (after thinning, resets excluded) | {kept / run:.0f} ({kept} of {steps} stored) |")
    print(f"| stored frames/s (resets included) | {kept / total:.0f} |")
    print(f"| per step: world (sim + render) | {world_ms:.2f} ms |")
    print(f"| per step: expert | {expert_ms:.2f} ms |")
    print(f"| per step: guidance (3 vectors) | {guidance_ms:.2f} ms |")
    print(f"| per step: writer + noise + thinning + loop | {max(total_ms - world_ms - expert_ms - guidance_ms, 0.0):.2f} ms |")
    print(f"| bytes per stored frame on disk | {size / max(kept, 1):.0f} |")
    if args.workers:
        with tempfile.TemporaryDirectory() as tmp:
            cfg_w = CollectConfig(town=args.town, weathers=("ClearNoon", "HardRainNoon"),
                                  vehicles=(args.vehicles, args.vehicles), pedestrians=(args.pedestrians, args.pedestrians),
                                  min_route_length=1000.0, max_episode_frames=per_episode)
            t = time.perf_counter()
            s = collect(tmp, town=args.town, weathers=cfg_w.weathers, frames=None, episodes=2 * args.workers,
                        workers=args.workers, config=cfg_w, progress=False)
            dt = time.perf_counter() - t
        print(f"| collect(workers={args.workers}), {s.episodes_written} episodes, incl. start-up | "
              f"{s.frames_written / dt:.0f} stored frames/s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
