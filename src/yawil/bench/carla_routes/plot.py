"""A picture of a CARLA route file over its map, to see by eye that the routes are sane (`--plot PNG`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from yawil.fileio import atomic_path
from yawil.sim.carla.topology import CarlaTopology

SHOWN = 4  # routes drawn per task


def plot_routes(topo: CarlaTopology, lists: dict[str, list[Any]], out: str | Path) -> Path:
    """Lane points in grey; the first SHOWN routes of each task re-planned on `topo`, start o, goal x. PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in ("straight", "one_turn", "navigation") if n in lists]
    if not names:
        raise ValueError(f"nothing to plot: no straight/one_turn/navigation lists (got {', '.join(lists) or 'none'})")
    fig, axes = plt.subplots(1, len(names), figsize=(6 * len(names), 6), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        for seg in topo.segments:
            ax.plot(seg.xy[:, 0], seg.xy[:, 1], color="0.8", lw=0.6)
        for spec in lists[name][:SHOWN]:
            xy = topo.plan(spec.start, spec.goal).route.xy
            (line,) = ax.plot(xy[:, 0], xy[:, 1], lw=2,
                              label=f"{spec.id}: {spec.length_m:.0f} m {' '.join(spec.turns) or '-'}")
            ax.plot(spec.start.x, spec.start.y, "o", color=line.get_color())
            ax.plot(spec.goal.x, spec.goal.y, "x", color=line.get_color(), ms=10)
        ax.set_title(f"{topo.name}: {name}")
        ax.set_aspect("equal")
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(out)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
    return path
