"""The results folder: an append-only JSON-lines file of episode records plus a small run description.

Why append-only: a benchmark takes hours and may be killed at any time. Each record is written as one line,
flushed and fsynced before the next episode counts as done, so a kill loses at most the episodes in flight.
On restart the file is read, a partial last line (the kill hit mid-write) is cut off, and the episodes whose
keys are present are skipped: nothing is repeated, nothing is lost.
"""

from __future__ import annotations

import functools
import json
import math
import os
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TextIO

from yawil.fileio import non_finite, write_json_atomic

EPISODES_FILE = "episodes.jsonl"
RUN_FILE = "run.json"
KEY_FIELDS: tuple[str, ...] = ("task", "condition", "weather", "route_id", "seed")
# Version of the episode protocol, written into every record and run.json. 2 (2026-12-02): every route in every
# weather (the weather joined the key), each suite's own timeout, the `blocked` end. Results of another version
# are refused, by `yawil bench` on resume and by `yawil report` (docs/benchmark.md, "Protocol versions"): their
# figures do not mean the same thing, and a report that mixed them would not say so.
PROTOCOL = 2
_PROTOCOLS = {1: "each route in one weather, one timeout for every task, no 'blocked' end"}


def _other_protocol(version: Any) -> str:
    what = _PROTOCOLS.get(version, "a version this yawil does not know") if isinstance(version, int) else "unknown"
    return (f"written under benchmark protocol {version} ({what}); this yawil drives and reports protocol "
            f"{PROTOCOL} (docs/benchmark.md, 'Protocol versions'): drive the agent again into a new folder "
            "(for `yawil experiment` and `reproduce`: remove the experiment's results/ and noise/ folders; its "
            "data and models are reused)")


def episode_key(rec: Mapping[str, Any]) -> str:
    """Identity of an episode: task, condition, weather, route and seed (the agent is fixed per results folder)."""
    try:
        return "/".join(str(rec[k]) for k in KEY_FIELDS)
    except KeyError as err:
        raise ValueError(f"episode record lacks key field {err.args[0]!r}") from None


