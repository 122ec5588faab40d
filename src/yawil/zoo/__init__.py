"""The model zoo: trained models shipped in the repository, each with its card and a probe of fixed frames.

    yawil models --zoo                                  # the zoo's models and their cards' headline figures
    yawil bench --agent zoo:yilratt-dagger ...          # any command that takes a checkpoint takes zoo:NAME
    yawil zoo pack runs/x/last.pt --name NAME --data data/town01 --card card.json   # add or replace one
    yawil zoo check                                     # every model's outputs on its probe frames vs its card

A zoo model is a folder `src/yawil/zoo/NAME/` with
- `model.pt`: a yawil checkpoint without the training-resume keys, its floating weights stored in bfloat16 and
  the weights no output depends on left out (YILRatt's layer4: `omitted`); loading restores float32 and leaves
  the omitted modules at their initialisation;
- `card.json`: how it was made and what it scored (commands, commit, data, steps, wall time, machine,
  validation, benchmark results, how to drive it), written by whoever trained it, plus `probe`: the outputs
  of the packed model on the probe frames;
- `probe.npz`: a few dataset frames as the agent receives them (camera uint8, speed, raw guidance, command).

Why a probe: a silent change of preprocessing or of a model's code would change what a shipped model does
without any error; `check_zoo_model` runs the probe through the agent's own input path and compares.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

ZOO_DIR = Path(__file__).resolve().parent
PREFIX = "zoo:"
WEIGHTS, CARD, PROBE = "model.pt", "card.json", "probe.npz"
PROBE_FRAMES = 8  # frames of its dataset a packed model's outputs are recorded on (`zoo check` compares them)


def zoo_names(root: Path | None = None) -> list[str]:
    root = root or ZOO_DIR
    return sorted(p.name for p in root.iterdir() if (p / WEIGHTS).is_file()) if root.is_dir() else []


def zoo_dir(name: str, root: Path | None = None) -> Path:
    root = root or ZOO_DIR
    if not (root / name / WEIGHTS).is_file():
        known = ", ".join(zoo_names(root)) or "none"
        raise ValueError(f"zoo:{name}: no such zoo model (the zoo has: {known})")
    return root / name


# weights files already checked against their cards: path -> (mtime_ns, size, sha256); a run resolves the same
# zoo model many times (spec, identity, hash, every agent built) and 20 MB is hashed once
_VERIFIED: dict[Path, tuple[int, int, str]] = {}


def weights_sha256(name: str) -> str:
    """The SHA-256 of zoo model `name`'s weights file, checked against its card's (`weights_sha256`), in one line
    naming the file when they differ."""
    path = zoo_dir(name) / WEIGHTS
    st = path.stat()
    seen = _VERIFIED.get(path)
    if seen is not None and seen[:2] == (st.st_mtime_ns, st.st_size):
        return seen[2]
    want = read_card(name).get("weights_sha256")
    if want is None:
        raise ValueError(f"{path.parent / CARD}: no weights_sha256; a zoo card names its weights' hash")
    from yawil.fileio import file_sha256

    if file_sha256(path) != want:
        raise ValueError(f"{path}: its SHA-256 differs from its card's weights_sha256: the file is damaged or was "
                         "replaced without `yawil zoo pack` (restore it, e.g. git checkout)")
    _VERIFIED[path] = (st.st_mtime_ns, st.st_size, want)
    return str(want)


def resolve_checkpoint(arg: str | os.PathLike[str]) -> Path:
    """A checkpoint path, or `zoo:NAME` -> that zoo model's weights file, checked against its card's SHA-256."""
    s = str(arg)
    if not s.startswith(PREFIX):
        return Path(s)
    weights_sha256(s[len(PREFIX):])
    return zoo_dir(s[len(PREFIX):]) / WEIGHTS


def read_card(name: str, root: Path | None = None) -> dict[str, Any]:
    path = zoo_dir(name, root) / CARD
    try:
        card = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable model card ({err})") from None
    if not isinstance(card, dict):
        raise ValueError(f"{path}: a model card is a JSON object")
    return card


DRIVE_KEYS = ("speed_control", "stop_release", "stop_creep", "stop_hold", "stop_gate", "light_hold")  # what a card's "drive" may name


def card_drive(agent: str) -> dict[str, Any]:
    """How a zoo model's card says it is driven (`drive`: speed_control, stop_release, stop_creep, as keyword
    options of `yawil.policy.drive.DriveSettings`); {} for anything else. An unknown key is refused in one line."""
    if not agent.startswith(PREFIX):
        return {}
    drive = read_card(agent[len(PREFIX):]).get("drive") or {}
    unknown = sorted(set(drive) - set(DRIVE_KEYS))
    if unknown:
        raise ValueError(f"{agent}: card.json drive names {', '.join(unknown)}; expected {', '.join(DRIVE_KEYS)}")
    return dict(drive)


def drive_flags(drive: dict[str, Any]) -> str:
    """A card's `drive` as the command-line flags it stands for."""
    return " ".join(f"--{k.replace('_', '-')} {v}" for k, v in drive.items())


def headline(name: str) -> dict[str, Any]:
    """What `yawil models --zoo` prints of a card."""
    card = read_card(name)
    ev = card.get("eval100") or {}
    return {"name": name, "model": card.get("model_name"), "steps": card.get("steps_total", card.get("step")),
            "eval100": f"{ev['successes']}/{ev['episodes']}" if "successes" in ev else "not measured",
            "drive": card.get("drive") or {}, "summary": card.get("summary", "")}


def table() -> str:
    """The zoo as `yawil models --zoo` and `yawil zoo list` print it."""
    names = zoo_names()
    if not names:
        return "the zoo is empty"
    lines = [f"{'name':<24}{'model':<12}{'steps':>7}  {'eval100':<14}drive"]
    for n in names:
        h = headline(n)
        drive = drive_flags(h["drive"]) or "-"
        lines.append(f"{n:<24}{h['model']!s:<12}{h['steps']!s:>7}  {h['eval100']:<14}{drive}")
    return "\n".join(lines)
