"""Failures explained (issue 42; docs/explain.md, "Failures explained"): for every failed episode of a benchmark
results folder, the heat maps of its last seconds and what they were on when the net should have braked.

A record says that an episode failed, not why. The paper reads its failures off heat maps ("erroneous
perception"); this module makes that reading repeatable:

- `failed_records`, `load_agent_of`: the failed records of a results folder, and the agent that drove them
  rebuilt from its run.json (checkpoint or zoo name, drive options, engine and precision), or `--checkpoint`'s.
- `redrive`: drives the record's episode again exactly as `yawil bench` drives it (`runner.drive_episode`, the
  same judge), with the semantic camera on, the agent's maps taken on every frame (`by_class.AgentMaps`:
  attention, or channel-mean activation for models without it) and the expert shadowing every frame without
  driving (as `yawil trace` does: what it would decide in the agent's state). It keeps the last `seconds` whole
  (camera, class ids, maps) and every step's controls and target speeds.
- `agreement`: whether the re-drive ended as the record says. A record can depend on the episodes its worker
  drove before it (a known open issue); a re-drive that ends otherwise is said so and explained as it ended.
- `explain_failure`: the numbers of one failure: each layer's lift on vehicle, pedestrian, lights and passable
  road (`by_class.by_class_table`, the same computation) in the last second and on the frames where the expert
  brakes, and what the agent did on those frames (`braking_summary`).
- `write_failures`: failures.json, failures.md, one strip figure (and the kept frames, .npz) per failure.

Why the agent drives and the expert only shadows: the failure is the agent's, so the states must be its own;
the expert's decision on them says when braking was due (by_class, which measures the maps in general, lets the
expert drive instead, because there the situation must come from a decision that shaped the states).
"""

from __future__ import annotations

import math
import re
import sys
import time
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from yawil.explain.by_class import BRAKE_REASONS, SituationRules, by_class_table, label_situations
from yawil.sim.types import DT

if TYPE_CHECKING:
    import argparse

    from yawil.agent import Agent
    from yawil.bench.suites import Episode
    from yawil.explain.by_class import AgentMaps
    from yawil.sim.types import Control, Observation, Scenario, World

FORMAT = "yawil-failures/1"
AGREE_STEPS = 10  # the re-drive ends within 1 s of the record's end: "about the same step count"
COLUMNS = ("vehicle", "pedestrian", "lights", "passable")  # the classes (and groups of by_class) reported
LAST_S = 1.0  # the lifts are taken over this last part of the kept window
SERIES = ("step", "time", "speed", "command", "steer", "throttle", "brake", "target_speed", "head_target_speed",
          "lead_stop", "expert_steer", "expert_brake", "expert_target_speed", "expert_reason", "expert_agent")


# ----- which failures, which agent ---------------------------------------------------------------------------


def run_info(results: Path) -> dict[str, Any]:
    """The folder's run.json (who drove, with which options); ValueError in one line when it has none."""
    import json

    from yawil.bench.records import RUN_FILE

    path = Path(results) / RUN_FILE
    if not path.is_file():
        raise ValueError(f"{results}: no {RUN_FILE} (expected a results folder written by `yawil bench`)")
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(info, dict) or not isinstance(info.get("agent"), str):
        raise ValueError(f"{path}: no 'agent' (expected the run description `yawil bench` writes)")
    return info


def failed_records(results: Path, reasons: Sequence[str] = (), max_failures: int | None = None
                   ) -> tuple[list[dict[str, Any]], int]:
    """The failed records (success false) in the file's order, only those whose reason is in `reasons` when
    given, at most `max_failures`; and how many failed in all."""
    from yawil.bench.records import iter_results

    failed = [r for r in iter_results(results) if not r["success"]]
    chosen = [r for r in failed if not reasons or str(r.get("reason")) in reasons]
    return chosen[:max_failures] if max_failures is not None else chosen, len(failed)


@dataclass(frozen=True)
class AgentOf:
    """The agent rebuilt for a results folder, and what differs from the one that drove it (`notes`)."""

    agent: Agent
    name: str  # what drove: the checkpoint, zoo:NAME or path
    engine: str  # engine-precision it runs on here
    notes: tuple[str, ...] = ()


