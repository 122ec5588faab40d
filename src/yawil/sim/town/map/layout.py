"""Layout files: the JSON description a town is built from, so a user can add a town without code.

Format (every key but `nodes` and `roads` has a default; see docs/simulator.md):

    {
      "name": "mytown",
      "nodes": {"a": [0, 0], "b": [120, 0], "c": [120, 90], "d": [0, 90]},
      "roads": [["a", "b"], ["b", "c"], ["c", "d"], ["d", "a"]],
      "lane_width": 3.5, "sidewalk_width": 3.0,
      "junction_setback": 10.0, "corner_setback": 10.0, "margin": 30.0,
      "signalised": true,
      "style": {"ground": [0.35, 0.45, 0.3], "road": [0.3, 0.3, 0.32], "sidewalk": [0.62, 0.6, 0.56],
                "building_palette": [[0.7, 0.55, 0.45]], "building_height": [6, 18],
                "building_depth": [8, 14], "building_density": 0.8, "seed": 1}
    }

Roads are straight two-way roads with one lane per direction between two nodes. A node where exactly two
roads meet is a corner (a lane-follow curve); three roads make a T-junction, four a crossing (signalised
unless `"signalised": false`). Nodes with one road (dead ends) or more than four are rejected: there are no
U-turns, so a dead end would trap traffic.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from yawil.sim.town.map.geometry import RGB, Style

MAPS_DIR = Path(__file__).with_name("maps")
BUILTIN_TOWNS: tuple[str, ...] = ("town01", "town02", "square")


@dataclass(frozen=True)
class BuildingStyle:
    height: tuple[float, float] = (6.0, 18.0)
    depth: tuple[float, float] = (8.0, 14.0)
    density: float = 0.8  # probability a building slot along a block is filled
    seed: int = 0


@dataclass(frozen=True)
class Layout:
    name: str
    nodes: tuple[tuple[str, float, float], ...]
    roads: tuple[tuple[int, int], ...]  # node indices
    lane_width: float = 3.5
    sidewalk_width: float = 3.0
    junction_setback: float = 10.0
    corner_setback: float = 10.0
    margin: float = 30.0
    signalised: bool = True
    style: Style = Style()
    buildings: BuildingStyle = BuildingStyle()
    source: str = ""

    @property
    def road_half_width(self) -> float:
        return self.lane_width

    def degree(self, node: int) -> int:
        return sum(1 for a, b in self.roads if node in (a, b))


def resolve_town(town: str) -> Path:
    """A built-in name or a path to a layout file -> the file; ValueError naming the choices otherwise."""
    if town in BUILTIN_TOWNS:
        return MAPS_DIR / f"{town}.json"
    p = Path(town)
    if p.suffix == ".json" and p.is_file():
        return p
    raise ValueError(f"unknown town {town!r}; choose one of {', '.join(BUILTIN_TOWNS)} or a path to a layout .json file")


def load_layout(town: str) -> Layout:
    path = resolve_town(town)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    return parse_layout(data, source=str(path))


def _num(src: str, field: str, value: Any, lo: float, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{src}: field {field!r} must be a number, got {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"{src}: field {field!r}={value!r} must be in [{lo}, {hi}]")
    return float(value)


def _rgb(src: str, field: str, value: Any) -> RGB:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ValueError(f"{src}: field {field!r} must be [r, g, b] with values in [0, 1], got {value!r}")
    r, g, b = (_num(src, field, v, 0.0, 1.0) for v in value)
    return (r, g, b)


def _range(src: str, field: str, value: Any) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ValueError(f"{src}: field {field!r} must be [min, max], got {value!r}")
    lo, hi = _num(src, field, value[0], 0.1), _num(src, field, value[1], 0.1)
    if lo > hi:
        raise ValueError(f"{src}: field {field!r} has min > max: {value!r}")
    return (lo, hi)


def parse_layout(data: Any, source: str = "<layout>") -> Layout:
    """Validate a decoded layout; every error names the file and the field."""
    src = source
    if not isinstance(data, dict):
        raise ValueError(f"{src}: a layout must be a JSON object")
    known = {"name", "nodes", "roads", "lane_width", "sidewalk_width", "junction_setback", "corner_setback",
             "margin", "signalised", "style", "comment"}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"{src}: unknown field(s) {sorted(unknown)}; expected some of {sorted(known)}")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str) or not name:
        raise ValueError(f"{src}: field 'name' must be a non-empty string")
    raw_nodes = data.get("nodes")
    if not isinstance(raw_nodes, dict) or len(raw_nodes) < 3:
        raise ValueError(f"{src}: field 'nodes' must be an object of at least 3 named [x, y] points")
    nodes: list[tuple[str, float, float]] = []
    index: dict[str, int] = {}
    for key, xy in raw_nodes.items():
        if not isinstance(xy, (list, tuple)) or len(xy) != 2:
            raise ValueError(f"{src}: node {key!r} must be [x, y], got {xy!r}")
        x = _num(src, f"nodes.{key}", xy[0], -1e5, 1e5)
        y = _num(src, f"nodes.{key}", xy[1], -1e5, 1e5)
        index[key] = len(nodes)
        nodes.append((key, x, y))
    raw_roads = data.get("roads")
    if not isinstance(raw_roads, list) or not raw_roads:
        raise ValueError(f"{src}: field 'roads' must be a non-empty list of [node, node] pairs")
    roads: list[tuple[int, int]] = []
    seen: set[frozenset[int]] = set()
    for i, r in enumerate(raw_roads):
        if not isinstance(r, (list, tuple)) or len(r) != 2:
            raise ValueError(f"{src}: roads[{i}] must be [node, node], got {r!r}")
        for n in r:
            if n not in index:
                raise ValueError(f"{src}: roads[{i}] names unknown node {n!r}; known nodes: {', '.join(index)}")
        a, b = index[r[0]], index[r[1]]
        if a == b or frozenset((a, b)) in seen:
            raise ValueError(f"{src}: roads[{i}] {r!r} is a loop or a duplicate road")
        seen.add(frozenset((a, b)))
        roads.append((a, b))
    lane_width = _num(src, "lane_width", data.get("lane_width", 3.5), 2.5, 5.0)
    sidewalk_width = _num(src, "sidewalk_width", data.get("sidewalk_width", 3.0), 1.0, 6.0)
    junction_setback = _num(src, "junction_setback", data.get("junction_setback", 10.0), 2 * lane_width + 1.0, 40.0)
    corner_setback = _num(src, "corner_setback", data.get("corner_setback", 10.0), lane_width, 60.0)
    margin = _num(src, "margin", data.get("margin", 30.0), 0.0, 500.0)
    signalised = data.get("signalised", True)
    if not isinstance(signalised, bool):
        raise ValueError(f"{src}: field 'signalised' must be true or false, got {signalised!r}")
    style, bstyle = _parse_style(src, data.get("style", {}))
    layout = Layout(name, tuple(nodes), tuple(roads), lane_width, sidewalk_width, junction_setback, corner_setback,
                    margin, signalised, style, bstyle, source)
    _check_topology(layout)
    return layout


def _parse_style(src: str, raw: Any) -> tuple[Style, BuildingStyle]:
    if not isinstance(raw, dict):
        raise ValueError(f"{src}: field 'style' must be an object")
    known = {"ground", "road", "sidewalk", "building_palette", "building_height", "building_depth",
             "building_density", "seed"}
    unknown = set(raw) - known
    if unknown:
        raise ValueError(f"{src}: unknown style field(s) {sorted(unknown)}; expected some of {sorted(known)}")
    d = Style()
    palette = raw.get("building_palette", d.building_palette)
    if not isinstance(palette, (list, tuple)) or not palette:
        raise ValueError(f"{src}: field 'style.building_palette' must be a non-empty list of [r, g, b]")
    style = Style(
        ground=_rgb(src, "style.ground", raw.get("ground", d.ground)),
        road=_rgb(src, "style.road", raw.get("road", d.road)),
        sidewalk=_rgb(src, "style.sidewalk", raw.get("sidewalk", d.sidewalk)),
        building_palette=tuple(_rgb(src, "style.building_palette", c) for c in palette),
    )
    seed = raw.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"{src}: field 'style.seed' must be a non-negative integer, got {seed!r}")
    b = BuildingStyle(
        height=_range(src, "style.building_height", raw.get("building_height", [6, 18])),
        depth=_range(src, "style.building_depth", raw.get("building_depth", [8, 14])),
        density=_num(src, "style.building_density", raw.get("building_density", 0.8), 0.0, 1.0),
        seed=seed,
    )
    return style, b


def _check_topology(layout: Layout) -> None:
    src = layout.source or layout.name
    for i, (key, x, y) in enumerate(layout.nodes):
        deg = layout.degree(i)
        if deg not in (2, 3, 4):
            raise ValueError(
                f"{src}: node {key!r} has {deg} road(s); every node needs 2 (corner), 3 (T-junction) or 4 (crossing)"
            )
        angles = sorted(
            math.atan2(layout.nodes[b if a == i else a][2] - y, layout.nodes[b if a == i else a][1] - x)
            for a, b in layout.roads
            if i in (a, b)
        )
        gaps = [(angles[(k + 1) % deg] - angles[k]) % (2 * math.pi) or 2 * math.pi for k in range(deg)]
        if min(gaps) < math.radians(45):
            raise ValueError(f"{src}: roads at node {key!r} meet at less than 45 degrees; junctions need wider angles")
        if deg == 2 and min(gaps) < math.radians(80):
            raise ValueError(f"{src}: corner {key!r} turns by more than 100 degrees; too sharp for a lane-follow curve")
    for a, b in layout.roads:
        (ka, xa, ya), (kb, xb, yb) = layout.nodes[a], layout.nodes[b]
        need = _setback(layout, a) + _setback(layout, b) + 10.0
        if math.hypot(xb - xa, yb - ya) < need:
            raise ValueError(f"{src}: road {ka!r}-{kb!r} is shorter than {need:.0f} m (setbacks plus 10 m)")


def _setback(layout: Layout, node: int) -> float:
    return layout.corner_setback if layout.degree(node) == 2 else layout.junction_setback


def setback(layout: Layout, node: int) -> float:
    """Distance from a node's centre where the straight road ends and the junction or curve begins."""
    return _setback(layout, node)
