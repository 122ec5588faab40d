"""Bird's-eye map of a town: roads, paint, buildings, lights, the route, agents and driven trajectories.

Drawn with matplotlib's object API on an Agg canvas (no pyplot, no global state, no display), from the
same `TownGeometry` the camera renders, so a map and a camera frame always agree.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from yawil.fileio import atomic_file
from yawil.sim.town.map.geometry import ActorView, Box, TownGeometry
from yawil.sim.types import Pose

_LIGHT_COLORS = {"red": "#e02020", "yellow": "#f0c020", "green": "#20c040", "off": "#808080"}
_ROUTE_COLOR = "#1f5fff"
_EGO_COLOR = "#ff2d95"
_TRAJ_COLORS = ("#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#17becf", "#d62728", "#bcbd22")


def _box_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [length / 2, width / 2]
    return local @ np.array([[c, s], [-s, c]]) + [x, y]


def _xy(arr: Any, what: str) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] < 2 or a.shape[0] < 1 or not np.all(np.isfinite(a[:, :2])):
        raise ValueError(f"draw_birdseye: {what} must be a finite (N, 2) array of x, y, got shape {a.shape}")
    return a[:, :2]


def draw_birdseye(
    geometry: TownGeometry,
    route_xy: np.ndarray | None = None,
    actors: Sequence[ActorView] = (),
    ego: Pose | ActorView | None = None,  # anything with x, y, yaw
    light_states: Mapping[int, str] | None = None,
    path: str | os.PathLike[str] | None = None,
    ax: Any = None,
    trajectories: Mapping[str, np.ndarray] | None = None,
) -> Any:
    """Draw the map (into `ax`, or a new figure sized to the town) and return the matplotlib Figure.

    `trajectories` maps a label to an (N, 2) path, drawn with a legend (e.g. one per method, as the
    paper's Fig. 7). With `path`, the figure is saved there (format from the suffix, PNG by default),
    written to a temporary file first and renamed, so an existing file is never left half-written.
    """
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.figure import Figure

    xmin, ymin, xmax, ymax = geometry.bounds
    if not (xmax > xmin and ymax > ymin):
        raise ValueError(f"draw_birdseye: TownGeometry {geometry.name!r} bounds {geometry.bounds} are empty")
    if ax is None:
        span = max(xmax - xmin, ymax - ymin)
        fig = Figure(figsize=(8.0 * (xmax - xmin) / span + 0.6, 8.0 * (ymax - ymin) / span + 0.6), dpi=100)
        ax = fig.add_subplot(1, 1, 1)
    fig = ax.figure
    style = geometry.style
    ax.set_facecolor(style.ground)
    if geometry.road_polygons:
        ax.add_collection(PolyCollection([np.asarray(p)[:, :2] for p in geometry.road_polygons],
                                         facecolors=[style.road], edgecolors="none", zorder=1))
    if geometry.sidewalk_polygons:
        ax.add_collection(PolyCollection([np.asarray(p)[:, :2] for p in geometry.sidewalk_polygons],
                                         facecolors=[style.sidewalk], edgecolors="none", zorder=2))
    solid = [m for m in geometry.markings if not m.dashed]
    dashed = [m for m in geometry.markings if m.dashed]
    for group, ls in ((solid, "solid"), (dashed, (0, (3, 3)))):
        if group:
            ax.add_collection(LineCollection([np.asarray(m.points)[:, :2] for m in group], colors=[m.color for m in group],
                                             linewidths=0.6, linestyles=ls, zorder=3))
    boxes: list[Box] = list(geometry.buildings) + list(geometry.props)
    if boxes:
        ax.add_collection(PolyCollection([_box_corners(b.x, b.y, b.yaw, b.length, b.width) for b in boxes],
                                         facecolors=[b.color for b in boxes], edgecolors="#303030",
                                         linewidths=0.3, zorder=4))
    if geometry.light_posts:
        states = light_states or {}
        ax.scatter([lp.x for lp in geometry.light_posts], [lp.y for lp in geometry.light_posts], s=14,
                   c=[_LIGHT_COLORS.get(states.get(lp.id, "off"), "#808080") for lp in geometry.light_posts],
                   edgecolors="black", linewidths=0.4, zorder=6)
    if route_xy is not None:
        r = _xy(route_xy, "route_xy")
        ax.plot(r[:, 0], r[:, 1], color=_ROUTE_COLOR, linewidth=2.0, alpha=0.8, zorder=5, label="route")
        ax.plot([r[0, 0]], [r[0, 1]], marker="o", color=_ROUTE_COLOR, markersize=6, zorder=7)
        ax.plot([r[-1, 0]], [r[-1, 1]], marker="*", color=_ROUTE_COLOR, markersize=11, zorder=7)
    for k, (label, traj) in enumerate((trajectories or {}).items()):
        t = _xy(traj, f"trajectories[{label!r}]")
        ax.plot(t[:, 0], t[:, 1], color=_TRAJ_COLORS[k % len(_TRAJ_COLORS)], linewidth=1.4, zorder=8, label=label)
    vehicles = [a for a in actors if a.kind == "vehicle"]
    walkers = [a for a in actors if a.kind != "vehicle"]
    if vehicles:
        ax.add_collection(PolyCollection([_box_corners(a.x, a.y, a.yaw, a.length, a.width) for a in vehicles],
                                         facecolors=[a.color for a in vehicles], edgecolors="black",
                                         linewidths=0.4, zorder=9))
    if walkers:
        ax.scatter([a.x for a in walkers], [a.y for a in walkers], s=8, c=[a.color for a in walkers],
                   edgecolors="black", linewidths=0.3, zorder=9)
    if ego is not None:
        ax.add_collection(PolyCollection([_box_corners(ego.x, ego.y, ego.yaw, 4.6, 2.0)], facecolors=[_EGO_COLOR],
                                         edgecolors="black", linewidths=0.6, zorder=10))
        ax.annotate("", xy=(ego.x + 6 * math.cos(ego.yaw), ego.y + 6 * math.sin(ego.yaw)), xytext=(ego.x, ego.y),
                    arrowprops={"arrowstyle": "->", "color": _EGO_COLOR, "lw": 1.5}, zorder=10)
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_title(geometry.name, fontsize=9)
    ax.tick_params(labelsize=7)
    if trajectories or route_xy is not None:
        ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    if path is not None:
        _save_atomic(fig, Path(path))
    return fig


def _save_atomic(fig: Any, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if fig.canvas is None or not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    with atomic_file(path) as f:
        fig.savefig(f, format=path.suffix[1:].lower() or "png", bbox_inches="tight")