def load_agent_of(info: Mapping[str, Any], checkpoint: str | None = None, where: str = "run.json") -> AgentOf:
    """The agent of a run.json (`info`) with its drive options (speed control, stop release and creep, noise) and,
    where the running machine has it, its engine and precision; `checkpoint` replaces the checkpoint (a moved file).
    ValueError in one line when it cannot be loaded."""
    from yawil.agent import Agent
    from yawil.bench.runner import EXPERT, AgentSpec
    from yawil.policy.drive import DriveSettings

    opts = dict(info.get("agent_options") or {})
    name = checkpoint or str(info["agent"])
    if name == EXPERT:
        raise ValueError(f"{where}: the agent is the expert: it has no heat maps to explain (give --checkpoint to "
                         "explain a learned agent's drive of the same episodes)")
    kw = {f.name: opts[f.name] for f in fields(DriveSettings) if f.name != "post" and f.name in opts}
    label = str(opts.get("engine", "auto"))
    engine, _, precision = label.partition("-")
    if precision == "int8":  # an engine of its own (yawil.policy.quantize); its float parts run as the machine can
        engine, precision = label, ""
    spec = AgentSpec(name, engine=engine or "auto", **kw)
    try:
        path = spec.checkpoint
    except (ValueError, OSError) as err:
        raise ValueError(f"{where}: agent {name!r} cannot be loaded ({err}); give --checkpoint") from None
    if not path.is_file():
        raise ValueError(f"{where}: agent {name!r}: no such checkpoint file here; give --checkpoint")
    notes = []
    sha = info.get("agent_sha256")
    if checkpoint is not None and sha and spec.content_hash() != sha:
        notes.append(f"--checkpoint {checkpoint} is not the checkpoint that drove these results (sha256 "
                     f"{str(sha)[:12]}...): the re-drives are its own")
    try:
        try:
            agent = Agent.from_checkpoint(path, seed=0, engine=spec.engine, precision=precision or "auto",
                                          attention=True, **spec.drive())
        except ValueError as err:  # the record's precision (e.g. CUDA's fp16) does not run here
            if not precision:
                raise
            agent = Agent.from_checkpoint(path, seed=0, engine="auto", attention=True, **spec.drive())
            notes.append(f"the record's engine {label} does not run here ({err}); driven on {agent.engine.label}")
    except Exception as err:  # a corrupt file, another program's checkpoint, an option its model cannot take
        raise ValueError(f"{where}: agent {name!r} cannot be loaded ({type(err).__name__}: {err})") from None
    agent.checkpoint_path = name
    return AgentOf(agent, name, agent.engine.label, tuple(notes))


# ----- the re-drive ------------------------------------------------------------------------------------------


class _SemanticWorld:
    """A world whose every scenario has the semantic camera on (and the camera), nothing else changed."""

    def __init__(self, world: World) -> None:
        self.world = world

    def reset(self, scenario: Scenario, seed: int) -> Observation:
        return self.world.reset(replace(scenario, camera=True, semantic=True), seed=seed)

    def step(self, control: Control) -> Observation:
        return self.world.step(control)

    def close(self) -> None:
        self.world.close()


@dataclass
class Kept:
    """What a re-drive kept: every step's numbers (`series`, names `SERIES`) and the last `window` frames whole."""

    layer_names: tuple[str, ...]
    series: dict[str, list[Any]]
    steps: list[int]  # the kept frames' steps
    images: list[np.ndarray]  # (88, 200, 3) uint8 each
    ids: list[np.ndarray]  # (88, 200) uint8 class ids
    maps: list[list[np.ndarray]]  # per kept frame, one (h, w) map per layer


class _Shadowed:
    """Drives with the agent through its map source, the expert shadowing every frame; keeps `Kept`."""

    def __init__(self, maps_fn: AgentMaps, window: int, name: str) -> None:
        from yawil.expert import Expert

        self.maps_fn, self.window, self.name = maps_fn, window, name
        self.expert = Expert()
        self.frames: deque[tuple[int, np.ndarray, np.ndarray, list[np.ndarray]]] = deque(maxlen=window)
        self.series: dict[str, list[Any]] = {k: [] for k in SERIES}

    def reset(self, seed: int | None = None) -> None:
        self.maps_fn.reset(0 if seed is None else seed)
        self.expert.reset()
        self.frames.clear()
        self.series = {k: [] for k in SERIES}

    def act(self, obs: Observation) -> Control:
        shadow = self.expert.act(obs)
        st = self.expert.state
        maps = [np.asarray(m, dtype=np.float32) for m in self.maps_fn(obs)]
        last = self.maps_fn.agent.last
        assert last is not None
        control = last.control
        if obs.image is None or obs.semantic is None:
            raise ValueError("the re-drive's world gave no camera or semantic image")
        step = len(self.series["step"])
        self.frames.append((step, np.asarray(obs.image, dtype=np.uint8), np.asarray(obs.semantic, dtype=np.uint8),
                            maps))
        hazard = st.hazard
        for k, v in zip(SERIES, (
            step, round(float(obs.time), 2), float(obs.speed), int(obs.command), control.steer, control.throttle,
            control.brake, _num(last.target_speed), _num(last.head_target_speed), _num(last.lead_stop), shadow.steer,
            shadow.brake, float(st.target_speed), st.reason, None if hazard is None else hazard.agent_id,
        ), strict=True):
            self.series[k].append(v)
        return control

    def kept(self) -> Kept:
        names = tuple(self.maps_fn.names) or tuple(f"layer {i + 1}" for i in range(len(self.frames[0][3])))
        return Kept(names, self.series, [f[0] for f in self.frames], [f[1] for f in self.frames],
                    [f[2] for f in self.frames], [f[3] for f in self.frames])


