"""`yawil explain`: attention heat maps of a trained agent, on dataset frames or on a driven episode."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "explain",
        help="attention heat maps (per frame, grid, episode video)",
        description=(
            "Heat maps of what a trained network attends to (YILRatt: its attention layers 1-3; models without "
            "attention such as CILRS: the channel mean of |activation| of ResNet layers 1-3). With --frames, "
            "one figure per dataset frame plus a grid (the paper's Figure 8); with --episode, a video of a "
            "driven episode (Figure 9)."
        ),
    )
    p.add_argument("--checkpoint", required=True, help="a yawil checkpoint (best.pt / last.pt)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", help="a dataset folder or one episode .h5 file to draw frames from")
    src.add_argument("--episode", action="store_true", help="drive a fresh episode and make a video")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--count", type=int, default=6, help="frames to explain with --frames (default 6)")
    p.add_argument("--seed", type=int, default=0, help="seed for frame choice / the episode (default 0)")
    p.add_argument("--alpha", type=float, default=0.5, help="weight of the colour map in the blend (default 0.5)")
    p.add_argument("--town", default="town02", help="--episode: town (default town02)")
    p.add_argument("--weather", default="SoftRainSunset", help="--episode: weather (default SoftRainSunset)")
    p.add_argument("--vehicles", type=int, default=20, help="--episode: vehicles (default 20)")
    p.add_argument("--pedestrians", type=int, default=20, help="--episode: pedestrians (default 20)")
    p.add_argument("--route", help="--episode: a benchmark route as TASK:ID of --condition (default: a random route)")
    p.add_argument("--condition", default="new-town-weather", help="--episode with --route: benchmark condition")
    p.add_argument("--steps", type=int, default=300, help="--episode: at most this many steps (default 300)")
    p.add_argument("--every", type=int, default=2, help="--episode: keep every Nth step in the video (default 2)")
    return p


def run(args: argparse.Namespace) -> int:
    from yawil.agent import Agent

    if args.count < 1 or args.steps < 1 or args.every < 1:
        raise SystemExit("yawil explain: --count, --steps and --every must be >= 1")
    agent = Agent.from_checkpoint(args.checkpoint)
    out = Path(args.out)
    if args.frames:
        paths = explain_frames(agent, Path(args.frames), out, args.count, args.seed, args.alpha)
        print(f"wrote {len(paths) - 1} frame figures and {paths[-1]}")
    else:
        video = explain_episode(agent, out, args)
        print(f"wrote {video}")
    return 0


def _episode_files(root: Path) -> list[Path]:
    if root.is_file():
        return [root]
    files = sorted(root.rglob("*.h5"))
    if not files:
        raise SystemExit(f"yawil explain: no episode files (*.h5) under {root}")
    return files


def explain_frames(agent, root: Path, out: Path, count: int, seed: int, alpha: float) -> list[Path]:  # type: ignore[no-untyped-def]
    """Figures for `count` frames spread over the dataset (seeded choice); returns their paths, grid last."""
    import numpy as np

    from yawil import explain
    from yawil.data.reader import open_episode

    rng = np.random.default_rng(seed)
    files = _episode_files(root)
    picks = sorted(rng.choice(len(files), size=count, replace=len(files) < count).tolist())
    items = []
    paths = []
    for n, fi in enumerate(picks):
        with open_episode(files[fi]) as ep:
            row = int(rng.integers(len(ep)))
            rec = ep[row]
            title = f"ep {ep.episode} frame {rec.frame} ({ep.attrs['weather']})"
        item = explain.explain_record(agent, rec, title=title)
        items.append(item)
        path = out / f"frame_{n:02d}.png"
        fig = explain.frame_figure(item, alpha, path)
        _close(fig)
        paths.append(path)
    grid = out / "grid.png"
    _close(explain.grid_figure(items, alpha, grid))
    paths.append(grid)
    return paths


def explain_episode(agent, out: Path, args: argparse.Namespace) -> Path:  # type: ignore[no-untyped-def]
    """Drive one episode with the agent and write a video of the camera with its heat maps."""
    from yawil import explain
    from yawil.sim import Scenario, make_world

    if args.route:
        from yawil.bench.suites import episodes

        task, _, rid = args.route.partition(":")
        eps = episodes("all", [args.condition], [task], routes=rid or "0", seeds=1)
        scenario = eps[0].scenario(camera=True)
    else:
        scenario = Scenario(
            town=args.town,
            weather=args.weather,
            vehicles=args.vehicles,
            pedestrians=args.pedestrians,
            camera=True,
            min_route_length=200.0,
        )
    world = make_world("embedded")
    frames = []
    try:
        obs = world.reset(scenario, seed=args.seed)
        agent.reset()
        for step in range(args.steps):
            if step % args.every == 0:
                item = explain.explain_observation(agent, obs, title=f"t={obs.time:5.1f}s")
                control = item_control(item)
                fig = explain.frame_figure(item, args.alpha)
                frames.append(explain.figure_to_array(fig))
                _close(fig)
            else:
                control = agent.act(obs)
            obs = world.step(control)
            if obs.done or any(e.kind.value == "collision" for e in obs.events):
                break
    finally:
        world.close()
    return explain.write_video(frames, out / "episode.mp4", fps=max(1, 10 // args.every))


def item_control(item):  # type: ignore[no-untyped-def]
    from yawil.sim.types import Control

    return Control(steer=item.steer, throttle=item.throttle, brake=item.brake)


def _close(fig) -> None:  # type: ignore[no-untyped-def]
    import matplotlib.pyplot as plt

    plt.close(fig)
