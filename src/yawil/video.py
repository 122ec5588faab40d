"""Video frames and files: a drawn matplotlib figure as pixels, frames written as MP4 (GIF without ffmpeg).

Used by the benchmark runner's episode recordings and by `yawil.explain`'s heat-map videos. numpy at module
level; matplotlib and imageio load inside the functions.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


def figure_to_array(fig) -> np.ndarray:  # type: ignore[no-untyped-def]
    """RGB uint8 pixels of a drawn matplotlib figure (for video frames).

    A bare `matplotlib.figure.Figure` (the bird's-eye map) has a FigureCanvasBase that cannot render:
    it gets an Agg canvas here, as pyplot would give it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[..., :3])


def write_video(frames: Sequence[np.ndarray], path: Path, fps: int = 10) -> Path:
    """MP4 through imageio-ffmpeg; GIF when ffmpeg is not available. Returns the path written."""
    import imageio.v2 as imageio

    from yawil.fileio import atomic_path

    if not frames:
        raise ValueError("write_video needs at least one frame")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h = max(f.shape[0] for f in frames)
    w = max(f.shape[1] for f in frames)
    # codecs want even sizes and equal frames: pad to a common even size
    h += h % 2
    w += w % 2
    padded = []
    for f in frames:
        canvas = np.zeros((h, w, 3), dtype=np.uint8)
        canvas[: f.shape[0], : f.shape[1]] = f
        padded.append(canvas)
    if path.suffix.lower() == ".mp4":
        try:
            with atomic_path(path) as tmp, imageio.get_writer(tmp, fps=fps, codec="libx264",
                                                              macro_block_size=1) as writer:
                for f in padded:
                    writer.append_data(f)  # type: ignore[attr-defined]
            return path
        except Exception:  # ffmpeg missing or failing: fall back to GIF
            path = path.with_suffix(".gif")
    with atomic_path(path) as tmp:
        imageio.mimsave(tmp, padded, duration=1.0 / fps, loop=0)  # type: ignore[arg-type]
    return path


def read_video_frames(path: Path) -> int:
    """Number of frames in a video file (used by tests and the report)."""
    import imageio.v3 as iio

    return sum(1 for _ in iio.imiter(path))
