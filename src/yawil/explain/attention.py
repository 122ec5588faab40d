"""Attention heat maps of a trained agent: what the network looked at when it decided (the paper's Figures 8
and 9).

A map is a probability over the positions of one attention layer (YILRatt) or, for networks without
attention (CILRS), the channel mean of |activation| of a ResNet layer normalised to sum to one. Either way
it is upsampled to the camera image, coloured and blended over it with weight `alpha` (documented
default 0.5: half image, half colour). Figures are drawn with matplotlib, videos written by `yawil.video`.

The two jobs of `yawil explain` are plain functions here: `explain_frames` (figures of dataset frames and a
grid, Figure 8) and `explain_episode` (a driven episode as a video, Figure 9; the episode is an
`EpisodeVideo`). `yawil.explain.cli` only turns the command line into their arguments.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from yawil.explain.figures import DEFAULT_ALPHA, Explained, frame_figure, grid_figure

if TYPE_CHECKING:
    from yawil.agent import Agent
    from yawil.sim.types import Control, Scenario


LAYER_NAMES = ("layer 1", "layer 2", "layer 3")


def activation_maps(model: Any, image: Any) -> list[np.ndarray]:
    """Per-stage maps (h, w) of a network without attention: the channel mean of |activation|, summing to one
    (`DrivingModel.activation_maps`), for one image (uint8 (H, W, 3) or a float tensor [1, 3, H, W] in [0, 1]).
    A YILRatt built without `compute_global` never uses its last stage (its forward stops at layer 3, and a zoo
    model ships without its weights), so that stage is left out."""
    import torch

    if isinstance(image, np.ndarray):
        image = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div(255.0)
    param = next(model.parameters(), None)
    if param is not None:
        image = image.to(param.device)
    with torch.inference_mode():
        maps = model.activation_maps(image)
    if getattr(model, "compute_global", True) is False:
        maps = maps[:3]
    return [m[0].float().cpu().numpy() for m in maps]


def _maps_of(agent, image_tensor, attention: list) -> tuple[list[np.ndarray], list[str]]:  # type: ignore[no-untyped-def]
    """Attention maps when the model has them; else the activation maps of its first three stages (CILRS)."""
    if attention:
        return [np.asarray(a, dtype=np.float64) for a in attention], [f"attention {n}" for n in LAYER_NAMES]
    return activation_maps(agent.model, image_tensor)[:3], [f"activation {n}" for n in LAYER_NAMES]


def explain_observation(agent, obs, title: str = "") -> Explained:  # type: ignore[no-untyped-def]
    """Run the agent on one observation and collect its maps (it acts, so its route hint advances)."""
    control = agent.act(obs)
    last = agent.last
    maps, names = _maps_of(agent, agent.spec.image(obs.image), last.attention)
    return Explained(
        image=np.asarray(obs.image),
        maps=maps,
        steer=control.steer,
        throttle=control.throttle,
        brake=control.brake,
        speed=last.speed,
        title=title,
        layer_names=names,
    )


def explain_record(agent, record, title: str = "") -> Explained:  # type: ignore[no-untyped-def]
    """Run the agent's network on a dataset frame, with the frame's stored speed, guidance and command (the
    model-input contract's `from_record`: the agent's preprocessing of an observation), on the agent's engine."""
    x = agent.spec.from_record(record)
    out = agent.engine.run(x, attention=True)
    control = agent.post(out.actions[0], float(record.speed))
    maps, names = _maps_of(agent, x.image, [a[0] for a in out.attention])
    return Explained(
        image=np.asarray(record.image),
        maps=maps,
        steer=control.steer,
        throttle=control.throttle,
        brake=control.brake,
        speed=float(agent.norm.speed_inverse(np.float32(out.speed[0]))),
        title=title,
        layer_names=names,
    )


# ----- the jobs of `yawil explain` -------------------------------------------------------------------------------


def _episode_files(root: Path) -> list[Path]:
    if root.is_file():
        return [root]
    files = sorted(root.rglob("*.h5"))
    if not files:
        raise SystemExit(f"yawil explain: no episode files (*.h5) under {root}")
    return files


def check_frame_count(root: Path, count: int) -> None:
    """`--count` figures need that many frames: refused before the agent is built (a count beyond the dataset
    drew frames again and again, one figure each). The manifest's counts where there is one, else the files'."""
    from yawil.data.manifest import read_manifest
    from yawil.data.reader import open_episode

    files = _episode_files(root)
    if root.is_dir() and (root / "manifest.json").is_file():
        total = sum(e.frames for e in read_manifest(root).episodes)
    else:
        total = 0
        for f in files:
            with open_episode(f) as ep:
                total += len(ep)
    if count > total:
        raise SystemExit(f"yawil explain: --count {count}: {root} holds {total} frames; give at most {total}")


