"""The town map under the benchmark's plots and videos.

Uses the simulator's bird's-eye drawing (`yawil.sim.town.render.birdseye.draw_birdseye`) when it is available, and
otherwise a plain drawing of the road and sidewalk polygons, so reports never depend on it.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def map_figure(town: str, route_xy: np.ndarray | None = None) -> Any:
    """A matplotlib Figure with the town's map (and the route) on its first axes, map units = metres."""
    import matplotlib

    matplotlib.use("Agg")
    from yawil.sim.town.map.town import get_town

    geometry = get_town(town).geometry
    try:
        from yawil.sim.town.render.birdseye import draw_birdseye
    except ImportError:
        return _plain_map(geometry, route_xy)
    return draw_birdseye(geometry, route_xy=route_xy)


def _plain_map(geometry: Any, route_xy: np.ndarray | None) -> Any:
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    xmin, ymin, xmax, ymax = geometry.bounds
    fig, ax = plt.subplots(figsize=(7, 7 * (ymax - ymin) / max(1e-6, xmax - xmin)))
    ax.set_facecolor(geometry.style.ground)
    for poly in geometry.sidewalk_polygons:
        ax.add_patch(Polygon(poly, closed=True, color=geometry.style.sidewalk, lw=0))
    for poly in geometry.road_polygons:
        ax.add_patch(Polygon(poly, closed=True, color=geometry.style.road, lw=0))
    if route_xy is not None:
        ax.plot(route_xy[:, 0], route_xy[:, 1], color="0.85", lw=2)
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    return fig
