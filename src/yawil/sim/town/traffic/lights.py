"""Traffic lights: one per junction approach, phases per group of approaches.

At each signalised junction, approaches are grouped so that opposite ones (headings within 30 degrees of
reverse) share a phase. Groups take turns: green, yellow, then an all-red gap. Each junction's cycle starts at
an offset drawn from the episode seed, so the same seed gives the same lights. Two junctions joined by a
block shorter than LINK_BLOCK (town02's 20 m block) are coordinated: the phases along that block turn green
together, so the block drains while it fills instead of holding two cars a cycle (queues spilled back over
the whole town in dense traffic), and that phase's green lasts LINKED_GREEN instead of `green`: each green
begins with the block's own cars leaving before the cars behind it find room, a fixed loss per cycle that a
12 s green mostly spent (one car from the queue behind passed a cycle; expert timeouts in town02 dense
traffic). Both are the usual treatment of closely spaced signals: coordination and a longer cycle.
"""

from __future__ import annotations

import math

import numpy as np

from yawil.sim.town.map.lanes import LaneGraph

GREEN, YELLOW, RED = 0, 1, 2
LINK_BLOCK = 30.0  # m: junctions joined by a shorter block share their phase along it
LINKED_GREEN = 24.0  # s: green of the phases along such a block (others: 12 s)
STATE_NAMES = ("green", "yellow", "red")


class TrafficLights:
    def __init__(self, lanes: LaneGraph, green: float = 12.0, yellow: float = 3.0, all_red: float = 2.0,
                 linked_green: float = LINKED_GREEN) -> None:
        self.green, self.yellow, self.all_red, self.linked_green = green, yellow, all_red, linked_green
        n = len(lanes.approaches)
        self.node = np.array([a.node for a in lanes.approaches], dtype=np.int64)
        self.group = np.zeros(n, dtype=np.int64)
        groups_of: dict[int, list[list[int]]] = {}
        for node in np.unique(self.node):
            ids = [int(i) for i in np.flatnonzero(self.node == node)]
            groups: list[list[int]] = []
            for i in ids:
                yaw = lanes.approaches[i].yaw
                for g in groups:
                    if all(abs(math.remainder(yaw - lanes.approaches[j].yaw - math.pi, 2 * math.pi)) < math.radians(30)
                           for j in g):
                        g.append(i)
                        break
                else:
                    groups.append([i])
            for k, g in enumerate(groups):
                self.group[g] = k
            groups_of[int(node)] = groups
        # a short block: (node a, node b, light at a of the block's lane into a, light at b of its lane into b)
        candidates = []
        for to_b, to_a in lanes.road_lanes:
            la, lb = int(lanes.light_of_lane[to_a]), int(lanes.light_of_lane[to_b])
            if la >= 0 and lb >= 0 and lanes.length[to_b] < LINK_BLOCK:
                candidates.append((int(self.node[la]), int(self.node[lb]), la, lb))
        long_phase = {i for _, _, la, lb in candidates for i in (la, lb)}
        # each group's green, the start of its slot in its junction's cycle, and the cycle
        self.green_of = np.full(n, green)
        self.start = np.zeros(n)
        self.cycle = np.zeros(n)
        for groups in groups_of.values():
            t = 0.0
            for g in groups:
                g_green = linked_green if long_phase.intersection(g) else green
                self.green_of[g] = g_green
                self.start[g] = t
                t += g_green + yellow + all_red
            self.cycle[[i for g in groups for i in g]] = t
        self.links = [c for c in candidates if self.cycle[c[2]] == self.cycle[c[3]]]
        self.offset = np.zeros(n)
        self.codes = np.full(n, RED, dtype=np.int64)

    def reset(self, rng: np.random.Generator) -> None:
        nodes = np.unique(self.node)
        per_node = dict(zip(nodes.tolist(), rng.uniform(0.0, 1.0, size=len(nodes)).tolist(), strict=True))
        for a, b, la, lb in self.links:  # b's phase along the block starts with a's
            per_node[b] = float(np.mod(per_node[a] + (self.start[lb] - self.start[la]) / self.cycle[la], 1.0))
        self.offset = np.array([per_node[int(n)] for n in self.node]) * self.cycle
        self.update(0.0)

    def update(self, t: float) -> np.ndarray:
        """Light codes (GREEN/YELLOW/RED) at time t."""
        tau = np.mod(t + self.offset, self.cycle) - self.start
        self.codes = np.where((tau >= 0) & (tau < self.green_of), GREEN,
                              np.where((tau >= self.green_of) & (tau < self.green_of + self.yellow), YELLOW, RED))
        return self.codes

    def names(self) -> dict[int, str]:
        return {i: STATE_NAMES[int(c)] for i, c in enumerate(self.codes)}
