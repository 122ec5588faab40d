"""Attention heat maps: what the network looked at when it decided (the paper's Figures 8 and 9).

A map is a probability over the positions of one attention layer (YILRatt) or, for networks without
attention (CILRS), the channel mean of |activation| of a ResNet layer normalised to sum to one. Either way
it is upsampled to the camera image, coloured and blended over it with weight `alpha` (documented
default 0.5: half image, half colour). Figures are drawn with matplotlib, videos written by `yawil.video`.

The two jobs of `yawil explain` are plain functions here: `explain_frames` (figures of dataset frames and a
grid, Figure 8) and `explain_episode` (a driven episode as a video, Figure 9; the episode is an
`EpisodeVideo`). `yawil.explain_cli` only turns the command line into their arguments.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from yawil.agent import Agent
    from yawil.sim.types import Control

DEFAULT_ALPHA = 0.5  # weight of the colour map in the blend
DEFAULT_CMAP = "jet"


def normalise_map(att: np.ndarray) -> np.ndarray:
    """A non-negative 2-D map scaled to sum to one (a probability over positions)."""
    a = np.asarray(att, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"attention map must be 2-D (h, w), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("attention map contains NaN or inf")
    a = np.clip(a, 0.0, None)
    total = a.sum()
    if total <= 0:
        return np.full(a.shape, 1.0 / a.size)
    return a / total


def upsample(att: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear upsampling of a map to the image size (align-corners off, like torch's default)."""
    a = np.asarray(att, dtype=np.float64)
    h, w = a.shape
    ys = (np.arange(height) + 0.5) * h / height - 0.5
    xs = (np.arange(width) + 0.5) * w / width - 0.5
    ys = np.clip(ys, 0, h - 1)
    xs = np.clip(xs, 0, w - 1)
    y0 = np.floor(ys).astype(int)
    x0 = np.floor(xs).astype(int)
    y1 = np.minimum(y0 + 1, h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    wy = (ys - y0)[:, None]
    wx = (xs - x0)[None, :]
    top = a[y0][:, x0] * (1 - wx) + a[y0][:, x1] * wx
    bottom = a[y1][:, x0] * (1 - wx) + a[y1][:, x1] * wx
    return top * (1 - wy) + bottom * wy


def overlay(image: np.ndarray, att: np.ndarray, alpha: float = DEFAULT_ALPHA, cmap: str = DEFAULT_CMAP) -> np.ndarray:
    """Blend a coloured map over an RGB uint8 image; returns an image of the same size."""
    import matplotlib

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    p = normalise_map(att)
    up = upsample(p, img.shape[0], img.shape[1])
    span = up.max() - up.min()
    scaled = (up - up.min()) / span if span > 0 else np.zeros_like(up)
    colour = matplotlib.colormaps[cmap](scaled)[..., :3]
    out = (1.0 - alpha) * img.astype(np.float64) / 255.0 + alpha * colour
    return np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Explained:
    """One frame with what the network made of it."""

    image: np.ndarray  # (H, W, 3) uint8
    maps: Sequence[np.ndarray]  # one (h, w) map per layer
    steer: float
    throttle: float
    brake: float
    speed: float  # predicted, m/s
    title: str = ""
    layer_names: Sequence[str] = ()


def frame_figure(item: Explained, alpha: float = DEFAULT_ALPHA, path: Path | None = None):  # type: ignore[no-untyped-def]
    """The camera image and one overlay per layer in a row, with the decision written under it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = 1 + len(item.maps)
    fig, axes = plt.subplots(1, n, figsize=(2.6 * n, 1.6), squeeze=False)
    axes[0, 0].imshow(item.image)
    axes[0, 0].set_title(item.title or "camera", fontsize=8)
    names = list(item.layer_names) or [f"layer {i + 1}" for i in range(len(item.maps))]
    for i, att in enumerate(item.maps):
        axes[0, i + 1].imshow(overlay(item.image, att, alpha))
        axes[0, i + 1].set_title(names[i], fontsize=8)
    for ax in axes[0]:
        ax.axis("off")
    fig.text(
        0.5,
        0.02,
        f"steer {item.steer:+.2f}   throttle {item.throttle:.2f}   brake {item.brake:.2f}   speed {item.speed * 3.6:.1f} km/h",
        ha="center",
        fontsize=8,
    )
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    if path is not None:
        _save(fig, path)
    return fig


def grid_figure(items: Sequence[Explained], alpha: float = DEFAULT_ALPHA, path: Path | None = None):  # type: ignore[no-untyped-def]
    """Several frames, one per row, as the paper's Figure 8."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not items:
        raise ValueError("grid_figure needs at least one frame")
    n_cols = 1 + max(len(it.maps) for it in items)
    fig, axes = plt.subplots(len(items), n_cols, figsize=(2.6 * n_cols, 1.45 * len(items)), squeeze=False)
    for r, it in enumerate(items):
        axes[r, 0].imshow(it.image)
        axes[r, 0].set_ylabel(it.title.replace(" (", "\n("), fontsize=6)  # two lines: one would overflow its row
        axes[r, 0].set_title(
            f"s {it.steer:+.2f} t {it.throttle:.2f} b {it.brake:.2f} v {it.speed * 3.6:.0f}km/h", fontsize=7
        )
        names = list(it.layer_names) or [f"layer {i + 1}" for i in range(len(it.maps))]
        for c in range(1, n_cols):
            ax = axes[r, c]
            if c - 1 < len(it.maps):
                ax.imshow(overlay(it.image, it.maps[c - 1], alpha))
                if r == 0:
                    ax.set_title(names[c - 1], fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    if path is not None:
        _save(fig, path)
    return fig


def _save(fig, path: Path) -> None:  # type: ignore[no-untyped-def]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    fig.savefig(tmp, dpi=110)
    tmp.replace(path)


# ----- from a trained agent ------------------------------------------------------------------------------------

LAYER_NAMES = ("layer 1", "layer 2", "layer 3")


def _maps_of(agent, image_tensor, attention: list) -> tuple[list[np.ndarray], list[str]]:  # type: ignore[no-untyped-def]
    """Attention maps when the model has them; else the activation maps of its first three stages (CILRS)."""
    if attention:
        return [np.asarray(a, dtype=np.float64) for a in attention], [f"attention {n}" for n in LAYER_NAMES]
    import torch

    with torch.inference_mode():
        maps = agent.model.activation_maps(image_tensor)
    return [m[0].float().cpu().numpy() for m in maps[:3]], [f"activation {n}" for n in LAYER_NAMES]


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
    model-input contract's `from_record`: the agent's preprocessing of an observation)."""
    import torch

    x = agent.spec.from_record(record)
    with torch.inference_mode(), agent.runtime.autocast():
        out = x.forward(agent.model)
    actions = out.actions[0].float().cpu().numpy()
    control = agent.post(actions, float(record.speed))
    attention = [a[0].float().cpu().numpy() for a in out.attention]
    maps, names = _maps_of(agent, x.image, attention)
    return Explained(
        image=np.asarray(record.image),
        maps=maps,
        steer=control.steer,
        throttle=control.throttle,
        brake=control.brake,
        speed=float(agent.norm.speed_inverse(out.speed[0, 0].float()).cpu()),
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


def explain_episode(agent: Agent, out: Path, episode: EpisodeVideo = EpisodeVideo(),
                    alpha: float = DEFAULT_ALPHA) -> Path:
    """Drive one episode with the agent and write a video of the camera with its heat maps."""
    from yawil.sim import Scenario, make_world
    from yawil.video import figure_to_array, write_video

    if episode.route:
        from yawil.bench.suites import episodes

        task, _, rid = episode.route.partition(":")
        eps = episodes("all", [episode.condition], [task], routes=rid or "0", seeds=1)
        scenario = eps[0].scenario(camera=True)
    else:
        scenario = Scenario(
            town=episode.town,
            weather=episode.weather,
            vehicles=episode.vehicles,
            pedestrians=episode.pedestrians,
            camera=True,
            min_route_length=200.0,
        )
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
