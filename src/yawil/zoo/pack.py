"""Making and checking zoo models (`yawil zoo pack`, `yawil zoo check`): compact weights, probe frames, cards.

The catalogue (names, cards, `zoo:NAME` paths) is `yawil.zoo`; this module needs torch and the agent.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from yawil.fileio import write_json_atomic
from yawil.policy.checkpoint import RESUME_KEYS, load_checkpoint, save_checkpoint
from yawil.policy.probe import read_probe, sample_probe  # noqa: F401  (re-exported: pack's own names)
from yawil.zoo import CARD, PROBE, PROBE_FRAMES, WEIGHTS, ZOO_DIR, read_card, zoo_dir

PROBE_TOLERANCE = 1e-3  # max |output - card| on the probe frames (float32 on any CPU agrees far closer)
DROP_KEYS = (*RESUME_KEYS, "scaler", "runtime", "rng_ranks", "raw_state_dict", "ema", "resume_sha256")


def unused_modules(model: torch.nn.Module, inputs: dict[str, torch.Tensor | None]) -> list[str]:
    """The largest sub-modules none of whose parameters get a gradient from any output: they can be left out."""
    model.zero_grad(set_to_none=True)
    out = model(**inputs)
    parts = [out.actions, out.speed, *(t for t in (out.aux, out.branches) if t is not None), *out.attention]
    sum(t.float().sum() for t in parts).backward()  # type: ignore[union-attr]
    dead = {n for n, p in model.named_parameters() if p.grad is None}
    model.zero_grad(set_to_none=True)
    found: list[str] = []
    for name, module in model.named_modules():
        params = [f"{name}.{n}" if name else n for n, _ in module.named_parameters()]
        if name and params and all(p in dead for p in params) and not any(name.startswith(f + ".") for f in found):
            found.append(name)
    return found


def compact_checkpoint(ckpt: dict[str, Any], omitted: list[str]) -> dict[str, Any]:
    """The checkpoint without resume keys and omitted modules, floating weights in bfloat16."""
    keep = {k: v for k, v in ckpt.items() if k not in DROP_KEYS}
    state = {}
    for k, v in ckpt["state_dict"].items():
        if any(k.startswith(m + ".") for m in omitted):
            continue
        state[k] = v.to(torch.bfloat16) if v.is_floating_point() else v
    return {**keep, "state_dict": state, "omitted": list(omitted)}


def probe_agent(checkpoint: str | Path) -> Any:
    """The checkpoint's agent as the probe runs it: torch, fp32 on the CPU, no channels_last (the same on any CPU)."""
    from yawil.agent import Agent

    return Agent.from_checkpoint(checkpoint, precision="fp32", channels_last="off", engine="torch")


def probe_inputs(agent: Any, probe: dict[str, np.ndarray], i: int) -> Any:
    """Probe frame `i` through the agent's own input path."""
    g = probe["guidance"][i] if agent.kind is not None else None
    c = int(probe["command"][i]) if agent.uses_command else None
    return agent.spec.from_frame(probe["image"][i], float(probe["speed"][i]), g, c)


def probe_outputs(agent: Any, probe: dict[str, np.ndarray]) -> dict[str, list[list[float]]]:
    """The agent's network outputs on the probe frames (a `probe_agent`)."""
    rows: dict[str, list[list[float]]] = {"actions": [], "speed": [], "aux": []}
    with torch.inference_mode():
        for i in range(len(probe["speed"])):
            out = probe_inputs(agent, probe, i).forward(agent.model)
            rows["actions"].append([round(float(v), 6) for v in out.actions[0]])
            rows["speed"].append([round(float(v), 6) for v in out.speed[0]])
            if out.aux is not None:
                rows["aux"].append([round(float(v), 6) for v in out.aux[0]])
    if not rows["aux"]:
        del rows["aux"]
    return rows


# The fields a card given to `pack` may hold (written by whoever trained the model); pack adds the rest.
CARD_FIELDS = ("summary", "commands", "commit", "data", "made_by", "machine", "wall_s", "steps_total", "steps_note",
               "validation", "selection", "eval100", "demo", "results", "drive", "training_seeds")
PACKED_FIELDS = ("name", "model_name", "model_config", "step", "omitted", "weights", "parameters_stored", "probe",
                 "weights_sha256")


def check_card(card: Any, where: str) -> dict[str, Any]:
    """A card's own fields, refused in one line if one is unknown (a typo would vanish silently), one is pack's
    to write, a number is NaN or infinite (a figure that means nothing, and card.json would not be JSON), or its
    `drive` is not a valid way of driving."""
    from yawil.fileio import non_finite
    from yawil.policy.drive import DriveSettings
    from yawil.zoo import DRIVE_KEYS

    if not isinstance(card, dict):
        raise ValueError(f"{where}: expected a JSON object")
    bad = non_finite(card)
    if bad is not None:
        raise ValueError(f"{where}: {bad[0]}={bad[1]}, expected a finite number")
    ours = sorted(set(card) & set(PACKED_FIELDS))
    if ours:
        raise ValueError(f"{where}: {', '.join(ours)} are written by yawil zoo pack; leave them out")
    unknown = sorted(set(card) - set(CARD_FIELDS))
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {', '.join(unknown)}; a card holds {', '.join(CARD_FIELDS)}")
    seeds = card.get("training_seeds", {})
    if not isinstance(seeds, dict) or not all(k.isdigit() and isinstance(v, dict) for k, v in seeds.items()):
        raise ValueError(f"{where}: training_seeds must map a training seed (\"1\", \"2\", ...) to an object of that "
                         f"seed's commands and figures, got {seeds!r}")
    drive = card.get("drive") or {}
    if not isinstance(drive, dict) or set(drive) - set(DRIVE_KEYS):
        raise ValueError(f"{where}: drive must be an object of {', '.join(DRIVE_KEYS)}, got {drive!r}")
    try:
        DriveSettings.from_options(drive)
    except ValueError as err:
        raise ValueError(f"{where}: drive: {err}") from None
    return card