def _num(v: float | None) -> float:
    return math.nan if v is None else float(v)


def redrive(agent: Agent, episode: Episode, seconds: float = 3.0, source: str = "auto",
            world: World | None = None) -> tuple[dict[str, Any], Kept]:
    """Drive `episode` as `yawil bench` drives it (`runner.drive_episode`), the semantic camera on, keeping the last
    `seconds` (`Kept`); returns the re-drive's record and what was kept."""
    from yawil.bench.runner import drive_episode
    from yawil.explain.by_class import AgentMaps
    from yawil.sim import make_world

    window = max(1, round(seconds / DT))
    shadowed = _Shadowed(AgentMaps(agent, source), window, str(agent.checkpoint_path or agent.name))
    inner = world if world is not None else make_world("embedded")
    try:
        record = drive_episode(shadowed, episode, camera=True, world=_SemanticWorld(inner))  # type: ignore[arg-type]
    finally:
        if world is None:
            inner.close()
    if not shadowed.frames:
        raise ValueError(f"{episode.key}: the re-drive ended before the agent's first step")
    return record, shadowed.kept()


def first_collision(rec: Mapping[str, Any]) -> dict[str, Any] | None:
    cols = rec.get("collisions") or []
    return dict(cols[0]) if cols else None


def agreement(record: Mapping[str, Any], redriven: Mapping[str, Any], steps: int = AGREE_STEPS) -> tuple[bool, str]:
    """Whether the re-drive ended as the record says: the same end (success or reason), within `steps` steps
    (and, for a collision, with the same agent); and a sentence saying how it ended against the record."""
    end = _end(redriven)
    want = _end(record)
    d = int(redriven.get("steps", 0)) - int(record.get("steps", 0))
    a, b = first_collision(record), first_collision(redriven)
    same_other = a is None or b is None or a.get("id") == b.get("id")
    ok = end == want and abs(d) <= steps and same_other
    text = f"re-driven: {end} at {float(redriven.get('time_s', 0.0)):.1f} s ({int(redriven.get('steps', 0))} steps)"
    if b is not None:
        text += f", {_collision_text(b)}"
    if ok:
        return True, text + (": as the record" if d == 0 else f": as the record ({d:+d} steps)")
    return False, (text + f"; the record: {want} at {float(record.get('time_s', 0.0)):.1f} s "
                   f"({int(record.get('steps', 0))} steps)" + ("" if a is None else f", {_collision_text(a)}")
                   + ". The re-drive differs from the record (a record may depend on the episodes its worker drove "
                   "before it): what follows explains the re-drive")


def _end(rec: Mapping[str, Any]) -> str:
    return "success" if rec.get("success") else str(rec.get("reason") or "unfinished")


def _collision_text(c: Mapping[str, Any]) -> str:
    return f"hit {c.get('type')} {c.get('id')}" + (" (rear-end)" if c.get("rear_end") else "")


# ----- the numbers ---------------------------------------------------------------------------------------------


def should_brake(expert_brake: Sequence[float] | np.ndarray, expert_reason: Sequence[str] | np.ndarray,
                 rules: SituationRules = SituationRules()) -> np.ndarray:
    """(F,) bool: the expert brakes (> rules.brake) for a vehicle, a pedestrian or a light (by_class's braking
    situations): the frames where the net should have braked."""
    b = np.asarray(expert_brake, dtype=np.float64)
    r = np.asarray(expert_reason).astype(str)
    return (b > rules.brake) & np.isin(r, list(BRAKE_REASONS))