def read_records(path: str | Path, repair: bool = False,
                 on_partial: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """All complete records of a JSON-lines file.

    A last line without its newline or that does not parse is the trace of a kill mid-write: it is ignored
    (`on_partial` is told, in one line), and cut from the file when `repair` is True so that appending continues
    on a clean line. A bad line anywhere else is corruption and raises ValueError naming the file and line, as
    does a number that is not finite (NaN, Infinity, 1e999: Python's JSON reads them, no figure may hold one).
    """
    return [rec for _, rec in _read_numbered(path, repair, on_partial)]


def _read_numbered(path: str | Path, repair: bool = False,
                   on_partial: Callable[[str], None] | None = None) -> list[tuple[int, dict[str, Any]]]:
    """`read_records` with each record's line number (for messages that name the line)."""
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    records: list[tuple[int, dict[str, Any]]] = []
    pos = 0
    lineno = 0
    good_end = 0
    while pos < len(data):
        lineno += 1
        nl = data.find(b"\n", pos)
        last = nl < 0 or nl == len(data) - 1
        chunk = data[pos:] if nl < 0 else data[pos:nl]
        try:
            if nl < 0:
                raise ValueError("no newline")
            rec = json.loads(chunk.decode("utf-8")) if chunk.strip() else None
            if rec is not None and not isinstance(rec, dict):
                raise ValueError("not a JSON object")
        except (ValueError, UnicodeDecodeError) as err:
            if last:
                break  # partial last line: ignored (and cut below if repairing)
            raise ValueError(f"{path}: line {lineno} is not a valid episode record ({err})") from None
        if rec is not None:
            try:  # the C encoder finds a non-finite number fast; the walk that names it runs only then
                json.dumps(rec, allow_nan=False)
            except ValueError:
                field, value = non_finite(rec) or ("?", float("nan"))
                raise ValueError(f"{path}: line {lineno}: {field}={value}, expected a finite number") from None
            records.append((lineno, rec))
        pos = nl + 1
        good_end = pos
    if good_end < len(data) and on_partial is not None:
        on_partial(f"{path}: line {lineno} is an unfinished record (a run stopped mid-write); left out, and the "
                   "episode is driven again when the run is resumed")
    if repair and good_end < len(data):
        with open(path, "r+b") as fh:
            fh.truncate(good_end)
            fh.flush()
            os.fsync(fh.fileno())
    return records


class EpisodeLog:
    """Appends records to `<folder>/episodes.jsonl`, durable per line; knows which keys are done."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.path = self.folder / EPISODES_FILE
        self.records = read_records(self.path, repair=True)
        self.done: set[str] = set()
        for i, rec in enumerate(self.records):
            key = episode_key(rec)
            if key in self.done:
                raise ValueError(f"{self.path}: record {i + 1} repeats episode {key}")
            self.done.add(key)
        self._fh: TextIO | None = None

    def __contains__(self, key: str) -> bool:
        return key in self.done

    def append(self, rec: Mapping[str, Any]) -> None:
        key = episode_key(rec)
        if key in self.done:
            raise ValueError(f"episode {key} is already in {self.path}")
        line = json.dumps(rec, separators=(",", ":"), allow_nan=False)
        if "\n" in line:
            raise ValueError("an episode record must serialise to one line")
        if self._fh is None:
            self._fh = open(self.path, "a", encoding="utf-8")
        self._fh.write(line + "\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self.done.add(key)
        self.records.append(dict(rec))

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> EpisodeLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def check_run_info(folder: str | Path, info: Mapping[str, Any], label_given: bool = False, write: bool = True) -> None:
    """Store the agent's identity (and the protocol version) with the results, or check that a resumed run
    uses the same agent under the same protocol.

    Mixing two agents' episodes in one folder would make its figures meaningless, so it is an error: the
    same path, options and checkpoint content (`agent_sha256`; folders written before it was recorded are
    checked by path only). A label given explicitly must match the folder's (it would otherwise be ignored).
    `write=False` only checks (before the lock is taken and the agent built).
    """
    path = Path(folder) / RUN_FILE
    if path.exists():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except ValueError as err:
            raise ValueError(f"{path}: not valid JSON ({err})") from None
        if not isinstance(old, dict) or not {"agent", "agent_options"} <= set(old):  # every version wrote both
            raise ValueError(f"{path}: this folder holds a run.json that is not a yawil results record (no agent "
                             "and agent_options); give a new or empty --out folder")
        if old.get("protocol", 1) != PROTOCOL:
            raise ValueError(f"{path}: results {_other_protocol(old.get('protocol', 1))}")
        keys = ["agent", "agent_options"] + (["label"] if label_given else [])
        same_weights = old.get("agent_sha256") is not None and old.get("agent_sha256") == info.get("agent_sha256")
        for key in keys:
            if key == "agent" and (_zoo_path_of(old.get(key)) == info.get(key) or same_weights):
                continue  # a zoo model named by its installed path before, or a checkpoint moved (same weights)
            if old.get(key) != info.get(key):
                raise ValueError(
                    f"{path}: results folder belongs to {key}={old.get(key)!r}, this run has {info.get(key)!r}; "
                    "use another --out folder"
                )
        if old.get("agent_sha256") is not None and old.get("agent_sha256") != info.get("agent_sha256"):
            raise ValueError(
                f"{path}: the checkpoint {info.get('agent')} has changed since these results were driven "
                f"(sha256 {str(old['agent_sha256'])[:12]}... then, {str(info.get('agent_sha256'))[:12]}... now); "
                "use another --out folder"
            )
        return
    if write:
        write_json_atomic(path, {**info, "protocol": PROTOCOL})


def _zoo_path_of(agent: Any) -> str | None:
    """`zoo:NAME` for the installed path of a zoo model's weights (how records named one before), else None."""
    parts = Path(str(agent)).parts
    if len(parts) >= 3 and parts[-1] == "model.pt" and parts[-3] == "zoo":
        return f"zoo:{parts[-2]}"
    return None


# Fields the report computes with, and what each must hold: a hand-edited "success": "yes" or a negative
# route id would otherwise become a figure.
_REPORT_FIELDS: dict[str, tuple[str, Any]] = {
    "task": ("a task name", lambda v: isinstance(v, str) and bool(v)),
    "condition": ("a condition name", lambda v: isinstance(v, str) and bool(v)),
    "weather": ("a weather name", lambda v: isinstance(v, str) and bool(v)),
    "route_id": ("an integer >= 0", lambda v: _is_int(v) and v >= 0),
    "seed": ("an integer >= 0", lambda v: _is_int(v) and v >= 0),
    "success": ("true or false", lambda v: isinstance(v, bool)),
    "km_driven": ("a number >= 0", lambda v: _is_num(v) and v >= 0),
}
_COUNT_FIELDS = ("lane_offroad", "lane_opposite", "lights_passed", "red_lights")


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def check_record(rec: Mapping[str, Any], where: str) -> None:
    """ValueError naming the record and field when a record cannot be counted as written."""
    if rec.get("protocol", 1) != PROTOCOL:
        raise ValueError(f"{where}: {_other_protocol(rec.get('protocol', 1))}")
    for name, (want, ok) in _REPORT_FIELDS.items():
        if name not in rec:
            raise ValueError(f"{where}: field {name!r} is missing (expected {want})")
        if not ok(rec[name]):
            raise ValueError(f"{where}: {name}={rec[name]!r}, expected {want}")
    for name in _COUNT_FIELDS:
        if name in rec and not (_is_num(rec[name]) and rec[name] >= 0):
            raise ValueError(f"{where}: {name}={rec[name]!r}, expected a count >= 0")


def iter_results(folder: str | Path) -> Iterator[dict[str, Any]]:
    """Records of a results folder (or of a JSON-lines file given directly)."""
    p = Path(folder)
    path = p / EPISODES_FILE if p.is_dir() else p
    if not path.exists():
        raise ValueError(f"{folder}: no {EPISODES_FILE} found (expected a folder written by `yawil bench`)")
    seen: dict[str, int] = {}
    note = functools.partial(print, file=sys.stderr)
    for i, (line, rec) in enumerate(_read_numbered(path, on_partial=lambda m: note(f"note: {m}"))):
        check_record(rec, f"{path}: line {line}, record {i + 1}")
        key = episode_key(rec)
        if key in seen:  # counted twice, a figure would be wrong without a word
            raise ValueError(f"{path}: line {line}, record {i + 1} repeats episode {key} (record {seen[key] + 1})")
        seen[key] = i
        yield rec