def pack(checkpoint: str | Path, name: str, data: Path, card: dict[str, Any], root: Path | None = None,
         count: int = PROBE_FRAMES, force: bool = False) -> Path:
    """Write zoo model `name` into `root` (default: the shipped zoo) from a training checkpoint: compact weights,
    probe frames, the card with the probe's outputs, the largest difference of the compact model from the
    checkpoint on them and the weights' SHA-256. Everything is checked first (name, card, dataset, an existing
    model of that name needs `force`); the model is built in a temporary folder and takes its place whole."""
    import os
    import shutil

    from yawil.data.check import check_dataset
    from yawil.fileio import _check_writable_parent, check_not_inside_owned
    from yawil.policy.drive import DriveSettings

    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"--name {name!r}: expected a plain folder name")
    check_card(card, "--card")
    root = root or ZOO_DIR
    final = root / name
    _check_writable_parent(final, "--out")  # else the OS names the temporary folder, after the work
    if root != ZOO_DIR:  # a model folder inside a dataset or run is read as part of it
        check_not_inside_owned(root, "--out")
    if final.exists() or final.is_symlink():
        if not (final.is_dir() and (final / WEIGHTS).is_file() and (final / CARD).is_file()):
            raise ValueError(f"{final}: exists and is not a zoo model (no {WEIGHTS} and {CARD}); choose another "
                             "--name or --out (--force replaces only a zoo model)")
        if not force:
            raise ValueError(f"{final}: a zoo model of that name exists; give --force to replace it (or another --name)")
    report = check_dataset(data, images=False)
    if not report.ok:
        raise ValueError(f"--data {data}: fails yawil data check: " + "; ".join(report.lines()[-3:]))
    if count > report.frames:  # more could only repeat frames, and a mistyped large count ran on for long
        raise ValueError(f"--frames {count}: {data} has {report.frames} frames; give at most that many probe frames")
    ckpt = load_checkpoint(checkpoint)
    full_agent = probe_agent(checkpoint)
    try:  # the card's drive must suit this model (a "stop" drive reads the aux head's lead-stop output)
        DriveSettings.from_options(card.get("drive") or {}).check(full_agent.model)
    except ValueError as err:
        raise ValueError(f"--card: drive {card.get('drive')}: {err}") from None
    probe = sample_probe(Path(data), full_agent.kind, count)
    omitted = unused_modules(full_agent.model, probe_inputs(full_agent, probe, 0).as_dict())
    folder = root / f".{name}.packing-{os.getpid()}"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    try:
        _write(ckpt, omitted, probe, full_agent, card, name, folder)
        if final.exists():  # --force: the old model leaves only once the new one is complete
            old = root / f".{name}.replaced-{os.getpid()}"
            os.replace(final, old)
            os.replace(folder, final)
            shutil.rmtree(old)
        else:
            os.replace(folder, final)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return final


def _write(ckpt: dict[str, Any], omitted: list[str], probe: dict[str, np.ndarray], full_agent: Any,
           card: dict[str, Any], name: str, folder: Path) -> None:
    from yawil.fileio import atomic_path, file_sha256

    compact = compact_checkpoint(ckpt, omitted)
    save_checkpoint(compact, folder / WEIGHTS)
    with atomic_path(folder / PROBE) as tmp:
        np.savez_compressed(tmp, image=probe["image"], speed=probe["speed"], guidance=probe["guidance"],
                            command=probe["command"])
    packed, full = probe_outputs(probe_agent(folder / WEIGHTS), probe), probe_outputs(full_agent, probe)
    drift = max(abs(a - b) for k in packed for ra, rb in zip(packed[k], full[k], strict=True)
                for a, b in zip(ra, rb, strict=True))
    card = {**card, "name": name, "model_name": ckpt["model_name"], "model_config": ckpt["model_config"],
            "step": ckpt["step"], "omitted": omitted, "weights": "bfloat16",
            "parameters_stored": sum(v.numel() for v in compact["state_dict"].values()),
            "probe": {**packed, "bf16_max_diff_from_fp32": round(drift, 6)},
            "weights_sha256": file_sha256(folder / WEIGHTS)}
    write_json_atomic(folder / CARD, card)


def check_zoo_model(name: str, root: Path | None = None) -> float:
    """The largest |output - card| on the probe frames; ValueError over PROBE_TOLERANCE."""
    folder = zoo_dir(name, root)
    want = read_card(name, root).get("probe")
    if not isinstance(want, dict) or "actions" not in want:
        raise ValueError(f"{folder / CARD}: no probe outputs (field 'probe.actions')")
    got = probe_outputs(probe_agent(folder / WEIGHTS), read_probe(folder))
    worst = 0.0
    for key, rows in got.items():
        ref = np.asarray(want.get(key), dtype=np.float64)
        if ref.shape != np.asarray(rows).shape:
            raise ValueError(f"{folder / CARD}: probe.{key} has shape {ref.shape}, the model gives {np.asarray(rows).shape}")
        worst = max(worst, float(np.abs(np.asarray(rows) - ref).max()))
    if worst > PROBE_TOLERANCE:
        raise ValueError(f"zoo:{name}: outputs on the probe frames differ from its card by {worst:.2e} "
                         f"(> {PROBE_TOLERANCE}): preprocessing or the model's code changed")
    return worst