def braking_summary(series: Mapping[str, Sequence[Any]], start: int, rules: SituationRules = SituationRules(),
                    hit: int | None = None) -> dict[str, Any]:
    """What the agent did where the expert would have braked, over the steps from `start` to the end: how many
    such frames, from when (seconds before the last frame), for what (reasons; whether for the agent `hit`), the
    share of them on which the agent braked (brake > 0) and the target speeds (mean; and at the first one). The
    end is one step after the last frame (the step whose outcome ended the episode)."""
    n = len(series["step"])
    sl = slice(start, n)
    eb = np.asarray(series["expert_brake"][sl], dtype=np.float64)
    reasons = np.asarray(series["expert_reason"][sl]).astype(str)
    should = should_brake(eb, reasons, rules)
    brake = np.asarray(series["brake"][sl], dtype=np.float64)
    times = np.asarray(series["time"][sl], dtype=np.float64)
    target = np.asarray(series["target_speed"][sl], dtype=np.float64)
    e_target = np.asarray(series["expert_target_speed"][sl], dtype=np.float64)
    speed = np.asarray(series["speed"][sl], dtype=np.float64)
    agents = list(series["expert_agent"][sl])
    lead_stop = np.asarray(series["lead_stop"][sl], dtype=np.float64)
    end_t = float(times[-1]) + DT if len(times) else 0.0

    def at(i: int) -> dict[str, Any]:
        return {"speed": _r(float(speed[i])), "agent_target": _r(float(target[i])),
                "expert_target": _r(float(e_target[i])), "agent_brake": _r(float(brake[i])),
                "agent_lead_stop": _r(float(lead_stop[i])), "expert_reason": str(reasons[i])}

    out: dict[str, Any] = {
        "frames": int(len(eb)), "expert_brakes": int(should.sum()),
        "agent_brakes": int((brake > 0).sum()),
        "first_agent_brake_s": _before(times, brake > 0, end_t),
        "min_speed": _r(float(speed.min())) if len(speed) else None,
        "at_last": at(len(eb) - 1) if len(eb) else None,
    }
    if not should.any():
        return out
    i = int(np.argmax(should))
    why = Counter(reasons[should].tolist())
    out.update({
        "expert_from_s": round(end_t - float(times[i]), 2),
        "expert_reasons": dict(why.most_common()),
        "agent_brakes_when_expert_brakes": int((brake[should] > 0).sum()),
        "agent_brake_share": round(float((brake[should] > 0).mean()), 3),
        "agent_target_mean": _r(float(np.nanmean(target[should])) if np.isfinite(target[should]).any() else math.nan),
        "expert_target_mean": _r(float(e_target[should].mean())),
        "at_first": at(i),
    })  # fmt: skip
    if hit is not None:
        out["expert_brakes_for_hit"] = int(sum(1 for a, s in zip(agents, should, strict=True) if s and a == hit))
    return out


def _before(times: np.ndarray, mask: np.ndarray, end_t: float) -> float | None:
    return round(end_t - float(times[int(np.argmax(mask))]), 2) if mask.any() else None


def _r(v: float, digits: int = 2) -> float | None:
    return round(v, digits) if math.isfinite(v) else None


def class_rows(kept: Kept, rules: SituationRules = SituationRules(), last_s: float = LAST_S
               ) -> list[dict[str, Any]]:
    """Each layer's lift and mass on `COLUMNS` over the kept frames of the last `last_s` seconds, and over the kept
    frames where the expert would have braked (`should_brake`): rows of by_class's table ("all" of those
    frames), the same computation as `yawil explain --by-class`."""
    n = len(kept.steps)
    ser = kept.series
    first = kept.steps[0]
    pick = {k: np.asarray(ser[k][first:first + n]) for k in ("expert_brake", "expert_reason", "command",
                                                              "expert_steer")}
    labels = label_situations(pick["expert_brake"], pick["expert_reason"], pick["command"], pick["expert_steer"],
                              rules)
    should = should_brake(pick["expert_brake"], pick["expert_reason"], rules)
    last = np.zeros(n, dtype=bool)
    last[max(0, n - max(1, round(last_s / DT))):] = True
    rows = []
    for name, sel in ((f"last {last_s:g} s", last), ("expert brakes", should)):
        if not sel.any():
            continue
        idx = np.flatnonzero(sel)
        maps = [np.stack([kept.maps[i][li] for i in idx]) for li in range(len(kept.layer_names))]
        ids = np.stack([kept.ids[i] for i in idx])
        t = by_class_table(maps, ids, labels[idx], layer_names=kept.layer_names, bootstrap=0)
        cols = [t.columns.index(c) for c in COLUMNS]
        for li, layer in enumerate(t.layers):
            rows.append({
                "frames": name, "count": int(len(idx)), "layer": layer,
                "lift": {c: _r(float(t.lift[li, 0, k])) for c, k in zip(COLUMNS, cols, strict=True)},
                "mass": {c: _r(float(t.mass[li, 0, k]), 4) for c, k in zip(COLUMNS, cols, strict=True)},
                "share": {c: _r(float(t.share[0, k]), 4) for c, k in zip(COLUMNS, cols, strict=True)},
            })  # fmt: skip
    return rows


