"""Are the heat maps faithful? Delete what a map points at and see whether the network's outputs change
(issue 42; docs/explain.md, "Faithfulness").

A heat map is faithful when the outputs depend on the pixels it ranks high more than on other pixels. Pictures
cannot show that; a deletion test measures it (Samek et al. 2017, Petsiuk et al.'s RISE 2018, Hooker et al.'s
ROAR 2019 in the same spirit):

- **open loop** (`deletion_test`, `yawil explain --frames D --faithfulness`): on each frame, for each map (every
  attention layer, or every stage's activation map for a network without attention, and their mean) the top-k %
  most attended pixels are filled (with the image's mean colour, or a blurred copy of the image), against the same
  k % of random pixels (seeded) and of the least attended ones; the absolute change of every output (steer,
  throttle, brake, predicted speed and the aux head's target speed, lead and light readings) is averaged over
  the frames. Faithful maps give top/random > 1; bottom should change the outputs least.
- **closed loop** (`closed_loop_test`, `yawil explain --episode --faithfulness`): at the moments an episode's
  unmasked agent starts braking, the episode is replayed to that step and driven on with the top-k % attended
  region masked in every frame (or the same k % at random): how often does the car still brake?

Maps are at feature resolution; they are brought to the camera image as the figures draw them
(`figures.normalise_map`, then `figures.upsample`) and scaled to sum to one there, so maps of different
resolutions weigh the same in the mean map. The random baseline is by default made of the same blobs as the
maps ("cells": a seeded random map at each layer's resolution, upsampled the same way): random single pixels
would be a different perturbation (a CNN sees scattered holes as noise), and the ratio would then compare two
kinds of damage, not two places. Networks without attention (CIL, CILRS) get the channel mean of |activation|
of each stage of their perception (`activation_map`), the baseline the issue names.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from yawil.explain.attention import activation_maps
from yawil.explain.figures import normalise_map, save_figure, upsample

if TYPE_CHECKING:
    import argparse

    from yawil.agent import Agent
    from yawil.explain.attention import EpisodeVideo

FILLS = ("mean", "blur")  # what a deleted pixel becomes: the image's mean colour, or the image blurred
RANDOMS = ("cells", "pixels")  # the random baseline: blobs of the maps' own grain, or single pixels
SOURCES = ("auto", "attention", "activation")  # which maps: attention where the model has it, else activation
KINDS = ("top", "random", "bottom")
DEFAULT_KS = (5.0, 10.0, 20.0, 40.0)
MEAN_MAP = "mean"  # the name of the combined map (the mean of the layers' maps at image resolution)
HEADLINE = ("steer", "brake", "target_speed", "lead_stop")  # the outputs the printed table shows (where present)
UNITS = {"steer": "[-1, 1]", "throttle": "[0, 1]", "brake": "[0, 1]", "speed": "m/s", "target_speed": "m/s",
         "lead_distance": "m", "lead_speed": "m/s", "light_ahead": "probability", "lead_stop": "probability"}
BOOTSTRAP = 1000  # resamples of the frames for the ratio's 95 % interval

Outputs = Callable[[np.ndarray], dict[str, np.ndarray]]  # images (B, H, W, 3) uint8 -> output name -> (B,)


@dataclass(frozen=True)
class DeletionSettings:
    """How the deletion test masks. `ks`: percentages of the image's pixels; `fill`: FILLS (`blur_sigma` in
    pixels for "blur"); `random`: RANDOMS; `draws`: random masks per frame, map and k (their changes averaged);
    `seed`: every random choice (masks, tie order, frames) derives from it and the frame's position."""

    ks: tuple[float, ...] = DEFAULT_KS
    fill: str = "mean"
    blur_sigma: float = 4.0
    random: str = "cells"
    draws: int = 1
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "ks", tuple(float(k) for k in self.ks))
        if not self.ks or any(not 0.0 <= k <= 100.0 for k in self.ks):
            raise ValueError(f"ks={list(self.ks)}: expected one or more percentages in [0, 100]")
        if self.fill not in FILLS:
            raise ValueError(f"fill={self.fill!r}: expected one of {', '.join(FILLS)}")
        if self.random not in RANDOMS:
            raise ValueError(f"random={self.random!r}: expected one of {', '.join(RANDOMS)}")
        if not self.blur_sigma > 0:
            raise ValueError(f"blur_sigma={self.blur_sigma!r}: expected > 0 pixels")
        if isinstance(self.draws, bool) or not isinstance(self.draws, int) or self.draws < 1:
            raise ValueError(f"draws={self.draws!r}: expected an integer >= 1")


# ----- maps at image resolution -----------------------------------------------------------------------------


