"""`yawil data stats`: what a dataset holds, as the paper's Figure 7 shows it.

Frames by road option and weather (bars), and the histograms of steer, throttle and brake. The figures
come from the label columns of the episode files (no image is decoded). An unusable file is an error naming
it: figures of the episodes that are left would describe another dataset without a word.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from yawil.data.dataset import as_roots, load_episode_labels, manifest_episodes
from yawil.data.schema import COMMAND_NAMES, DRIVERS, SPEED_REASONS
from yawil.fileio import atomic_file

PathLike = str | os.PathLike[str]
BINS = {"steer": np.linspace(-1.0, 1.0, 41), "throttle": np.linspace(0.0, 1.0, 21), "brake": np.linspace(0.0, 1.0, 21)}
OPTION_ORDER = ("LEFT", "RIGHT", "STRAIGHT", "LANEFOLLOW")  # the paper's bar order


@dataclass
class DatasetStats:
    episodes: int = 0
    frames: int = 0
    by_weather_option: dict[str, dict[str, int]] = field(default_factory=dict)  # weather -> option -> frames
    lane_follow_turn_frames: int = 0
    noise_frames: int = 0
    histograms: dict[str, np.ndarray] = field(default_factory=dict)  # name -> counts over BINS[name]
    means: dict[str, float] = field(default_factory=dict)
    by_driver: dict[str, int] = field(default_factory=dict)  # DRIVERS name -> frames (schema 2)
    by_round: dict[int, int] = field(default_factory=dict)  # DAgger round -> frames
    by_reason: dict[str, int] = field(default_factory=dict)  # what set the expert's target speed; "unknown"

    def by_option(self) -> dict[str, int]:
        return {o: sum(w.get(o, 0) for w in self.by_weather_option.values()) for o in OPTION_ORDER}

    def by_weather(self) -> dict[str, int]:
        return {w: sum(c.values()) for w, c in sorted(self.by_weather_option.items())}

    def lines(self) -> list[str]:
        f = max(self.frames, 1)
        out = [f"{self.episodes} episodes, {self.frames} frames"]
        out.append("by road option: " + ", ".join(f"{o} {n} ({100 * n / f:.1f}%)" for o, n in self.by_option().items()))
        out.append("by weather: " + ", ".join(f"{w} {n} ({100 * n / f:.1f}%)" for w, n in self.by_weather().items()))
        out.append(
            f"lane-follow curve frames {self.lane_follow_turn_frames} ({100 * self.lane_follow_turn_frames / f:.1f}%), "
            f"noisy frames {self.noise_frames} ({100 * self.noise_frames / f:.1f}%)"
        )
        out.append("means: " + ", ".join(f"{k} {v:.3f}" for k, v in self.means.items()))
        out.append("by driver: " + ", ".join(f"{d} {n} ({100 * n / f:.1f}%)" for d, n in self.by_driver.items() if n)
                   + "; by round: " + ", ".join(f"{r}: {n}" for r, n in sorted(self.by_round.items())))
        out.append("expert's target speed set by: "
                   + ", ".join(f"{r} {n} ({100 * n / f:.1f}%)" for r, n in self.by_reason.items() if n))
        return out


def compute_stats(roots: PathLike | Sequence[PathLike]) -> DatasetStats:
    st = DatasetStats(histograms={k: np.zeros(len(b) - 1, dtype=np.int64) for k, b in BINS.items()})
    sums = {k: 0.0 for k in ("steer", "throttle", "brake", "speed")}
    for root, entry in manifest_episodes(as_roots(roots)):
        path = root / entry.file
        lab = load_episode_labels(path, entry)  # a ValueError naming the file
        st.episodes += 1
        st.frames += len(lab["frame"])
        per = st.by_weather_option.setdefault(entry.weather, {o: 0 for o in OPTION_ORDER})
        for value, name in COMMAND_NAMES.items():
            per[name] += int(np.sum(lab["command"] == value))
        st.lane_follow_turn_frames += int(lab["lane_follow_turn"].sum())
        st.noise_frames += int(lab["noise"].sum())
        for i, name in enumerate(DRIVERS):
            st.by_driver[name] = st.by_driver.get(name, 0) + int(np.sum(lab["driver"] == i))
        for r, n in zip(*np.unique(lab["round"], return_counts=True), strict=True):
            st.by_round[int(r)] = st.by_round.get(int(r), 0) + int(n)
        for i, name in enumerate((*SPEED_REASONS, "unknown")):
            st.by_reason[name] = st.by_reason.get(name, 0) + int(np.sum(lab["speed_reason"] == (i if i < len(SPEED_REASONS) else -1)))
        for k, b in BINS.items():
            st.histograms[k] += np.histogram(np.clip(lab[k], b[0], b[-1]), bins=b)[0]
        for k in sums:
            sums[k] += float(lab[k].astype(np.float64).sum())
    st.means = {k: v / max(st.frames, 1) for k, v in sums.items()}
    return st


def plot_stats(st: DatasetStats, png_path: PathLike, title: str = "") -> Path:
    """Figure 7's four panels into a PNG (written to a temporary file, then renamed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    ax = axes[0]
    weathers = sorted(st.by_weather_option)
    x = np.arange(len(OPTION_ORDER))
    width = 0.8 / max(len(weathers), 1)
    for i, w in enumerate(weathers):
        ax.bar(x + (i - (len(weathers) - 1) / 2) * width, [st.by_weather_option[w][o] for o in OPTION_ORDER], width, label=w)
    ax.set_xticks(x, [o.lower() for o in OPTION_ORDER])
    ax.set_ylabel("frames")
    ax.set_title("road option by weather")
    if weathers:
        ax.legend(fontsize=7)
    for ax, (name, counts) in zip(axes[1:], st.histograms.items(), strict=True):
        b = BINS[name]
        ax.bar(b[:-1], counts, width=np.diff(b), align="edge", color="tab:gray", edgecolor="black", linewidth=0.3)
        ax.set_yscale("log")  # throttle and brake are mostly exactly 0: a linear axis would show one bar
        ax.set_ylim(bottom=0.8)
        ax.set_title(f"{name} (mean {st.means.get(name, 0.0):.3f})")
        ax.set_xlabel(name)
    axes[1].set_ylabel("frames (log)")
    fig.suptitle(title or f"{st.episodes} episodes, {st.frames} frames")
    fig.tight_layout()
    out = Path(png_path)
    try:
        with atomic_file(out) as f:
            fig.savefig(f, format="png", dpi=100)
    finally:
        plt.close(fig)
    return out


def write_stats(root: PathLike | Sequence[PathLike], png_path: PathLike, quiet: bool = False) -> Path:
    """Print the dataset's distribution and plot it (Figure 7) to `png_path`; returns the PNG's path."""
    st = compute_stats(root)
    if st.frames == 0:
        raise ValueError(f"{root}: no usable frames to describe")
    if not quiet:
        print("\n".join(st.lines()))
    roots = as_roots(root)
    return plot_stats(st, png_path, title=f"{', '.join(r.name for r in roots)}: {st.episodes} episodes, {st.frames} frames")