# ----- one failure ----------------------------------------------------------------------------------------------


@dataclass
class Failure:
    """One failed record explained: its re-drive, the numbers, the kept frames."""

    key: str
    record: dict[str, Any]  # the judged fields of the record (reason, steps, time_s, collisions)
    redriven: dict[str, Any]  # the same of the re-drive
    agrees: bool
    agreement: str
    kept: Kept
    classes: list[dict[str, Any]]
    braking: dict[str, Any]
    drive_s: float
    files: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        first = self.kept.steps[0]
        window = {k: [_json(v) for v in self.kept.series[k][first:]] for k in SERIES}
        return {"key": self.key, "record": self.record, "redriven": self.redriven, "agrees": self.agrees,
                "agreement": self.agreement, "layers": list(self.kept.layer_names),
                "window": {"seconds": round(len(self.kept.steps) * DT, 2), "first_step": first,
                           "last_step": self.kept.steps[-1], **window},
                "classes": self.classes, "braking": self.braking, "drive_s": self.drive_s, "files": self.files}


def _json(v: Any) -> Any:
    if isinstance(v, float):
        return round(v, 4) if math.isfinite(v) else None
    return v


JUDGED = ("success", "reason", "time_s", "steps", "collisions", "km_driven")


def explain_failure(agent: Agent, rec: Mapping[str, Any], seconds: float = 3.0, source: str = "auto",
                    rules: SituationRules = SituationRules(), world: World | None = None) -> Failure:
    """Re-drive one failed record's episode (`redrive`) and compute its numbers."""
    from yawil.bench.records import episode_key
    from yawil.bench.trace import find_episode

    key = episode_key(rec)
    ep = find_episode(key, str(rec.get("suite") or "all"))
    started = time.perf_counter()
    redriven, kept = redrive(agent, ep, seconds, source, world)
    agrees, text = agreement(rec, redriven)
    hit = first_collision(redriven)
    braking = braking_summary(kept.series, kept.steps[0], rules, None if hit is None else hit.get("id"))
    return Failure(key, {k: rec.get(k) for k in JUDGED}, {k: redriven.get(k) for k in JUDGED}, agrees, text, kept,
                   class_rows(kept, rules), braking, round(time.perf_counter() - started, 1))


# ----- output --------------------------------------------------------------------------------------------------


def slug(key: str, index: int) -> str:
    return f"failure_{index:02d}_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", key)