def image_map(att: np.ndarray, height: int, width: int) -> np.ndarray:
    """A feature-resolution map brought to the image as the figures draw it (normalised, `figures.upsample`),
    then scaled to sum to one, so that a coarse layer does not outweigh a fine one in the mean map."""
    return normalise_map(upsample(normalise_map(att), height, width))


def image_maps(maps: Mapping[str, np.ndarray], height: int, width: int) -> dict[str, np.ndarray]:
    """Each map at image resolution and, with more than one, their mean (`MEAN_MAP`)."""
    out = {name: image_map(m, height, width) for name, m in maps.items()}
    if len(out) > 1:
        out[MEAN_MAP] = np.mean(np.stack(list(out.values())), axis=0)
    return out


def map_names(maps: Mapping[str, np.ndarray]) -> list[str]:
    """The names `image_maps` gives: the maps' own, then `MEAN_MAP` with more than one."""
    return list(maps) + ([MEAN_MAP] if len(maps) > 1 else [])


def activation_map(model: Any, image: np.ndarray, stage: int = -1) -> np.ndarray:
    """The baseline heat map of a network without attention (CIL, CILRS): the channel-mean |activation| of one
    stage (default the last conv stage), at the image's resolution (H, W), summing to one."""
    img = np.asarray(image)
    return image_map(activation_maps(model, img)[stage], img.shape[0], img.shape[1])


# ----- masks ------------------------------------------------------------------------------------------------


