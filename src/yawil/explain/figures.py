"""Heat maps as pictures: a map normalised, upsampled to the camera image, coloured and blended over it with
weight `alpha` (documented default 0.5: half image, half colour); one frame's figure and a grid of frames
(the paper's Figure 8), drawn with matplotlib."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
        save_figure(fig, path)
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
        save_figure(fig, path)
    return fig


def save_figure(fig, path: Path, dpi: int = 110) -> None:  # type: ignore[no-untyped-def]
    """A matplotlib figure written whole (`yawil.fileio.atomic_path`): every explain figure goes through here."""
    from yawil.fileio import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