def strip_figure(f: Failure, count: int = 6, alpha: float = 0.5, path: Path | None = None) -> Any:
    """`count` frames spread over the kept seconds, one column each: the camera, the class ids, each layer's map
    blended over the camera (`figures.overlay`); under them speed and target speeds (agent, expert) and both
    brakes over the window."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from yawil.explain.figures import overlay
    from yawil.sim.semantic import colorize

    kept = f.kept
    n = len(kept.steps)
    cols = sorted(set(np.linspace(0, n - 1, min(count, n)).round().astype(int).tolist()))
    names = ["camera", "classes", *kept.layer_names]
    fig = plt.figure(figsize=(2.1 * len(cols) + 0.6, 1.0 * len(names) + 2.2))
    grid = fig.add_gridspec(len(names) + 1, len(cols), height_ratios=[1.0] * len(names) + [2.0])
    ser = kept.series
    end_t = float(ser["time"][kept.steps[-1]]) + DT  # the end: the step after the last frame
    for c, i in enumerate(cols):
        s = kept.steps[i]
        pics = [kept.images[i], colorize(kept.ids[i])] + [overlay(kept.images[i], m, alpha) for m in kept.maps[i]]
        for r, pic in enumerate(pics):
            ax = fig.add_subplot(grid[r, c])
            ax.imshow(pic)
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(names[r].replace("attention ", "").replace("activation ", "act. "), fontsize=7)
            if r == 0:
                ax.set_title(f"{float(ser['time'][s]) - end_t:+.1f} s  {3.6 * float(ser['speed'][s]):.0f} km/h\n"
                             f"b {float(ser['brake'][s]):.2f}  expert b {float(ser['expert_brake'][s]):.2f}",
                             fontsize=7)
    ax = fig.add_subplot(grid[len(names), :])
    first = kept.steps[0]
    t = np.asarray(ser["time"][first:], dtype=np.float64) - end_t
    for k, label, style in (("speed", "speed", "k-"), ("target_speed", "agent target", "b-"),
                            ("expert_target_speed", "expert target", "g--")):
        v = np.asarray(ser[k][first:], dtype=np.float64)
        if np.isfinite(v).any():
            ax.plot(t, v, style, lw=1.2, label=label)
    ax.set_ylabel("m/s", fontsize=7)
    ax.set_xlabel("s before the end", fontsize=7)
    ax.tick_params(labelsize=7)
    ax2 = ax.twinx()
    ax2.fill_between(t, 0, np.asarray(ser["brake"][first:], dtype=np.float64), color="b", alpha=0.2, step="mid",
                     label="agent brake")
    ax2.plot(t, np.asarray(ser["expert_brake"][first:], dtype=np.float64), "g:", lw=1.2, label="expert brake")
    ax2.set_ylim(0, 1.05)
    ax2.set_ylabel("brake", fontsize=7)
    ax2.tick_params(labelsize=7)
    lines = ax.get_legend_handles_labels()
    more = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=6, ncol=5, loc="upper left")
    fig.suptitle(f"{f.key}: {_end(f.redriven)} ({'as the record' if f.agrees else 'differs from the record'})",
                 fontsize=8)
    fig.tight_layout()
    if path is not None:
        from yawil.explain.figures import save_figure

        save_figure(fig, path, dpi=100)
    return fig


def save_kept(kept: Kept, path: Path) -> Path:
    """The kept frames as one compressed .npz (written atomically): images, ids, maps per layer, their steps."""
    from yawil.fileio import atomic_path

    arrays: dict[str, Any] = {f"map_{li}": np.stack([m[li] for m in kept.maps]) for li in range(len(kept.layer_names))}
    arrays.update(images=np.stack(kept.images), ids=np.stack(kept.ids), steps=np.asarray(kept.steps),
                  layer_names=np.array(kept.layer_names))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


def _cell(row: Mapping[str, Any], c: str) -> str:
    lift, mass = row["lift"][c], row["mass"][c]
    return "-" if lift is None else f"{lift:.2f} ({100 * mass:.0f} %)"


def class_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown: one row per frames x layer, the lift (mass %) of each of `COLUMNS`."""
    lines = ["| frames | layer | " + " | ".join(COLUMNS) + " |", "| --- | --- |" + " ---: |" * len(COLUMNS)]
    for r in rows:
        lines.append(f"| {r['frames']} ({r['count']}) | {r['layer']} | " + " | ".join(_cell(r, c) for c in COLUMNS)
                     + " |")
    return "\n".join(lines)


def braking_text(b: Mapping[str, Any]) -> str:
    """One sentence: when the expert would have braked and what the agent did then."""
    if not b.get("expert_brakes"):
        agent = ("the agent braked on none of them" if not b.get("agent_brakes") else
                 f"the agent braked on {b['agent_brakes']} (first {b['first_agent_brake_s']} s before the end)")
        return f"the expert would not have braked in the last {b['frames']} frames; {agent}"
    first, last = b["at_first"], b["at_last"]
    why = ", ".join(f"{k}: {v}" for k, v in b["expert_reasons"].items())
    hit = ""
    if "expert_brakes_for_hit" in b:
        hit = f" ({b['expert_brakes_for_hit']} of them for the agent hit)"
    return (f"the expert would have braked on {b['expert_brakes']} of the last {b['frames']} frames, from "
            f"{b['expert_from_s']} s before the end (frames by reason: {why}){hit}; the agent braked on "
            f"{b['agent_brakes_when_expert_brakes']} of them; target speed then {_ms(b['agent_target_mean'])} "
            f"(agent) against {_ms(b['expert_target_mean'])} (expert); targets agent / expert at the first of them "
            f"{_ms(first['agent_target'])} / {_ms(first['expert_target'])} (speed {_ms(first['speed'])}), at the "
            f"last frame {_ms(last['agent_target'])} / {_ms(last['expert_target'])} (speed {_ms(last['speed'])}; "
            f"lowest in the window {_ms(b['min_speed'])})")


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f} m/s"