def pixel_order(saliency: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Flat pixel indices, most salient first; equal values in a seeded random order (a flat map has no top, and
    numpy's order would delete the image's top rows first)."""
    s = np.asarray(saliency, dtype=np.float64).ravel()
    return np.lexsort((rng.random(s.size), -s))


def region(order: np.ndarray, k: float, which: str = "top") -> np.ndarray:
    """The boolean flat mask of k % of the pixels: the first of `order` ("top") or the last ("bottom")."""
    n = int(round(k / 100.0 * order.size))
    mask = np.zeros(order.size, dtype=bool)
    if n:
        mask[order[:n] if which == "top" else order[order.size - n:]] = True
    return mask


def random_saliency(maps: Mapping[str, np.ndarray], height: int, width: int, how: str,
                    rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A random map in place of each map (and of the mean map): "cells" a uniform random map at each layer's own
    resolution brought to the image like the real ones (blobs of the same grain), "pixels" per-pixel noise."""
    if how == "pixels":
        return {name: rng.random((height, width)) for name in map_names(maps)}
    return image_maps({name: rng.random(np.shape(m)) for name, m in maps.items()}, height, width)


def gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """The image blurred by a separable Gaussian (edges reflected), uint8: what "blur" puts in deleted pixels."""
    radius = max(1, int(math.ceil(3 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel /= kernel.sum()
    out = np.asarray(image, dtype=np.float64)
    for axis in (0, 1):
        pad = [(0, 0)] * out.ndim
        pad[axis] = (radius, radius)
        padded = np.pad(out, pad, mode="reflect" if out.shape[axis] > radius else "edge")
        n = out.shape[axis]
        out = sum(w * np.take(padded, np.arange(i, i + n), axis=axis) for i, w in enumerate(kernel))  # type: ignore[assignment]
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def filler(image: np.ndarray, fill: str, sigma: float = 4.0) -> np.ndarray:
    """What deleted pixels become (H, W, 3) uint8: the image's mean colour everywhere, or the image blurred."""
    img = np.asarray(image)
    if fill == "blur":
        return gaussian_blur(img, sigma)
    mean = np.round(img.reshape(-1, img.shape[-1]).astype(np.float64).mean(axis=0))
    return np.broadcast_to(mean.astype(np.uint8), img.shape).copy()


def masked(image: np.ndarray, mask: np.ndarray, fill_image: np.ndarray) -> np.ndarray:
    """The image with the pixels of `mask` (flat or (H, W)) replaced by those of `fill_image`."""
    out = np.array(image, copy=True)
    m = np.asarray(mask, dtype=bool).reshape(out.shape[:2])
    out[m] = fill_image[m]
    return out


# ----- the open-loop deletion test --------------------------------------------------------------------------


@dataclass
class DeletionResult:
    """The changes of every frame: `deltas[f, m, k, kind, o]` = |output o with the mask - without| of frame f,
    map `maps[m]`, percentage `settings.ks[k]` and KINDS[kind] (random: the mean over `settings.draws` masks)."""

    settings: DeletionSettings
    maps: list[str]
    outputs: list[str]
    deltas: np.ndarray
    frames: list[dict[str, Any]] = field(default_factory=list)  # what each frame was, and its unmasked outputs
    source: str = "attention"  # attention or activation maps
    model: str = ""

    def summary(self) -> list[dict[str, Any]]:
        """One row per (map, k, output): the mean change of top, random and bottom masks over the frames, the
        ratio top/random (None where random changed nothing) and its 95 % interval (bootstrap over frames)."""
        means = self.deltas.mean(axis=0)  # (M, K, 3, O)
        lo, hi = self._ratio_interval()
        rows = []
        for m, name in enumerate(self.maps):
            for ki, k in enumerate(self.settings.ks):
                for o, out in enumerate(self.outputs):
                    top, rnd, bot = (float(means[m, ki, j, o]) for j in range(3))
                    rows.append({"map": name, "k": k, "output": out, "top": top, "random": rnd, "bottom": bot,
                                 "ratio": _ratio(top, rnd), "ratio_lo": _finite(lo[m, ki, o]),
                                 "ratio_hi": _finite(hi[m, ki, o]), "frames": int(self.deltas.shape[0])})
        return rows

    def _ratio_interval(self) -> tuple[np.ndarray, np.ndarray]:
        """2.5 and 97.5 percentiles of top/random over frames resampled with replacement (seeded)."""
        f = self.deltas.shape[0]
        shape = self.deltas.shape[1:]
        if f < 2:
            nan = np.full((shape[0], shape[1], shape[3]), np.nan)
            return nan, nan
        rng = np.random.default_rng([self.settings.seed, 42])
        counts = rng.multinomial(f, np.full(f, 1.0 / f), size=BOOTSTRAP).astype(np.float64)  # (B, F)
        resampled = (counts @ self.deltas.reshape(f, -1) / f).reshape(BOOTSTRAP, *shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = resampled[:, :, :, 0] / resampled[:, :, :, 1]
        ratio[~np.isfinite(ratio)] = np.nan
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices (random changed nothing) stay NaN
            return np.nanpercentile(ratio, 2.5, axis=0), np.nanpercentile(ratio, 97.5, axis=0)

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": "deletion (open loop)",
            "model": self.model,
            "map_source": self.source,
            "settings": dataclasses.asdict(self.settings),
            "maps": self.maps,
            "outputs": self.outputs,
            "units": {o: UNITS.get(o, "") for o in self.outputs},
            "frames": self.frames,
            "results": self.summary(),
        }


def _ratio(top: float, rnd: float) -> float | None:
    return top / rnd if rnd > 1e-12 else None


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def frame_deletion(image: np.ndarray, maps: Mapping[str, np.ndarray], outputs: Outputs,
                   settings: DeletionSettings, rng: np.random.Generator,
                   batch: int = 64) -> tuple[dict[str, float], np.ndarray]:
    """One frame of the test: its unmasked outputs and the changes (M, K, 3, O) for the maps (feature
    resolution, by name; the mean map is added), in the order of `image_maps` and of the outputs' names.
    `outputs` runs the network on a stack of images (everything but the image held as the frame's)."""
    img = np.asarray(image)
    h, w = img.shape[:2]
    saliency = image_maps(maps, h, w)
    fill_image = filler(img, settings.fill, settings.blur_sigma)
    images = [img]
    rows: list[tuple[int, int, int]] = []  # (map, k, kind) of each masked image
    orders = {name: pixel_order(s, rng) for name, s in saliency.items()}
    random_orders = [{name: pixel_order(s, rng) for name, s in random_saliency(maps, h, w, settings.random, rng).items()}
                     for _ in range(settings.draws)]
    for m, name in enumerate(saliency):
        for ki, k in enumerate(settings.ks):
            images.append(masked(img, region(orders[name], k, "top"), fill_image))
            rows.append((m, ki, 0))
            for draw in random_orders:
                images.append(masked(img, region(draw[name], k, "top"), fill_image))
                rows.append((m, ki, 1))
            images.append(masked(img, region(orders[name], k, "bottom"), fill_image))
            rows.append((m, ki, 2))
    stack = np.stack(images)
    parts = [outputs(stack[i:i + batch]) for i in range(0, len(stack), batch)]
    names = list(parts[0])
    values = np.stack([np.concatenate([np.asarray(p[n], dtype=np.float64).reshape(-1) for p in parts])
                       for n in names], axis=1)  # (1 + rows, O)
    change = np.abs(values[1:] - values[0])
    deltas = np.zeros((len(saliency), len(settings.ks), len(KINDS), len(names)))
    counts = np.zeros(deltas.shape[:3])
    for (m, ki, kind), d in zip(rows, change, strict=True):
        deltas[m, ki, kind] += d
        counts[m, ki, kind] += 1
    return {n: float(values[0, i]) for i, n in enumerate(names)}, deltas / counts[..., None]


@dataclass(frozen=True)
class Frame:
    """One frame of the test: the image, its maps at feature resolution (by name) and how to run the network
    on masked copies of its image; `info` says which frame it is (kept in the JSON)."""

    image: np.ndarray
    maps: Mapping[str, np.ndarray]
    outputs: Outputs
    info: Mapping[str, Any] = field(default_factory=dict)


def deletion_test(frames: Iterable[Frame], settings: DeletionSettings = DeletionSettings(),
                  source: str = "attention", model: str = "",
                  progress: Callable[[int], None] | None = None) -> DeletionResult:
    """The deletion test over frames (an iterable of `Frame`); each frame's random choices come from the seed
    and its position, so a frame's masks do not depend on which other frames were chosen."""
    all_deltas = []
    infos: list[dict[str, Any]] = []
    first: list[str] = []
    out_names: list[str] = []
    for i, fr in enumerate(frames):
        rng = np.random.default_rng([settings.seed, i])
        base, deltas = frame_deletion(fr.image, fr.maps, fr.outputs, settings, rng)
        names = map_names(fr.maps)
        if first and (names != first or list(base) != out_names):
            raise ValueError(f"frame {i}: maps {names} / outputs {list(base)} differ from the first frame's")
        first, out_names = names, list(base)
        all_deltas.append(deltas)
        infos.append({**dict(fr.info), "outputs": base})
        if progress is not None:
            progress(i)
    if not all_deltas:
        raise ValueError("the deletion test needs at least one frame")
    return DeletionResult(settings, first, out_names, np.stack(all_deltas), infos, source, model)


# ----- an agent's network as the test's subject -------------------------------------------------------------


def net_outputs(agent: Agent, out: Any) -> dict[str, np.ndarray]:
    """A forward's outputs by name, in the units the drive reads them (`DriveSettings.decide`): the action heads
    (before any speed control), the predicted speed in m/s and, with an aux head, its target speed (m/s, >= 0),
    lead distance (m) and speed (m/s), the light-ahead and lead-stop probabilities."""
    from yawil.data.schema import LEAD_RANGE

    def mps(v: np.ndarray) -> np.ndarray:
        return np.asarray(agent.norm.speed_inverse(np.asarray(v, dtype=np.float32)), dtype=np.float64)  # type: ignore[arg-type]

    a = np.asarray(out.actions, dtype=np.float64)
    res = {"steer": a[:, 0], "throttle": a[:, 1], "brake": a[:, 2], "speed": mps(out.speed)}
    if out.aux is not None:
        aux = np.asarray(out.aux, dtype=np.float64)
        res.update(target_speed=np.maximum(0.0, mps(aux[:, 0])), lead_distance=np.maximum(0.0, aux[:, 1] * LEAD_RANGE),
                   lead_speed=np.maximum(0.0, mps(aux[:, 2])), light_ahead=_sigmoid(aux[:, 3]))
        if aux.shape[1] > 4:
            res["lead_stop"] = _sigmoid(aux[:, 4])
    return res


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return np.asarray(1.0 / (1.0 + np.exp(-x)), dtype=np.float64)


def map_source(agent: Agent, source: str = "auto") -> str:
    """"attention" or "activation": what `source` (SOURCES) means for this agent's model."""
    if source not in SOURCES:
        raise ValueError(f"maps {source!r}: expected one of {', '.join(SOURCES)}")
    import torch

    layers = getattr(agent.model, "attention", None)  # YILRatt's attention blocks; CIL, CILRS and GuidedIL have none
    has = isinstance(layers, torch.nn.ModuleList) and len(layers) > 0
    if source == "attention" and not has:
        raise ValueError(f"{agent.name} has no attention maps; use activation maps (--maps activation)")
    return "attention" if source == "auto" and has else ("activation" if source == "auto" else source)


def agent_maps(agent: Agent, x: Any, source: str) -> dict[str, np.ndarray]:
    """The maps of one prepared input (`ModelInputs` of one frame), by name: "layer 1".. (attention layers, or
    the stages of `activation_maps`)."""
    if source == "attention":
        maps = [a[0] for a in agent.engine.run(x, attention=True).attention]
    else:
        maps = activation_maps(agent.model, x.image)
    return {f"layer {i + 1}": np.asarray(m, dtype=np.float64) for i, m in enumerate(maps)}


def record_frame(agent: Agent, record: Any, source: str, info: Mapping[str, Any]) -> Frame:
    """A stored dataset frame as the test's subject, with its own speed, guidance and command (as
    `explain_record` runs it)."""
    x = agent.spec.from_record(record)
    key = agent.spec.guidance_key
    guidance = None if key is None else getattr(record, key)
    command = record.command if agent.uses_command else None

    def outputs(images: np.ndarray) -> dict[str, np.ndarray]:
        n = len(images)
        xb = agent.spec.from_frames(list(images), [record.speed] * n, [guidance] * n, [command] * n)
        return net_outputs(agent, agent.engine.run(xb, attention=False))

    return Frame(np.asarray(record.image), agent_maps(agent, x, source), outputs, info)


def pick_records(root: Path, count: int, seed: int, select: str = "all") -> list[tuple[Path, int]]:
    """`count` (file, row) pairs drawn without replacement from every frame of the dataset (or episode file),
    seeded, in file and row order; `select="braking"` draws only frames where the expert brakes."""
    from yawil.data.reader import open_episode
    from yawil.explain.attention import _episode_files

    if select not in ("all", "braking"):
        raise ValueError(f"select {select!r}: expected all or braking")
    files = _episode_files(root)
    pool: list[tuple[int, int]] = []
    for fi, path in enumerate(files):
        with open_episode(path) as ep:
            rows = np.flatnonzero(ep.labels()["brake"] > 0) if select == "braking" else np.arange(len(ep))
        pool += [(fi, int(r)) for r in rows]
    if not pool:
        raise ValueError(f"{root}: no frames{' where the expert brakes' if select == 'braking' else ''}")
    picks = np.random.default_rng(seed).choice(len(pool), size=min(count, len(pool)), replace=False)
    return [(files[pool[i][0]], pool[i][1]) for i in sorted(picks.tolist())]


def dataset_frames(agent: Agent, picks: Sequence[tuple[Path, int]], source: str) -> Iterator[Frame]:
    """The picked frames as `Frame`s, one at a time (the maps of the next are computed when it is reached);
    refuses data of another guidance reference (`check_guidance`)."""
    from yawil.data.reader import open_episode
    from yawil.explain.attention import check_guidance

    checked: set[Path] = set()
    for path, row in picks:
        with open_episode(path) as ep:
            if path not in checked:
                check_guidance(agent, ep.attrs["config"], path)
                checked.add(path)
            rec = ep[row]
            info = {"file": path.name, "episode": ep.episode, "frame": rec.frame, "weather": ep.attrs["weather"],
                    "expert_brake": rec.brake, "speed": rec.speed}
        yield record_frame(agent, rec, source, info)


def deletion_test_dataset(agent: Agent, root: Path, count: int, settings: DeletionSettings = DeletionSettings(),
                          source: str = "auto", select: str = "all", verbose: bool = False) -> DeletionResult:
    """The deletion test of an agent on `count` frames of a dataset (seeded choice, `pick_records`)."""
    import sys

    kind = map_source(agent, source)
    picks = pick_records(root, count, settings.seed, select)

    def tick(i: int) -> None:
        if verbose:
            print(f"\rfaithfulness: frame {i + 1}/{len(picks)}", end="", file=sys.stderr, flush=True)

    result = deletion_test(dataset_frames(agent, picks, kind), settings, kind,
                           str(agent.checkpoint_path or agent.name), tick)
    if verbose:
        print(file=sys.stderr)
    return result


# ----- tables, plot, files ----------------------------------------------------------------------------------


def _num(v: float | None, digits: int = 3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _short(v: float) -> str:
    """A change in at most 5 characters: 3 decimals, or 1e-05 style under 0.001 (an action head that sits at
    zero, such as the brake of a model driven by its target speed, still shows its size)."""
    return f"{v:.3f}" if v == 0 or abs(v) >= 0.001 else f"{v:.0e}".replace("e-0", "e-")


def format_table(result: DeletionResult, outputs: Sequence[str] = HEADLINE) -> str:
    """The printed table: per map and k, for each headline output the mean |change| of top / random / bottom
    masks and the ratio top/random."""
    shown = [o for o in outputs if o in result.outputs] or result.outputs[:3]
    rows = {(r["map"], r["k"], r["output"]): r for r in result.summary()}
    head = f"{'map':<8} {'k%':>4}  " + "  ".join(f"{o[:12] + ' top/rand/bot ratio':>31}" for o in shown)
    lines = [f"deletion test, {result.deltas.shape[0]} frames, {result.source} maps, fill {result.settings.fill}, "
             f"random {result.settings.random}; mean |output change| of top / random / bottom masks, then the "
             "ratio top/random", head]
    for name in result.maps:
        for k in result.settings.ks:
            cells = []
            for o in shown:
                r = rows[(name, k, o)]
                cells.append(f"{_short(r['top']):>5}/{_short(r['random']):>5}/{_short(r['bottom']):>5} "
                             f"{_num(r['ratio'], 2):>5}")
            lines.append(f"{name:<8} {k:>4g}  " + "  ".join(f"{c:>31}" for c in cells))
    return "\n".join(lines)


def markdown_table(result: DeletionResult) -> str:
    """faithfulness.md: the settings, then one table per output (every map and k, with the ratio's interval)."""
    s = result.settings
    lines = [f"# Deletion test ({result.source} maps)", "",
             f"{result.model}: {result.deltas.shape[0]} frames; masks of the top-k % attended pixels, the same k % "
             f"at random ({s.random}, {s.draws} draw(s)) and the least attended, filled with the image's "
             f"{'mean colour' if s.fill == 'mean' else f'blur (sigma {s.blur_sigma:g} px)'}; seed {s.seed}. "
             "Cells: mean |output change| over the frames; ratio top/random with its 95 % bootstrap interval "
             "over frames (faithful maps: > 1).", ""]
    rows = result.summary()
    for o in result.outputs:
        lines += [f"## {o} ({UNITS.get(o, '')})", "", "| map | k % | top | random | bottom | top/random (95 %) |",
                  "|---|---:|---:|---:|---:|---|"]
        for r in (r for r in rows if r["output"] == o):
            ci = f" ({_num(r['ratio_lo'], 2)}-{_num(r['ratio_hi'], 2)})" if r["ratio_lo"] is not None else ""
            cells = " | ".join(f"{v:.4f}" if v == 0 or abs(v) >= 1e-3 else f"{v:.2e}"
                               for v in (r["top"], r["random"], r["bottom"]))
            lines.append(f"| {r['map']} | {r['k']:g} | {cells} | {_num(r['ratio'], 2)}{ci} |")
        lines.append("")
    return "\n".join(lines)


def csv_table(result: DeletionResult) -> str:
    """faithfulness.csv: one row per (map, k, output)."""
    cols = ("map", "k", "output", "top", "random", "bottom", "ratio", "ratio_lo", "ratio_hi", "frames")
    lines = [",".join(cols)]
    for r in result.summary():
        lines.append(",".join("" if r[c] is None else (f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]))
                              for c in cols))
    return "\n".join(lines) + "\n"


def deletion_figure(result: DeletionResult, path: Path | None = None, outputs: Sequence[str] = HEADLINE) -> Any:
    """Mean |output change| against k: one panel per headline output, one colour per map, top solid, random
    dashed, bottom dotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [o for o in outputs if o in result.outputs] or result.outputs[:3]
    means = result.deltas.mean(axis=0)
    fig, axes = plt.subplots(1, len(shown), figsize=(3.6 * len(shown), 3.0), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = {"top": "-", "random": "--", "bottom": ":"}
    ks = result.settings.ks
    for ax, o in zip(axes[0], shown, strict=True):
        oi = result.outputs.index(o)
        for m, name in enumerate(result.maps):
            for j, kind in enumerate(KINDS):
                ax.plot(ks, means[m, :, j, oi], styles[kind], marker="o", ms=3, color=colours[m % len(colours)],
                        label=f"{name} {kind}")
        ax.set_title(f"{o} ({UNITS.get(o, '')})", fontsize=9)
        ax.set_xlabel("masked pixels k (%)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0, 0].set_ylabel("mean |output change|", fontsize=8)
    axes[0, -1].legend(fontsize=6, ncol=1, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.suptitle(f"deletion test: {result.source} maps, {result.deltas.shape[0]} frames "
                 "(top solid, random dashed, bottom dotted)", fontsize=9)
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path)
    return fig


def write_deletion(result: DeletionResult, out: Path) -> list[Path]:
    """faithfulness.json, .md, .csv and .png in `out`, each written atomically."""
    import matplotlib.pyplot as plt

    from yawil.fileio import write_atomic, write_json_atomic

    paths = [out / "faithfulness.json", out / "faithfulness.md", out / "faithfulness.csv", out / "faithfulness.png"]
    write_json_atomic(paths[0], result.to_dict())
    write_atomic(paths[1], markdown_table(result))
    write_atomic(paths[2], csv_table(result))
    plt.close(deletion_figure(result, paths[3]))
    return paths


# ----- the closed-loop test ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClosedLoopSettings:
    """The closed-loop test: from each braking moment (an onset of braking while the car moves at `min_speed`
    m/s or more: a car that holds still is not braking for something it sees; at most `moments`, evenly
    spread) drive `horizon` steps with the top-k % of `layer`'s map (MEAN_MAP or "layer N") masked in every
    frame, and the same k % at random; the car "still brakes" when it brakes within the first `react` steps.
    Masks as `DeletionSettings`."""

    k: float = 20.0
    layer: str = MEAN_MAP
    horizon: int = 20
    react: int = 5
    moments: int = 8
    min_speed: float = 0.5
    fill: str = "mean"
    blur_sigma: float = 4.0
    random: str = "cells"
    seed: int = 0

    def __post_init__(self) -> None:
        DeletionSettings(ks=(self.k,), fill=self.fill, blur_sigma=self.blur_sigma, random=self.random)  # checks
        for name in ("horizon", "react", "moments"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}={v!r}: expected an integer >= 1")
        if not self.min_speed >= 0:
            raise ValueError(f"min_speed={self.min_speed!r}: expected >= 0 m/s")
        if self.react > self.horizon:
            raise ValueError(f"react={self.react} is longer than horizon={self.horizon}")


def braking_moments(brakes: Sequence[float], most: int, speeds: Sequence[float] | None = None,
                    min_speed: float = 0.0) -> list[int]:
    """Steps where the agent starts braking (brake > 0 after a step without, or at step 0) at a speed of at least
    `min_speed` (`speeds`: m/s at each step), at most `most`, spread evenly over the episode when there are more."""
    onsets = [t for t, b in enumerate(brakes) if b > 0 and (t == 0 or brakes[t - 1] <= 0)
              and (speeds is None or speeds[t] >= min_speed)]
    if len(onsets) <= most:
        return onsets
    return [onsets[int(i)] for i in np.linspace(0, len(onsets) - 1, most).round().astype(int)]


def _masked_observation(agent: Agent, obs: Any, kind: str, settings: ClosedLoopSettings, source: str,
                        rng: np.random.Generator) -> Any:
    """The observation with k % of its image masked: the top of the chosen map of the unmasked image (computed
    on a copy of the agent's episode state, so the agent steps once per frame), or random cells / pixels."""
    img = np.asarray(obs.image)
    h, w = img.shape[:2]
    saved = copy.deepcopy(agent.states[0])
    x, _, _ = agent.model_inputs(obs)
    agent.states[0] = saved
    maps = agent_maps(agent, x, source)
    chosen = image_maps(maps, h, w) if kind == "top" else random_saliency(maps, h, w, settings.random, rng)
    if settings.layer not in chosen:
        raise ValueError(f"map {settings.layer!r}: this model's maps are {', '.join(chosen)}")
    order = pixel_order(chosen[settings.layer], rng)
    image = masked(img, region(order, settings.k, "top"), filler(img, settings.fill, settings.blur_sigma))
    return dataclasses.replace(obs, image=image)


def closed_loop_test(agent: Agent, episode: EpisodeVideo, settings: ClosedLoopSettings = ClosedLoopSettings(),
                     source: str = "auto", verbose: bool = False) -> dict[str, Any]:
    """Drive one episode unmasked, find its braking moments, and from each drive on with the attended region
    masked (and with a random one): the JSON-ready record, its `summary` the share of moments the car still
    brakes under each mask. A moment is replayed by resetting the world with the episode's seed and repeating
    the recorded controls (the world is deterministic given both), the agent's episode state restored from a
    copy taken at that step; a replay that does not reach the recorded pose is reported, not counted."""
    import sys

    from yawil.explain.attention import episode_scenario
    from yawil.sim import DT, make_world

    kind_of_maps = map_source(agent, source)
    scenario = episode_scenario(episode)
    world = make_world("embedded")
    controls, poses, states, speeds = [], [], [], []
    try:
        obs = world.reset(scenario, seed=episode.seed)
        names = map_names(agent_maps(agent, agent.model_inputs(obs)[0], kind_of_maps))
        if settings.layer not in names:  # refused before the drive, not after it
            raise ValueError(f"map {settings.layer!r}: this model's maps are {', '.join(names)}")
        agent.reset()
        for _ in range(episode.steps):
            states.append(copy.deepcopy(agent.states[0]))
            poses.append((obs.pose.x, obs.pose.y, obs.pose.yaw))
            speeds.append(float(obs.speed))
            control = agent.act(obs)
            controls.append(control)
            obs = world.step(control)
            if obs.done or any(e.kind.value == "collision" for e in obs.events):
                break
        moments = braking_moments([c.brake for c in controls], settings.moments, speeds, settings.min_speed)
        records = []
        for mi, t in enumerate(moments):
            if verbose:
                print(f"closed loop: {len(controls)} steps driven; braking moment {mi + 1}/{len(moments)} "
                      f"(step {t})", file=sys.stderr, flush=True)
            rec: dict[str, Any] = {"step": t, "time": round(t * DT, 1), "speed": speeds[t],
                                   "unmasked_brake_steps": int(sum(c.brake > 0 for c in controls[t:t + settings.horizon]))}
            for kind in ("top", "random"):
                rec[kind] = _drive_masked(agent, world, scenario, episode.seed, controls[:t], poses[t], states[t],
                                          kind, settings, kind_of_maps, np.random.default_rng([settings.seed, mi]))
            records.append(rec)
    finally:
        world.close()
    return {"test": "closed loop", "model": str(agent.checkpoint_path or agent.name), "map_source": kind_of_maps,
            "episode": dataclasses.asdict(episode), "settings": dataclasses.asdict(settings), "steps": len(controls),
            "moments": records, "summary": closed_loop_summary(records)}


def _drive_masked(agent: Agent, world: Any, scenario: Any, seed: int, replay: Sequence[Any],
                  pose: tuple[float, float, float], state: Any, kind: str, settings: ClosedLoopSettings,
                  source: str, rng: np.random.Generator) -> dict[str, Any]:
    """Replay to a braking moment, then drive `horizon` steps with the masked images."""
    obs = world.reset(scenario, seed=seed)
    for c in replay:
        obs = world.step(c)
    got = (obs.pose.x, obs.pose.y, obs.pose.yaw)
    if not np.allclose(got, pose, atol=1e-6):
        return {"diverged": True, "pose": list(got), "expected": list(pose)}
    agent.states[0] = copy.deepcopy(state)
    agent.outputs[0] = None
    brakes: list[float] = []
    collided = False
    for _ in range(settings.horizon):
        control = agent.act(_masked_observation(agent, obs, kind, settings, source, rng))
        brakes.append(control.brake)
        obs = world.step(control)
        if any(e.kind.value == "collision" for e in obs.events):
            collided = True
            break
        if obs.done:
            break
    return {"diverged": False, "still_brakes": any(b > 0 for b in brakes[:settings.react]),
            "brake_steps": int(sum(b > 0 for b in brakes)), "end_speed": float(obs.speed), "collision": collided}


def closed_loop_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per mask: moments counted (not diverged), how many still braked, their share, collisions."""
    out: dict[str, Any] = {}
    for kind in ("top", "random"):
        ok = [r[kind] for r in records if not r[kind]["diverged"]]
        n = len(ok)
        still = sum(bool(r["still_brakes"]) for r in ok)
        out[kind] = {"moments": n, "still_brakes": still, "share": still / n if n else None,
                     "collisions": sum(bool(r["collision"]) for r in ok),
                     "diverged": sum(bool(r[kind]["diverged"]) for r in records)}
    return out


def format_closed_loop(record: Mapping[str, Any]) -> str:
    """The printed summary of the closed-loop test."""
    s = record["settings"]
    lines = [f"closed-loop test: {len(record['moments'])} braking moments in {record['steps']} steps; "
             f"top-{s['k']:g} % of {record['map_source']} {s['layer']} masked for {s['horizon']} steps "
             f"(fill {s['fill']}); still brakes = brakes within {s['react']} steps",
             f"{'mask':<8} {'moments':>7} {'still brakes':>12} {'share':>6} {'collisions':>10} {'diverged':>8}"]
    for kind, v in record["summary"].items():
        lines.append(f"{kind:<8} {v['moments']:>7} {v['still_brakes']:>12} {_num(v['share'], 2):>6} "
                     f"{v['collisions']:>10} {v['diverged']:>8}")
    return "\n".join(lines)


def write_closed_loop(record: Mapping[str, Any], out: Path) -> list[Path]:
    """faithfulness_closed.json and .md in `out`, atomically."""
    from yawil.fileio import write_atomic, write_json_atomic

    paths = [out / "faithfulness_closed.json", out / "faithfulness_closed.md"]
    write_json_atomic(paths[0], dict(record))
    write_atomic(paths[1], "# Closed-loop deletion test\n\n```\n" + format_closed_loop(record) + "\n```\n")
    return paths


# ----- `yawil explain --faithfulness` (its options: yawil.explain.cli) --------------------------------------


def run_from_args(agent: Agent, args: argparse.Namespace, out: Path) -> int:
    """`yawil explain --faithfulness`: the open-loop test with --frames, the closed-loop one with --episode."""
    try:
        ks = tuple(float(v) for v in str(args.ks).split(",") if v.strip())
    except ValueError:
        raise ValueError(f"--ks {args.ks!r}: expected percentages separated by commas, e.g. 5,10,20,40") from None
    if args.frames:
        settings = DeletionSettings(ks=ks, fill=args.fill, random=args.random, seed=args.seed)
        result = deletion_test_dataset(agent, Path(args.frames), args.count, settings, args.maps, args.select,
                                       verbose=True)
        paths = write_deletion(result, out)
        print(format_table(result))
        print(f"wrote {', '.join(str(p) for p in paths)}")
        return 0
    from yawil.explain.attention import EpisodeVideo

    episode = EpisodeVideo(route=args.route, condition=args.condition, town=args.town, weather=args.weather,
                           vehicles=args.vehicles, pedestrians=args.pedestrians, seed=args.seed, steps=args.steps)
    layer = f"layer {args.mask_layer}" if str(args.mask_layer).isdigit() else str(args.mask_layer)
    closed = ClosedLoopSettings(k=args.mask_k, layer=layer, horizon=args.horizon, moments=args.moments,
                                react=min(5, args.horizon), fill=args.fill, random=args.random, seed=args.seed)
    record = closed_loop_test(agent, episode, closed, args.maps, verbose=True)
    paths = write_closed_loop(record, out)
    print(format_closed_loop(record))
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0
