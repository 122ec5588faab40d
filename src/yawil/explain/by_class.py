"""Attention by class: how much of each map's mass falls on each semantic class, against the class's pixel share
(issue 42; docs/explain.md, "Attention by class").

The paper shows heat maps and says what they look at (layer 1 the passable area, layer 2 the lane lines, layer 3
details, braking frames the obstacle). The semantic camera (`Scenario(semantic=True)`) knows what every pixel is,
so this module measures it:

- `gather_frames`: drives benchmark episodes **with the expert** and runs a map source (the learned agent's
  attention by default, `AgentMaps`) on every `every`-th frame of the same observations. The expert drives, not the
  agent, because the situation labels come from the expert's own decision (it knows why it brakes: a vehicle, a
  pedestrian, a light), and its decisions are only meaningful on the states it drove into itself: evaluated beside
  a learned driver its PID, light decisions and restart hold would describe a car it does not control. These are
  also the states the agent was trained on (expert data and DAgger), and the drive is the same for any map source.
- `label_situations`: free driving, turning, braking for a vehicle / pedestrian / light, other (`SituationRules`).
- `by_class_table`: the pure computation from arrays (maps, class ids, situation labels) to the table (`ByClass`);
  unit-tested with synthetic maps whose answers are known.
- `write_by_class`: JSON, Markdown and one figure, written atomically; `run_by_class` does all of it.

Maps of any resolution are brought to the camera image as the figures draw them (`figures.normalise_map`, then
`figures.upsample`, bilinear) and scaled to sum to one there. A map source is any callable `obs -> [map, ...]`
(non-negative 2-D arrays, one per layer, the same shapes every frame): channel-mean activation maps of CIL/CILRS
(`AgentMaps(agent, "activation")`) or any other.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from yawil.explain.figures import normalise_map, save_figure, upsample
from yawil.sim.semantic import CLASS_ID, CLASSES
from yawil.sim.types import RoadOption

if TYPE_CHECKING:
    import argparse

    from yawil.agent import Agent
    from yawil.bench.suites import Episode
    from yawil.sim.types import Observation, World

FORMAT = "yawil-attention-by-class/1"
ALL = "all"
# Row order of the table (ALL first); every frame is in exactly one of the others (`label_situation`).
SITUATIONS: tuple[str, ...] = ("free", "turning", "brake_vehicle", "brake_pedestrian", "brake_light", "other")
TITLES: dict[str, str] = {
    ALL: "all frames", "free": "free driving", "turning": "turning", "brake_vehicle": "braking for a vehicle",
    "brake_pedestrian": "braking for a pedestrian", "brake_light": "braking for a red/yellow light",
    "other": "other",
}
# The expert's reasons (`ExpertState.reason`) that make a braking frame one of the braking situations. "junction"
# is a vehicle crossing the junction the ego is about to enter.
BRAKE_REASONS: dict[str, str] = {"vehicle": "brake_vehicle", "junction": "brake_vehicle",
                                 "pedestrian": "brake_pedestrian", "red_light": "brake_light",
                                 "yellow_light": "brake_light"}
FREE_REASONS = ("cruise", "curve")  # no agent or light binds the expert's target speed
# Unions of classes reported beside the classes (their lift: summed mass over summed share).
GROUPS: dict[str, tuple[str, ...]] = {
    "passable": ("road", "lane_marking", "crosswalk"),
    "lights": ("traffic_light", "light_red", "light_yellow", "light_green"),
}
STANDING = 0.5  # m/s: below this the car stands (the expert's own hold threshold)

MapsFn = Callable[["Observation"], Sequence[np.ndarray]]


# ----- situations -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SituationRules:
    """How a frame's situation is read from the expert's decision on it (first match wins):

    1. `brake_vehicle` / `brake_pedestrian` / `brake_light`: the expert brakes (brake > `brake`) and the stop
       point that binds its target speed is a vehicle (or crossing traffic in a junction), a pedestrian, a red or
       yellow light (`BRAKE_REASONS`). Standing at the stop (hold brake) counts: the net must keep braking there.
    2. `turning`: the command is LEFT or RIGHT (the route's road option 3 waypoints ahead, what CIL is told), or
       the expert steers harder than |steer| > `steer` (1 = 35 degrees at the wheels; 0.15 is 5.25 degrees, a
       31 m radius with the expert's 2.9 m wheelbase: every junction turn, no lane keeping).
    3. `free`: not braking, and nothing but the cruise speed or the road's curvature sets the target speed.
    4. `other`: the rest: braking for the goal or a bend, following or coasting behind a lead, slowing for a
       hazard without braking yet."""

    brake: float = 0.05
    steer: float = 0.15

    def __post_init__(self) -> None:
        for name in ("brake", "steer"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v < 1.0:
                raise ValueError(f"SituationRules.{name}={v!r}: expected a number in [0, 1)")


def label_situation(brake: float, reason: str, command: int, steer: float,
                    rules: SituationRules = SituationRules()) -> str:
    """The situation of one frame (`SituationRules`)."""
    braking = brake > rules.brake
    if braking and reason in BRAKE_REASONS:
        return BRAKE_REASONS[reason]
    if int(command) in (RoadOption.LEFT, RoadOption.RIGHT) or abs(steer) > rules.steer:
        return "turning"
    if not braking and reason in FREE_REASONS:
        return "free"
    return "other"


def label_situations(brake: ArrayLike, reason: ArrayLike, command: ArrayLike, steer: ArrayLike,
                     rules: SituationRules = SituationRules()) -> np.ndarray:
    """`label_situation` of every frame, as a string array."""
    b, r, c, s = (np.atleast_1d(np.asarray(v)) for v in (brake, reason, command, steer))
    if not len(b) == len(r) == len(c) == len(s):
        raise ValueError(f"label_situations: {len(b)} brakes, {len(r)} reasons, {len(c)} commands, "
                         f"{len(s)} steers: one each per frame")
    labels = [label_situation(float(bi), str(ri), int(ci), float(si), rules)
              for bi, ri, ci, si in zip(b, r, c, s, strict=True)]
    return np.array(labels, dtype=f"<U{max(map(len, SITUATIONS))}")


# ----- the pure computation ------------------------------------------------------------------------------------


def image_map(att: np.ndarray, height: int, width: int) -> np.ndarray:
    """A map as the figures draw it (normalised, bilinearly upsampled), scaled to sum to one on the image."""
    up = upsample(normalise_map(att), height, width)
    return np.asarray(up / up.sum())


def class_mass(att: np.ndarray, ids: np.ndarray, n_classes: int = len(CLASSES)) -> np.ndarray:
    """(n_classes,): the mass of one map (any resolution) on each class of one frame's ids (H, W); sums to one."""
    return _bincount(image_map(att, ids.shape[0], ids.shape[1]), ids, n_classes)


def _bincount(p: np.ndarray, ids: np.ndarray, n_classes: int = len(CLASSES)) -> np.ndarray:
    return np.bincount(ids.ravel(), weights=p.ravel(), minlength=n_classes)[:n_classes]


def _layer_masses(att: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One layer's (F, n_classes) masses; those of its mean map (the mean over the frames of the maps at image
    resolution: where the layer looks on average) on the same frames; and each frame's spread (`ByClass`)."""
    height, width = ids.shape[1:]
    total = np.zeros((height, width))
    masses, spread = [], []
    for f in range(ids.shape[0]):
        p = image_map(att[f], height, width)
        total += p
        masses.append(_bincount(p, ids[f]))
        q = p[p > 0]
        spread.append(math.exp(float(-(q * np.log(q)).sum())) / p.size)
    mean = total / max(ids.shape[0], 1)
    return np.stack(masses), np.stack([_bincount(mean, ids[f]) for f in range(ids.shape[0])]), np.array(spread)


def class_share(ids: np.ndarray, n_classes: int = len(CLASSES)) -> np.ndarray:
    """(n_classes,): the fraction of one frame's pixels of each class."""
    return np.bincount(ids.ravel(), minlength=n_classes)[:n_classes] / ids.size


@dataclass(frozen=True)
class ByClass:
    """Attention by class, per layer x situation x column (the classes, then `GROUPS`).

    For the frames of a situation: `share` is the mean over frames of each column's pixel share, `mass` the mean
    over frames of each layer's map mass on it, and `lift` = mass / share, the lift of the means. That is the
    lift over all the situation's pixels pooled (every frame has one unit of mass and one of pixels), and it is
    what the table reports, rather than the mean of per-frame lifts: a class of a few pixels in one frame (a
    far pedestrian, a light's face) gives a per-frame lift of up to 1/share, which would swamp such a mean.

    A frame where a class is absent adds nothing to its mass or share, so it drops out of the class's lift
    (while `mass` and `share` stay means over all the situation's frames); a class absent from every frame of a
    situation has lift NaN (JSON null, "-" in the tables). `present` is the fraction of frames that show the
    column at all. 1 means the map looks at a class as much as a uniform map would; above 1 it favours it.

    `lift_lo`/`lift_hi`: a 95 % bootstrap interval of the lift, resampling whole episodes (`groups`) with
    replacement (frames of one episode are far from independent); NaN with fewer than two episodes.

    `prior`: the lift that the layer's mean map (its maps at image resolution averaged over all the table's
    frames, whatever their situation) gets on the same frames: what the layer would score by looking where it
    usually looks, whatever the frame shows. Classes have habitual places (the road below the horizon, lights
    above it), so a lift above 1 alone does not say the map follows the class; lift / prior above 1 does.
    `spread`: per layer and situation, the mean over frames of exp(entropy) / pixels of the map at image
    resolution: the fraction of the image it effectively covers (1: uniform; 0.01: a blob of 1 % of the image).
    `flags`: per situation, the mean of per-frame values given to `by_class_table` (e.g. the share of frames
    where the agent brakes, or where the car stands)."""

    layers: tuple[str, ...]
    situations: tuple[str, ...]
    columns: tuple[str, ...]
    frames: np.ndarray  # (S,) frames per situation
    episodes: np.ndarray  # (S,) distinct groups per situation
    share: np.ndarray  # (S, K)
    present: np.ndarray  # (S, K)
    mass: np.ndarray  # (L, S, K)
    lift: np.ndarray  # (L, S, K)
    lift_lo: np.ndarray  # (L, S, K)
    lift_hi: np.ndarray  # (L, S, K)
    prior: np.ndarray  # (L, S, K) the lift of the layer's mean map (where it looks on average) on the same frames
    spread: np.ndarray  # (L, S) mean over frames of the fraction of the image a map effectively covers
    flags: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (S,)

    def shown_columns(self) -> list[int]:
        """Columns with any pixel in any frame (the tables and the figure leave out the others)."""
        return [k for k in range(len(self.columns)) if self.share[0, k] > 0]  # row 0 is ALL

    def to_dict(self) -> dict[str, Any]:
        rows = []
        for li, layer in enumerate(self.layers):
            for si, sit in enumerate(self.situations):
                rows.append({
                    "layer": layer, "situation": sit, "frames": int(self.frames[si]),
                    "episodes": int(self.episodes[si]),
                    "share": _named(self.columns, self.share[si]), "present": _named(self.columns, self.present[si]),
                    "mass": _named(self.columns, self.mass[li, si]), "lift": _named(self.columns, self.lift[li, si]),
                    "prior": _named(self.columns, self.prior[li, si]),
                    "lift_ci95": {c: [_finite(lo), _finite(hi)] for c, lo, hi in
                                  zip(self.columns, self.lift_lo[li, si], self.lift_hi[li, si], strict=True)},
                    "spread": _finite(float(self.spread[li, si])),
                    **{name: _finite(float(v[si])) for name, v in self.flags.items()},
                })  # fmt: skip
        return {"format": FORMAT, "layers": list(self.layers), "situations": list(self.situations),
                "columns": list(self.columns), "groups": {k: list(v) for k, v in GROUPS.items()}, "rows": rows}


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _named(columns: Sequence[str], values: np.ndarray) -> dict[str, float | None]:
    return {c: _finite(float(v)) for c, v in zip(columns, values, strict=True)}


def _column_matrix(n_classes: int) -> tuple[tuple[str, ...], np.ndarray]:
    """Column names (classes, then groups) and the (n_classes, K) 0/1 matrix that sums classes into them."""
    names = list(CLASSES[:n_classes])
    cols = [np.eye(n_classes)]
    for g, members in GROUPS.items():
        v = np.zeros((n_classes, 1))
        v[[CLASS_ID[m] for m in members if CLASS_ID[m] < n_classes], 0] = 1.0
        names.append(g)
        cols.append(v)
    return tuple(names), np.concatenate(cols, axis=1)


def by_class_table(
    maps: Sequence[np.ndarray],
    ids: np.ndarray,
    situations: ArrayLike,
    *,
    layer_names: Sequence[str] | None = None,
    groups: ArrayLike | None = None,
    flags: Mapping[str, ArrayLike] | None = None,
    bootstrap: int = 1000,
    seed: int = 0,
) -> ByClass:
    """The table (`ByClass`) from arrays: `maps` one (F, h, w) array per layer (any resolution, non-negative),
    `ids` (F, H, W) class ids of `yawil.sim.semantic`, `situations` (F,) labels (`SITUATIONS`; others are an
    error). `groups` (F,): which episode each frame comes from, for the bootstrap interval (default: one group,
    no interval). `flags`: per-frame values averaged per situation. Situation "all" is every frame."""
    ids = np.asarray(ids)
    if ids.ndim != 3 or not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"ids: expected an integer array (frames, H, W), got {ids.shape} {ids.dtype}")
    n_frames = ids.shape[0]
    if ids.size and (int(ids.min()) < 0 or int(ids.max()) >= len(CLASSES)):
        raise ValueError(f"ids must lie in [0, {len(CLASSES)})")
    if not maps:
        raise ValueError("maps: expected one (frames, h, w) array per layer, got none")
    layer_maps = [np.asarray(m, dtype=np.float64) for m in maps]
    for i, m in enumerate(layer_maps):
        if m.ndim != 3 or m.shape[0] != n_frames:
            raise ValueError(f"maps[{i}]: expected ({n_frames}, h, w), got {m.shape}")
    labels = np.asarray(situations).astype(str)
    if labels.shape != (n_frames,):
        raise ValueError(f"situations: expected {n_frames} labels, got shape {labels.shape}")
    unknown = sorted(set(labels.tolist()) - set(SITUATIONS))
    if unknown:
        raise ValueError(f"situations: unknown labels {unknown}; expected {', '.join(SITUATIONS)}")
    group = np.zeros(n_frames, dtype=np.int64) if groups is None else np.asarray(groups, dtype=np.int64)
    if group.shape != (n_frames,):
        raise ValueError(f"groups: expected {n_frames} values, got shape {group.shape}")
    names = tuple(layer_names) if layer_names is not None else tuple(f"layer {i + 1}" for i in range(len(maps)))
    if len(names) != len(layer_maps):
        raise ValueError(f"layer_names: {len(names)} names for {len(layer_maps)} layers")

    columns, to_cols = _column_matrix(len(CLASSES))
    if not n_frames:
        raise ValueError("by_class_table: no frames")
    share_f = np.stack([class_share(f) for f in ids]) @ to_cols  # (F, K)
    both = [_layer_masses(m, ids) for m in layer_maps]
    mass_f = np.stack([m for m, _, _ in both]) @ to_cols  # (L, F, K)
    prior_f = np.stack([p for _, p, _ in both]) @ to_cols
    spread_f = np.stack([e for _, _, e in both])  # (L, F)

    rows = (ALL, *SITUATIONS)
    n_s, n_l, n_k = len(rows), len(layer_maps), len(columns)
    frames = np.zeros(n_s, dtype=np.int64)
    episodes = np.zeros(n_s, dtype=np.int64)
    share, present = np.full((n_s, n_k), np.nan), np.full((n_s, n_k), np.nan)
    mass, lift = np.full((n_l, n_s, n_k), np.nan), np.full((n_l, n_s, n_k), np.nan)
    lo, hi = np.full((n_l, n_s, n_k), np.nan), np.full((n_l, n_s, n_k), np.nan)
    prior = np.full((n_l, n_s, n_k), np.nan)
    spread = np.full((n_l, n_s), np.nan)
    flag_out = {k: np.full(n_s, np.nan) for k in (flags or {})}
    rng = np.random.default_rng(seed)
    for si, sit in enumerate(rows):
        sel = np.ones(n_frames, dtype=bool) if sit == ALL else labels == sit
        frames[si] = int(sel.sum())
        if not frames[si]:
            continue
        episodes[si] = len(np.unique(group[sel]))
        share[si] = share_f[sel].mean(axis=0)
        present[si] = (share_f[sel] > 0).mean(axis=0)
        mass[:, si] = mass_f[:, sel].mean(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            lift[:, si] = np.where(share[si] > 0, mass[:, si] / share[si], np.nan)
            prior[:, si] = np.where(share[si] > 0, prior_f[:, sel].mean(axis=1) / share[si], np.nan)
        spread[:, si] = spread_f[:, sel].mean(axis=1)
        for k, v in (flags or {}).items():
            vals = np.asarray(v, dtype=np.float64)[sel]
            flag_out[k][si] = float(np.nanmean(vals)) if np.isfinite(vals).any() else np.nan
        if episodes[si] >= 2 and bootstrap > 0:
            lo[:, si], hi[:, si] = _bootstrap(mass_f[:, sel], share_f[sel], group[sel], bootstrap, rng)
    return ByClass(names, rows, columns, frames, episodes, share, present, mass, lift, lo, hi, prior, spread,
                   flag_out)


def _bootstrap(mass_f: np.ndarray, share_f: np.ndarray, group: np.ndarray, draws: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """95 % interval of the lift of the means, resampling groups (episodes) with replacement: (L, K) twice."""
    uniq, inv = np.unique(group, return_inverse=True)
    g_mass = np.stack([np.stack([m[inv == g].sum(axis=0) for g in range(len(uniq))]) for m in mass_f])  # (L, G, K)
    g_share = np.stack([share_f[inv == g].sum(axis=0) for g in range(len(uniq))])  # (G, K)
    weights = rng.multinomial(len(uniq), np.full(len(uniq), 1.0 / len(uniq)), size=draws).astype(np.float64)
    num = np.einsum("bg,lgk->blk", weights, g_mass)
    den = (weights @ g_share)[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        lifts = np.where(den > 0, num / den, np.nan)
    out = np.full((2, *lifts.shape[1:]), np.nan)
    ok = np.isfinite(lifts).any(axis=0)
    if ok.any():
        out[:, ok] = np.nanpercentile(lifts[:, ok], [2.5, 97.5], axis=0)
    return out[0], out[1]


# ----- frames: the expert drives, a map source looks ------------------------------------------------------------


@dataclass
class Frames:
    """What `gather_frames` kept: per frame the maps (one (F, h, w) array per layer), the semantic ids, the
    expert's decision (the situation's source) and what the map source said (`agent_brake`, NaN if unknown)."""

    maps: list[np.ndarray]
    ids: np.ndarray  # (F, H, W) uint8
    layer_names: tuple[str, ...]
    episode: np.ndarray  # (F,) index into `episode_keys`
    step: np.ndarray  # (F,) step of the episode
    expert_brake: np.ndarray
    expert_steer: np.ndarray
    expert_reason: np.ndarray  # (F,) str
    command: np.ndarray  # (F,) int, RoadOption values
    speed: np.ndarray  # (F,) m/s
    agent_brake: np.ndarray  # (F,) the map source's brake on the frame (AgentMaps), NaN when it has none
    episode_keys: list[str]

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def situations(self, rules: SituationRules = SituationRules()) -> np.ndarray:
        return label_situations(self.expert_brake, self.expert_reason, self.command, self.expert_steer, rules)

    def table(self, rules: SituationRules = SituationRules(), bootstrap: int = 1000, seed: int = 0) -> ByClass:
        """`by_class_table` of these frames, with the share of frames where the agent brakes and the car stands."""
        flags = {"standing": (self.speed < STANDING).astype(np.float64)}
        if np.isfinite(self.agent_brake).any():
            flags["agent_brakes"] = np.where(np.isfinite(self.agent_brake), self.agent_brake > 0.0, np.nan)
        return by_class_table(self.maps, self.ids, self.situations(rules), layer_names=self.layer_names,
                              groups=self.episode, flags=flags, bootstrap=bootstrap, seed=seed)

    def save(self, path: Path) -> Path:
        """All arrays in one compressed .npz (written atomically): the table can be recomputed without driving."""
        from yawil.fileio import atomic_path

        arrays = {f"map_{i}": m for i, m in enumerate(self.maps)}
        arrays.update(ids=self.ids, layer_names=np.array(self.layer_names), episode=self.episode, step=self.step,
                      expert_brake=self.expert_brake, expert_steer=self.expert_steer,
                      expert_reason=self.expert_reason, command=self.command, speed=self.speed,
                      agent_brake=self.agent_brake, episode_keys=np.array(self.episode_keys))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: Path) -> Frames:
        with np.load(path, allow_pickle=False) as z:
            n = len([k for k in z.files if k.startswith("map_")])
            return cls(maps=[z[f"map_{i}"] for i in range(n)], ids=z["ids"],
                       layer_names=tuple(z["layer_names"].tolist()), episode=z["episode"], step=z["step"],
                       expert_brake=z["expert_brake"], expert_steer=z["expert_steer"],
                       expert_reason=z["expert_reason"], command=z["command"], speed=z["speed"],
                       agent_brake=z["agent_brake"], episode_keys=list(z["episode_keys"].tolist()))


class AgentMaps:
    """The map source of a learned agent: it acts on the observation (so its route projection and drive state
    follow the episode; its control is discarded) and returns its attention maps (`source="attention"`, YILRatt)
    or the channel-mean |activation| of each stage of its perception (`"activation"`: CIL, CILRS, or any model);
    "auto" picks attention where the model has it. `last_brake` is the agent's brake on the last frame."""

    def __init__(self, agent: Agent, source: str = "auto") -> None:
        if source not in ("auto", "attention", "activation"):
            raise ValueError(f"source={source!r}: expected auto, attention or activation")
        self.agent = agent
        self.source = source
        self.last_brake = math.nan
        self.names: tuple[str, ...] = ()

    def reset(self, seed: int) -> None:
        self.agent.reset(seed=seed)

    def __call__(self, obs: Observation) -> list[np.ndarray]:
        agent = self.agent
        keep = agent.attention
        agent.attention = self.source != "activation"
        try:
            control = agent.act(obs)
        finally:
            agent.attention = keep
        self.last_brake = float(control.brake)
        last = agent.last
        attention = [] if last is None else list(last.attention)
        if self.source == "attention" and not attention:
            raise ValueError(f"{agent.name} has no attention maps: use source='activation' (or another map source)")
        if attention and self.source != "activation":
            self.names = tuple(f"attention layer {i + 1}" for i in range(len(attention)))
            return [np.asarray(a, dtype=np.float32) for a in attention]
        from yawil.explain.attention import activation_maps

        if obs.image is None:
            raise ValueError("AgentMaps needs observations with the camera image")
        maps = activation_maps(agent.model, agent.spec.image(obs.image))
        self.names = tuple(f"activation stage {i + 1}" for i in range(len(maps)))
        return maps


def gather_frames(
    maps_fn: MapsFn,
    episodes: Sequence[Episode],
    *,
    every: int = 10,
    max_frames: int | None = None,
    max_steps: int | None = None,
    layer_names: Sequence[str] | None = None,
    world_factory: Callable[[], World] | None = None,
    verbose: bool = False,
) -> Frames:
    """Drive each episode with the expert (`Expert`, seeded by the episode's world seed, semantic camera on) and
    keep every `every`-th step from the first, at most `max_frames` per episode, for at most `max_steps` steps
    (default: to the goal or the time-out). On each kept step `maps_fn(obs)` gives the maps; a `maps_fn` with a
    `reset(seed)` method is reset at each episode's start with the world seed, and its `last_brake` attribute
    (if any) is kept as the agent's brake. Deterministic for the same episodes and map source."""
    from yawil.expert.driver import Expert
    from yawil.sim import make_world

    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"every={every!r}: expected an integer >= 1")
    for name, limit in (("max_frames", max_frames), ("max_steps", max_steps)):
        if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
            raise ValueError(f"{name}={limit!r}: expected an integer >= 1 or None")
    layers: list[list[np.ndarray]] = []
    ids: list[np.ndarray] = []
    cols: dict[str, list[Any]] = {k: [] for k in ("episode", "step", "expert_brake", "expert_steer", "expert_reason",
                                                   "command", "speed", "agent_brake")}
    keys: list[str] = []
    for e_index, ep in enumerate(episodes):
        started = time.perf_counter()
        scenario = replace(ep.scenario(camera=True), semantic=True)
        world = world_factory() if world_factory is not None else make_world("embedded")
        expert = Expert()
        kept = 0
        try:
            obs = world.reset(scenario, seed=ep.world_seed)
            expert.reset()
            reset = getattr(maps_fn, "reset", None)
            if callable(reset):
                reset(ep.world_seed)
            step = 0
            while True:
                control = expert.act(obs)
                if step % every == 0:
                    if obs.semantic is None or obs.image is None:
                        raise ValueError(f"{ep.key}: the world gave no camera or semantic image")
                    maps = [np.asarray(m, dtype=np.float32) for m in maps_fn(obs)]
                    if not layers:
                        layers = [[] for _ in maps]
                    if len(maps) != len(layers) or any(len(lay) and lay[0].shape != m.shape
                                                       for lay, m in zip(layers, maps, strict=False)):
                        raise ValueError(f"{ep.key} step {step}: the map source gave {[m.shape for m in maps]}, "
                                         f"earlier frames {[lay[0].shape for lay in layers]}")
                    for lay, m in zip(layers, maps, strict=True):
                        lay.append(m)
                    ids.append(np.asarray(obs.semantic, dtype=np.uint8))
                    vals = (e_index, step, control.brake, control.steer, expert.state.reason, int(obs.command),
                            float(obs.speed), float(getattr(maps_fn, "last_brake", math.nan)))
                    for k, v in zip(cols, vals, strict=True):
                        cols[k].append(v)
                    kept += 1
                step += 1
                if obs.done or (max_frames is not None and kept >= max_frames) or \
                        (max_steps is not None and step >= max_steps):
                    break
                obs = world.step(control)
        finally:
            if world_factory is None:
                world.close()
        keys.append(ep.key)
        if verbose:
            print(f"by-class: {ep.key}: {kept} frames of {step} steps in {time.perf_counter() - started:.0f} s",
                  file=sys.stderr, flush=True)
    if not ids:
        raise ValueError("gather_frames: no frames (no episodes given?)")
    names = tuple(layer_names) if layer_names is not None else tuple(getattr(maps_fn, "names", ()) or ())
    if len(names) != len(layers):
        names = tuple(f"layer {i + 1}" for i in range(len(layers)))
    return Frames(
        maps=[np.stack(lay) for lay in layers], ids=np.stack(ids), layer_names=names,
        episode=np.array(cols["episode"], dtype=np.int64), step=np.array(cols["step"], dtype=np.int64),
        expert_brake=np.array(cols["expert_brake"], dtype=np.float64),
        expert_steer=np.array(cols["expert_steer"], dtype=np.float64),
        expert_reason=np.array(cols["expert_reason"], dtype=str), command=np.array(cols["command"], dtype=np.int64),
        speed=np.array(cols["speed"], dtype=np.float64), agent_brake=np.array(cols["agent_brake"], dtype=np.float64),
        episode_keys=keys,
    )  # fmt: skip


# ----- which episodes ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EpisodePlan:
    """Which benchmark episodes to drive and which of their frames to keep. The defaults: NoCrash's dense traffic
    (50 vehicles, 30 pedestrians) on town01's routes 0-7 in the training condition, one seed, route i in weather
    i mod 4 (`cycle`, each weather twice), every 15th frame (1.5 s apart: neighbours at 10 Hz are near copies),
    at most 190 frames per episode: about 1,400 frames, 5 minutes on one thread."""

    suite: str = "nocrash"
    condition: str = "training"
    task: str = "dense"
    routes: str = "0:8"
    seeds: int = 1
    weather_rule: str = "cycle"
    every: int = 15
    max_frames: int | None = 190
    max_steps: int | None = None

    def episodes(self) -> list[Episode]:
        from yawil.bench.suites import episodes

        return episodes(self.suite, [self.condition], [self.task], routes=self.routes, seeds=self.seeds,
                        weather_rule=self.weather_rule)


# ----- output -------------------------------------------------------------------------------------------------


def _fmt(v: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(v) else f"{v:.{digits}f}"


def _cells_table(t: ByClass, cell: Callable[[int, int, int], str]) -> str:
    """A Markdown table: rows layer x situation (with its frame count), columns the classes shown, `cell(l, s, k)`."""
    shown = t.shown_columns()
    head = ["layer", "situation", "frames", *(t.columns[k] for k in shown)]
    lines = ["| " + " | ".join(head) + " |", "| --- | --- | ---: |" + " ---: |" * len(shown)]
    for li, layer in enumerate(t.layers):
        for si, sit in enumerate(t.situations):
            cells = [cell(li, si, k) for k in shown]
            lines.append("| " + " | ".join([layer, sit, str(int(t.frames[si])), *cells]) + " |")
    return "\n".join(lines)


def format_table(t: ByClass) -> str:
    """The lift table as Markdown (what `yawil explain --by-class` prints)."""
    return _cells_table(t, lambda li, si, k: _fmt(float(t.lift[li, si, k])))


def markdown(t: ByClass, meta: Mapping[str, Any] | None = None) -> str:
    """The report: lift, the mean map's lift (prior) and their ratio, the situations, the lift's 95 % intervals,
    then mass and share in percent."""
    out = ["# Attention by class", ""]
    out += [f"- {k}: {v}" for k, v in (meta or {}).items()]
    out += ["", "Lift = (mean attention mass on the class) / (mean pixel share of the class) over the situation's "
            "frames; 1 is what a uniform map gives, '-' a class absent from all those frames. Prior = the lift of "
            "the layer's mean map (where it looks on average) on the same frames; lift / prior > 1: the map follows "
            "the class beyond its habitual place (docs/explain.md, \"Attention by class\").", "",
            "## Lift", "", format_table(t), "",
            "## Prior: lift of the layer's mean map", "", _cells_table(t, lambda li, si, k: _fmt(float(t.prior[li, si, k]))),
            "", "## Lift / prior", "",
            _cells_table(t, lambda li, si, k: _fmt(float(t.lift[li, si, k] / t.prior[li, si, k]))
                         if t.prior[li, si, k] > 0 else "-"), ""]
    flag_names = list(t.flags)
    out += ["## Situations", "", "| situation | frames | episodes | " + " | ".join(f"{f} %" for f in flag_names)
            + " |", "| --- | ---: | ---: |" + " ---: |" * len(flag_names)]
    for si, sit in enumerate(t.situations):
        vals = [_fmt(100.0 * float(t.flags[f][si]), 0) for f in flag_names]
        out.append(f"| {TITLES.get(sit, sit)} | {int(t.frames[si])} | {int(t.episodes[si])} | " + " | ".join(vals)
                   + " |")

    out += ["", "## Spread (fraction of the image a map effectively covers, mean over frames)", "",
            "| layer | " + " | ".join(t.situations) + " |", "| --- |" + " ---: |" * len(t.situations)]
    out += [f"| {layer} | " + " | ".join(_fmt(float(v), 3) for v in t.spread[li]) + " |"
            for li, layer in enumerate(t.layers)]

    def interval(li: int, si: int, k: int) -> str:
        lo, hi = float(t.lift_lo[li, si, k]), float(t.lift_hi[li, si, k])
        return f"{_fmt(lo)}-{_fmt(hi)}" if math.isfinite(lo) else "-"

    out += ["", "## Lift, 95 % interval (episodes resampled)", "", _cells_table(t, interval), "",
            "## Mass % (share %)", "",
            _cells_table(t, lambda li, si, k: f"{_fmt(100 * float(t.mass[li, si, k]), 1)} "
                                              f"({_fmt(100 * float(t.share[si, k]), 1)})")]
    return "\n".join(out) + "\n"


def by_class_figure(t: ByClass, path: Path | None = None) -> Any:
    """Per layer, the lift of each class shown, one bar per situation, on a log scale around 1 (bars start at 1:
    up favours the class, down avoids it); a black tick on each bar marks its prior (the mean map's lift)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = t.shown_columns()
    sits = [si for si in range(len(t.situations)) if t.frames[si] > 0]
    fig, axes = plt.subplots(len(t.layers), 1, figsize=(max(8.0, 0.62 * len(shown) + 2), 2.5 * len(t.layers)),
                             squeeze=False, sharex=True)
    width = 0.85 / max(len(sits), 1)
    x = np.arange(len(shown))
    cmap = matplotlib.colormaps["tab10"]
    floor = 1.0 / 64
    for li, ax in enumerate(axes[:, 0]):
        for j, si in enumerate(sits):
            v = np.array([float(t.lift[li, si, k]) for k in shown])
            ok = np.isfinite(v)
            h = np.clip(v, floor, None)
            xs = x[ok] + (j - (len(sits) - 1) / 2) * width
            ax.bar(xs, h[ok] - 1.0, width, bottom=1.0, color=cmap(si % 10),
                   label=f"{t.situations[si]} ({int(t.frames[si])})")
            pri = np.clip(np.array([float(t.prior[li, si, k]) for k in shown])[ok], floor, None)
            ax.hlines(pri, xs - 0.45 * width, xs + 0.45 * width, colors="k", lw=1.0)
        ax.set_yscale("log", base=2)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_ylabel(f"{t.layers[li]}\nlift", fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[-1, 0].set_xticks(x, [t.columns[k] for k in shown], rotation=40, ha="right", fontsize=8)
    axes[0, 0].legend(fontsize=7, ncol=min(4, len(sits)), loc="upper left")
    axes[0, 0].set_title("attention mass / pixel share by class (1: as a uniform map; ticks: the layer's mean "
                         "map)", fontsize=9)
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig


def write_by_class(t: ByClass, out: Path, meta: Mapping[str, Any] | None = None) -> list[Path]:
    """by_class.json, by_class.md and by_class.png in `out`, each written atomically."""
    import matplotlib.pyplot as plt

    from yawil.fileio import write_atomic, write_json_atomic

    out.mkdir(parents=True, exist_ok=True)
    data = t.to_dict()
    data["meta"] = dict(meta or {})
    write_json_atomic(out / "by_class.json", data)
    write_atomic(out / "by_class.md", markdown(t, meta))
    plt.close(by_class_figure(t, out / "by_class.png"))
    return [out / "by_class.json", out / "by_class.md", out / "by_class.png"]


def run_by_class(
    agent: Agent | None,
    out: Path,
    plan: EpisodePlan = EpisodePlan(),
    *,
    maps_fn: MapsFn | None = None,
    source: str = "auto",
    rules: SituationRules = SituationRules(),
    bootstrap: int = 1000,
    seed: int = 0,
    save_frames: bool = True,
    verbose: bool = False,
) -> ByClass:
    """Drive `plan`'s episodes with the expert, take `agent`'s maps (`AgentMaps(agent, source)`) or `maps_fn`'s on
    the kept frames, and write the table, its Markdown, figure and (`save_frames`) the frames as frames.npz."""
    if maps_fn is None:
        if agent is None:
            raise ValueError("run_by_class needs an agent or a maps_fn")
        maps_fn = AgentMaps(agent, source)
    eps = plan.episodes()
    started = time.perf_counter()
    frames = gather_frames(maps_fn, eps, every=plan.every, max_frames=plan.max_frames, max_steps=plan.max_steps,
                           verbose=verbose)
    table = frames.table(rules, bootstrap=bootstrap, seed=seed)
    meta = {
        "model": None if agent is None else str(getattr(agent, "checkpoint_path", None) or agent.name),
        "maps": f"AgentMaps({maps_fn.source})" if isinstance(maps_fn, AgentMaps)
        else str(getattr(maps_fn, "__qualname__", type(maps_fn).__name__)),
        "episodes": ", ".join(frames.episode_keys), "frames": len(frames), "plan": asdict(plan),
        "rules": asdict(rules), "bootstrap": bootstrap, "seed": seed,
        "drive_s": round(time.perf_counter() - started, 1),
    }
    out.mkdir(parents=True, exist_ok=True)
    if save_frames:
        frames.save(out / "frames.npz")
    write_by_class(table, out, meta)
    return table


# ----- command line (`yawil explain --by-class`) -----------------------------------------------------------------


def add_by_class_arguments(group: Any, flag_group: Any = None) -> None:
    """The options of `yawil explain --by-class` (defaults written out: --help computes nothing). `--by-class`
    itself goes to `flag_group` when given (e.g. the mutually exclusive group of --frames and --episode)."""
    (flag_group if flag_group is not None else group).add_argument("--by-class", action="store_true",
                       help="attention mass per semantic class against its pixel share, by situation, on frames "
                            "of benchmark episodes driven by the expert (writes by_class.json/.md/.png, frames.npz)")
    group.add_argument("--class-task", default="dense", help="--by-class: benchmark task (default dense)")
    group.add_argument("--class-condition", default="training", help="--by-class: condition (default training)")
    group.add_argument("--class-suite", default="nocrash", help="--by-class: suite (default nocrash)")
    group.add_argument("--class-routes", default="0:8", help="--by-class: route ids, 0:8 or 1,4,7 (default 0:8)")
    group.add_argument("--class-seeds", type=int, default=1, help="--by-class: seeds per route (default 1)")
    group.add_argument("--class-every", type=int, default=15, help="--by-class: keep every Nth step (default 15)")
    group.add_argument("--class-max-frames", type=int, default=190,
                       help="--by-class: at most this many frames per episode (default 190)")
    group.add_argument("--class-brake", type=float, default=0.05,
                       help="--by-class: the expert brakes above this brake (default 0.05)")
    group.add_argument("--class-steer", type=float, default=0.15,
                       help="--by-class: turning above this |steer| (or on a LEFT/RIGHT command; default 0.15)")


def run_from_args(agent: Agent, args: argparse.Namespace, out: Path, maps_fn: MapsFn | None = None) -> int:
    """`yawil explain --by-class`: `run_by_class` with the options of `add_by_class_arguments`; `args.maps`
    (auto/attention/activation), when the command has it, picks the agent's map source."""
    plan = EpisodePlan(suite=args.class_suite, condition=args.class_condition, task=args.class_task,
                       routes=args.class_routes, seeds=args.class_seeds, every=args.class_every,
                       max_frames=args.class_max_frames)
    rules = SituationRules(brake=args.class_brake, steer=args.class_steer)
    table = run_by_class(agent, out, plan, maps_fn=maps_fn, source=getattr(args, "maps", "auto"), rules=rules,
                         seed=getattr(args, "seed", 0), verbose=True)
    print(format_table(table))
    print(f"wrote {out / 'by_class.json'}, {out / 'by_class.md'}, {out / 'by_class.png'}, {out / 'frames.npz'}")
    return 0