def summary_table(failures: Sequence[Failure]) -> str:
    """The printed table: one row per failure."""
    head = ["key", "record", "re-drive", "expert brakes from", "agent brakes", "targets agent/expert",
            "vehicle lift L1/L2/L3 (last 1 s)"]
    lines = ["| " + " | ".join(head) + " |", "| --- " * len(head) + "|"]
    for f in failures:
        b = f.braking
        last = [r for r in f.classes if r["frames"].startswith("last")]
        lifts = "/".join("-" if r["lift"]["vehicle"] is None else f"{r['lift']['vehicle']:.1f}" for r in last)
        targets = (f"{_ms(b.get('agent_target_mean'))} / {_ms(b.get('expert_target_mean'))}"
                   if b.get("expert_brakes") else "-")
        cells = [f.key, f"{_end(f.record)} {f.record.get('time_s')} s",
                 f"{_end(f.redriven)} {f.redriven.get('time_s')} s " + ("ok" if f.agrees else "DIFFERS"),
                 f"-{b['expert_from_s']} s" if b.get("expert_brakes") else "never",
                 f"{b.get('agent_brakes_when_expert_brakes', 0)}/{b['expert_brakes']}" if b.get("expert_brakes")
                 else f"{b['agent_brakes']}/{b['frames']} frames", targets, lifts or "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown(failures: Sequence[Failure], meta: Mapping[str, Any]) -> str:
    out = ["# Failures explained", ""]
    out += [f"- {k}: {v}" for k, v in meta.items()]
    out += ["", "Each failed episode is driven again as the benchmark drove it, the semantic camera on and the expert "
            "shadowing (docs/explain.md, \"Failures explained\"). Lift = attention mass on the class / its pixel "
            "share over the frames named (1: as a uniform map); in brackets the mass. *expert brakes*: the kept "
            "frames where the expert, in the agent's state, brakes for a vehicle, pedestrian or light.", ""]
    if not failures:
        return "\n".join(out + ["No failed episode to explain.", ""])
    out += ["## Summary", "", summary_table(failures), ""]
    for n, f in enumerate(failures, 1):
        col = first_collision(f.record)
        out += [f"## {n}. {f.key}", "",
                f"- record: {_end(f.record)} at {f.record.get('time_s')} s ({f.record.get('steps')} steps)"
                + ("" if col is None else f", {_collision_text(col)}"),
                f"- {f.agreement}", f"- {braking_text(f.braking)}", "", class_table(f.classes), ""]
        if "figure" in f.files:
            out += [f"![{f.key}]({f.files['figure']})", ""]
    return "\n".join(out) + "\n"


@dataclass(frozen=True)
class FailurePlan:
    """Which failures and how much of each: `reasons` (empty: all), at most `max_failures`, the last `seconds`,
    `strip` frames in each figure, the map source (`by_class.AgentMaps`), the blend weight."""

    seconds: float = 3.0
    reasons: tuple[str, ...] = ()
    max_failures: int | None = None
    strip: int = 6
    source: str = "auto"
    alpha: float = 0.5
    save_frames: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.seconds, (int, float)) and math.isfinite(self.seconds) and self.seconds >= DT):
            raise ValueError(f"--seconds {self.seconds!r}: expected at least {DT} s (one step)")
        if self.max_failures is not None and self.max_failures < 1:
            raise ValueError(f"--max-failures {self.max_failures}: expected >= 1")
        if self.strip < 1:
            raise ValueError(f"strip={self.strip}: expected >= 1 frames")


@dataclass(frozen=True)
class Prepared:
    """A results folder read and its agent built (None when nothing is to be explained): all that can refuse,
    done before any output is written."""

    results: Path
    info: dict[str, Any]
    chosen: list[dict[str, Any]]
    failed: int
    agent: AgentOf | None


def prepare(results: Path, plan: FailurePlan = FailurePlan(), checkpoint: str | None = None) -> Prepared:
    """Read the folder's run.json and records, pick the failures, build the agent (only when there are some)."""
    from yawil.bench.records import RUN_FILE

    info = run_info(results)
    chosen, n_failed = failed_records(results, plan.reasons, plan.max_failures)
    agent = load_agent_of(info, checkpoint, str(Path(results) / RUN_FILE)) if chosen else None
    return Prepared(Path(results), info, chosen, n_failed, agent)