def check_guidance(agent: Agent, ep_config: dict, path: Path) -> None:  # type: ignore[type-arg]
    """A guided network explained on frames whose stored guidance it was not trained on would show maps of
    inputs it never saw (an `ego` model on the paper's `route` data): refuse, naming both."""
    from yawil.guidance import GuidanceConfig

    stored = ep_config.get("guidance")
    if agent.kind is None or not isinstance(stored, dict):
        return
    if GuidanceConfig.from_dict(stored) != agent.guidance_config:
        raise ValueError(f"{path}: its guidance {stored} differs from the checkpoint's "
                         f"{agent.guidance_config.to_dict()}; explain on data collected with the checkpoint's "
                         f"(`yawil collect --guidance-reference {agent.guidance_config.reference}`)")


def explain_frames(agent: Agent, root: Path, out: Path, count: int, seed: int, alpha: float) -> list[Path]:
    """Figures for `count` frames spread over the dataset (seeded choice); returns their paths, grid last."""
    from yawil.data.reader import open_episode

    rng = np.random.default_rng(seed)
    files = _episode_files(root)
    picks = sorted(rng.choice(len(files), size=count, replace=len(files) < count).tolist())
    items = []
    paths = []
    for n, fi in enumerate(picks):
        with open_episode(files[fi]) as ep:
            check_guidance(agent, ep.attrs["config"], files[fi])
            row = int(rng.integers(len(ep)))
            rec = ep[row]
            title = f"ep {ep.episode} frame {rec.frame} ({ep.attrs['weather']})"
        item = explain_record(agent, rec, title=title)
        items.append(item)
        path = out / f"frame_{n:02d}.png"
        fig = frame_figure(item, alpha, path)
        _close(fig)
        paths.append(path)
    grid = out / "grid.png"
    _close(grid_figure(items, alpha, grid))
    paths.append(grid)
    return paths


@dataclass(frozen=True)
class EpisodeVideo:
    """The episode `explain_episode` drives: a benchmark route (`route` as TASK:ID of `condition`; the route's
    own town, weather and traffic) or, without one, a random route of `town` in `weather` with this traffic."""

    route: str | None = None
    condition: str = "new-town-weather"
    town: str = "town02"
    weather: str = "SoftRainSunset"
    vehicles: int = 20
    pedestrians: int = 20
    seed: int = 0
    steps: int = 300  # at most this many steps
    every: int = 2  # keep every Nth step in the video


def episode_scenario(episode: EpisodeVideo) -> Scenario:
    """The scenario (with the camera) of an `EpisodeVideo`: its benchmark route, or a random route of its town;
    shared by the video and the closed-loop faithfulness test (`yawil.explain.faithfulness`)."""
    from yawil.sim import Scenario

    if episode.route:
        from yawil.bench.suites import episodes

        task, _, rid = episode.route.partition(":")
        eps = episodes("all", [episode.condition], [task], routes=rid or "0", seeds=1)
        scenario: Scenario = eps[0].scenario(camera=True)
        return scenario
    return Scenario(
        town=episode.town,
        weather=episode.weather,
        vehicles=episode.vehicles,
        pedestrians=episode.pedestrians,
        camera=True,
        min_route_length=200.0,
    )


def explain_episode(agent: Agent, out: Path, episode: EpisodeVideo = EpisodeVideo(),
                    alpha: float = DEFAULT_ALPHA) -> Path:
    """Drive one episode with the agent and write a video of the camera with its heat maps."""
    from yawil.sim import make_world
    from yawil.video import figure_to_array, write_video

    scenario = episode_scenario(episode)
    world = make_world("embedded")
    frames = []
    try:
        obs = world.reset(scenario, seed=episode.seed)
        agent.reset()
        for step in range(episode.steps):
            if step % episode.every == 0:
                item = explain_observation(agent, obs, title=f"t={obs.time:5.1f}s")
                control = item_control(item)
                fig = frame_figure(item, alpha)
                frames.append(figure_to_array(fig))
                _close(fig)
            else:
                control = agent.act(obs)
            obs = world.step(control)
            if obs.done or any(e.kind.value == "collision" for e in obs.events):
                break
    finally:
        world.close()
    return write_video(frames, out / "episode.mp4", fps=max(1, 10 // episode.every))


def item_control(item: Explained) -> Control:
    from yawil.sim.types import Control

    return Control(steer=item.steer, throttle=item.throttle, brake=item.brake)


def _close(fig) -> None:  # type: ignore[no-untyped-def]
    import matplotlib.pyplot as plt

    plt.close(fig)