def explain_failures(results: Path, out: Path, plan: FailurePlan = FailurePlan(), checkpoint: str | None = None,
                     verbose: bool = False, prepared: Prepared | None = None) -> list[Failure]:
    """Every failed record of `results` (as `plan` selects) re-driven and explained; failures.json, failures.md,
    and per failure its figure (and kept frames) written into `out`, each atomically. `prepared`: `prepare`'s
    result, when the caller has it already."""
    import matplotlib.pyplot as plt

    from yawil.fileio import write_atomic, write_json_atomic

    pre = prepared if prepared is not None else prepare(results, plan, checkpoint)
    info, chosen = pre.info, pre.chosen
    meta: dict[str, Any] = {"results": str(results), "failed": pre.failed, "explained": len(chosen),
                            "reasons": ",".join(plan.reasons) or "all", "seconds": plan.seconds}
    failures: list[Failure] = []
    if chosen:
        of = pre.agent
        assert of is not None
        meta.update({"agent": of.name, "agent_options": info.get("agent_options"), "engine": of.engine})
        meta.update({f"note {i + 1}": n for i, n in enumerate(of.notes)})
        for n, rec in enumerate(chosen, 1):
            f = explain_failure(of.agent, rec, plan.seconds, plan.source)
            stem = slug(f.key, n)
            out.mkdir(parents=True, exist_ok=True)
            plt.close(strip_figure(f, plan.strip, plan.alpha, out / f"{stem}.png"))
            f.files["figure"] = f"{stem}.png"
            if plan.save_frames:
                save_kept(f.kept, out / f"{stem}.npz")
                f.files["frames"] = f"{stem}.npz"
            failures.append(f)
            if verbose:
                print(f"failures: {n}/{len(chosen)} {f.key}: {f.agreement} ({f.drive_s:.0f} s)", file=sys.stderr,
                      flush=True)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "failures.json", {"format": FORMAT, "meta": meta,
                                              "failures": [f.to_dict() for f in failures]})
    write_atomic(out / "failures.md", markdown(failures, meta))
    return failures


# ----- command line (`yawil explain --failures`) --------------------------------------------------------------


def add_failures_arguments(group: Any, flag_group: Any = None) -> None:
    """The options of `yawil explain --failures` (defaults written out: --help computes nothing)."""
    (flag_group if flag_group is not None else group).add_argument(
        "--failures", metavar="RESULTS",
        help="explain every failed episode of a benchmark results folder: re-drive it as the benchmark did (its "
             "run.json's agent, or --checkpoint) and show its last seconds' heat maps, attention by class and "
             "braking (writes failures.json/.md and a figure per failure)")
    group.add_argument("--failure-reasons", default="",
                       help="--failures: only these reasons, e.g. collision_vehicle,collision_pedestrian (default all)")
    group.add_argument("--max-failures", type=int, default=None, help="--failures: at most this many (default all)")
    group.add_argument("--seconds", type=float, default=3.0,
                       help="--failures: the last seconds kept and shown (default 3 = 30 steps)")
    group.add_argument("--strip", type=int, default=6, help="--failures: frames in each figure (default 6)")


def run_from_args(args: argparse.Namespace, out: str | Path) -> int:
    """`yawil explain --failures`: `explain_failures` with the options of `add_failures_arguments`; prints the
    summary table. `out` is claimed as explain's output folder only once the folder is read and the agent built
    (a refusal leaves nothing behind)."""
    from yawil.fileio import claimed_output_folder

    results = Path(args.failures)
    reasons = tuple(r.strip() for r in str(args.failure_reasons).split(",") if r.strip())
    plan = FailurePlan(seconds=args.seconds, reasons=reasons, max_failures=args.max_failures, strip=args.strip,
                       source=getattr(args, "maps", "auto"), alpha=getattr(args, "alpha", 0.5))
    checkpoint = getattr(args, "checkpoint", None)
    pre = prepare(results, plan, checkpoint)
    with claimed_output_folder(out, "explain") as out:
        failures = explain_failures(results, out, plan, checkpoint, verbose=True, prepared=pre)
    if not failures:
        what = f" with reason {', '.join(reasons)}" if reasons else ""
        print(f"{results}: no failed episode{what} to explain; wrote {out / 'failures.md'}")
        return 0
    print(summary_table(failures))
    differ = sum(not f.agrees for f in failures)
    if differ:
        print(f"{differ} of {len(failures)} re-drives differ from their records (failures.md says how)")
    print(f"wrote {out / 'failures.json'}, {out / 'failures.md'} and {len(failures)} figures")
    return 0
