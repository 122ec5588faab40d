"""docs/results.md, made from committed records: `yawil results records/results.json --out docs/results.md`.

The manifest (JSON) lists the headline runs, each a results folder under the manifest's folder with what the
table needs to say about it: which model family it is (to sit beside the paper's column of that family), how
many training seeds stand behind it, its role (test: the condition run once per shipped model; selection:
the training-town set that chose it), the command that drove it and, for the agents the tables compare, its
`column`: the test rows of one agent (its cells of several runs, e.g. Dense and Regular) share one. Every row is
listed beside the paper's figure; Tables III and IV, README's headline and the paper's claims are of the columns
only, so earlier models and drive variants stay on the page without crowding the tables. Every cell carries a
95 % Wilson interval, and each claim is marked by its evidence: a difference counts only when its interval (Newcombe's, from the two Wilson intervals)
excludes zero. A claim whose rows are absent reads "not tested". Nothing on the page is typed by hand but the
manifest's notes, so the page and README's headline cell regenerate on any clone.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from yawil.bench.metrics import difference_interval, mean_std, wilson_interval
from yawil.bench.paper import PAPER_MODELS, TABLE_III, paper_cell
from yawil.bench.records import episode_key
from yawil.bench.suites import CONDITIONS, TABLE_TASKS, TASKS

TITLE = "# Results: what yawil's agents drive"  # the page's first line: how `yawil results` knows its own page
MODELS = ("expert", "cil", "cilrs", "yaw-guided", "yilratt", "yilratt-pretrained")
ROLES = ("test", "selection")
_ROW_FIELDS = {"folder": str, "label": str, "model": str, "training_seeds": int, "role": str, "command": str}
_OPTIONAL = {"note": str, "column": str, "training_seed": int}


@dataclass(frozen=True)
class Row:
    """One headline run of the manifest and its records."""

    label: str
    model: str
    training_seeds: int
    role: str
    command: str
    folder: Path
    records: tuple[dict[str, Any], ...]
    note: str = ""
    column: str = ""  # the agent's column in Tables III/IV and the claims ("": listed only)
    training_seed: int | None = None  # which training seed's model drove it, where a column has several

    def episodes(self, task: str, condition: str) -> list[dict[str, Any]]:
        """The records of one Table III cell."""
        return [r for r in self.records if r["task"] == task and r["condition"] == condition]

    def cell(self, task: str, condition: str) -> tuple[int, int]:
        """(successes, episodes) of one Table III cell, seeds pooled."""
        return _successes(self.episodes(task, condition))


def _successes(records: Sequence[dict[str, Any]]) -> tuple[int, int]:
    return sum(bool(r["success"]) for r in records), len(records)


@dataclass(frozen=True)
class Claim:
    """A claim of the paper, checked on the rows of two model families (or one against a published level)."""

    text: str
    a: str
    b: str | None  # None: `a` against the paper's own figure of its cells
    tasks: tuple[str, ...]
    condition: str


CLAIMS: tuple[Claim, ...] = (
    Claim("YILRatt beats CILRS in traffic, New Town02 & Weather (paper: +41 points Regular, +42 Dense)",
          "yilratt", "cilrs", ("regular", "dense"), "new-town-weather"),
    Claim("YILRatt beats CIL in traffic, New Town02 & Weather (paper: +30 Regular, +51 Dense)",
          "yilratt", "cil", ("regular", "dense"), "new-town-weather"),
    Claim("CIL beats CILRS in New Town02 & Weather, the paper's sign of the larger network over-fitting (paper: +6 "
          "One Turn, +20 Navigation, +11 Regular, but -9 Dense)", "cil", "cilrs", TABLE_TASKS, "new-town-weather"),
    Claim("Attention helps generalisation: YILRatt beats the yaw-guided network without it (the same guidance on "
          "CIL's small perception: no ResNet34, no attention), New Town02 & Weather", "yilratt", "yaw-guided",
          TABLE_TASKS, "new-town-weather"),
    Claim("Yaw guidance beats commands: the yaw-guided network beats CIL (the same perception with command "
          "branches), New Town02 & Weather (the paper's Tables I-II thesis, here in its benchmark)", "yaw-guided",
          "cil", TABLE_TASKS, "new-town-weather"),
    Claim("ImageNet pretraining helps a little (paper: +6 Dense, +11 Regular, New Town02 & Weather)",
          "yilratt-pretrained", "yilratt", ("regular", "dense"), "new-town-weather"),
    Claim("YILRatt drives Nav. (Dense) in New Town02 & Weather at the paper's level (76.0 ± 3.27)",
          "yilratt", None, ("dense",), "new-town-weather"),
    Claim("YILRatt drives Nav. (Regular) in New Town02 & Weather at the paper's level (76.66 ± 0.94)",
          "yilratt", None, ("regular",), "new-town-weather"),
)


def _bad(where: str, what: str) -> ValueError:
    return ValueError(f"{where}: {what}")


def _read_attention(path: Path, item: Any) -> dict[str, Any]:
    """The manifest's `attention` block: label, command, and the JSON outputs of `yawil explain --by-class`
    (`by_class`) and `--faithfulness` (`faithfulness`), paths relative to the manifest, read here."""
    where = f"{path} attention"
    if not isinstance(item, dict) or not all(isinstance(item.get(k), str) for k in ("label", "by_class", "command")):
        raise _bad(where, "expected an object with strings 'label', 'command', 'by_class' (and 'faithfulness')")
    out: dict[str, Any] = {"label": item["label"], "command": item["command"]}
    for key in ("by_class", "faithfulness"):
        if key in item:
            file = path.parent / str(item[key])
            try:
                out[key] = json.loads(file.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:
                raise _bad(where, f"{key} {file} cannot be read as JSON ({err})") from None
    return out


def read_results_manifest(path: str | Path) -> tuple[list[Row], str, dict[str, Any] | None]:
    """The manifest's rows with their records (checked: every field named, every folder readable), the text
    of its `notes_file` (Markdown: rows measured before their records were kept) and its `attention` block."""
    from yawil.bench.records import iter_results

    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise _bad(str(path), f"cannot be read ({err.strerror or err})") from None
    except ValueError as err:
        raise _bad(str(path), f"not valid JSON ({err})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("rows"), list) or not doc["rows"]:
        raise _bad(str(path), "expected an object with a non-empty list 'rows'")
    rows = []
    for i, item in enumerate(doc["rows"]):
        where = f"{path} rows[{i}]"
        if not isinstance(item, dict):
            raise _bad(where, "expected an object")
        unknown = sorted(set(item) - set(_ROW_FIELDS) - set(_OPTIONAL))
        if unknown:
            raise _bad(where, f"unknown field(s) {', '.join(unknown)}; expected {', '.join(_ROW_FIELDS)} "
                              f"(and optionally {', '.join(_OPTIONAL)})")
        for name, kind in _ROW_FIELDS.items():
            if not isinstance(item.get(name), kind) or isinstance(item.get(name), bool):
                raise _bad(where, f"field {name!r} must be a {kind.__name__}, got {item.get(name)!r}")
        for name, kind in _OPTIONAL.items():
            if name in item and (not isinstance(item[name], kind) or isinstance(item[name], bool)
                                 or (kind is str and not item[name]) or (kind is int and item[name] < 0)):
                want = "a non-empty str" if kind is str else "an int >= 0"
                raise _bad(where, f"field {name!r} must be {want}, got {item[name]!r}")
        if "training_seed" in item and item["training_seeds"] != 1:
            raise _bad(where, f"training_seed {item['training_seed']} on a row of {item['training_seeds']} training "
                              "seeds; a row with training_seed is one model (training_seeds 1)")
        if item["model"] not in MODELS:
            raise _bad(where, f"model {item['model']!r}; expected one of {', '.join(MODELS)}")
        if item["role"] not in ROLES:
            raise _bad(where, f"role {item['role']!r}; expected one of {', '.join(ROLES)}")
        if "column" in item and item["role"] != "test":
            raise _bad(where, f"column {item['column']!r} on a {item['role']} row; only test rows are table columns")
        if item["training_seeds"] < 0:
            raise _bad(where, f"training_seeds must be >= 0 (0: the expert), got {item['training_seeds']}")
        folder = path.parent / item["folder"]
        try:
            records = tuple(iter_results(folder))
        except ValueError as err:
            raise _bad(where, str(err)) from None
        if not records:
            raise _bad(where, f"{folder} holds no episode records")
        rows.append(Row(item["label"], item["model"], item["training_seeds"], item["role"], item["command"],
                        folder, records, item.get("note", ""), item.get("column", ""), item.get("training_seed")))
    labels = [r.label for r in rows]
    if len(set(labels)) != len(labels):
        raise _bad(str(path), f"row labels must differ, got {labels}")
    columns(rows, str(path))  # a column's rows agree and never share a cell
    attention = doc.get("attention")
    if attention is not None:
        attention = _read_attention(path, attention)
    notes = ""
    if doc.get("notes_file") is not None:
        notes_path = path.parent / str(doc["notes_file"])
        try:
            notes = notes_path.read_text(encoding="utf-8")
        except OSError as err:
            raise _bad(f"{path} notes_file", f"{notes_path} cannot be read ({err.strerror or err})") from None
    return rows, notes, attention


def _cells(row: Row) -> set[tuple[str, str]]:
    return {(r["task"], r["condition"]) for r in row.records}


def columns(rows: Sequence[Row], where: str = "results manifest") -> list[Row]:
    """The table columns: each column's test rows as one Row (records pooled, in manifest order). A column is one
    agent: its rows are of one model family, and a cell (task, condition) comes from one run, or from one run per
    training seed where the column's rows name their `training_seed` (all of them, then; the column's training
    seeds are how many it names)."""
    groups: dict[str, list[Row]] = {}
    for row in rows:
        if row.column:
            groups.setdefault(row.column, []).append(row)
    out = []
    for name, group in groups.items():
        first = group[0]
        seeded = [r.training_seed is not None for r in group]
        if any(seeded) and not all(seeded):
            raise _bad(where, f"column {name!r}: some of its rows name a training_seed and some do not; name it on all")
        seen: dict[tuple[str, str, int | None], str] = {}
        for row in group:
            if (row.model, row.training_seeds) != (first.model, first.training_seeds):
                raise _bad(where, f"column {name!r}: row {row.label!r} is {row.model} with {row.training_seeds} "
                                  f"training seed(s), the column's first row {first.model} with {first.training_seeds}")
            for task, cond in sorted(_cells(row)):
                other = seen.setdefault((task, cond, row.training_seed), row.label)
                if other != row.label:
                    seed = "" if row.training_seed is None else f" with training seed {row.training_seed}"
                    raise _bad(where, f"column {name!r}: rows {other!r} and {row.label!r} both drive {task} in {cond}"
                                      f"{seed}; one run per cell (and training seed)")
        seeds = len({r.training_seed for r in group}) if all(seeded) else first.training_seeds
        out.append(Row(name, first.model, seeds, "test", "; ".join(r.command for r in group), first.folder,
                       tuple(rec for r in group for rec in r.records), column=name))
    return out


def seed_spread(rows: Sequence[Row]) -> list[str]:
    """Per column and cell with several training seeds: each seed's successes and the mean ± population std of
    their success rates (the spread a reader needs before trusting a difference between two recipes)."""
    lines = []
    for name in dict.fromkeys(r.column for r in rows if r.column and r.training_seed is not None):
        group = [r for r in rows if r.column == name]
        for cond in CONDITIONS:
            for task in TASKS:
                per = {r.training_seed: r.cell(task, cond) for r in group if r.cell(task, cond)[1]}
                if len(per) < 2:
                    continue
                spread = mean_std([100 * ok / n for ok, n in per.values()])
                each = ", ".join(f"seed {k}: {ok}/{n}" for k, (ok, n) in sorted(per.items()))
                lines.append(f"| {name} | {TASKS[task].title} | {CONDITIONS[cond].title} | {len(per)} | {each} | "
                             f"{spread.value:.1f} ± {spread.std:.1f} |")
    if not lines:
        return []
    return ["| column | task | condition | training seeds | successes per training seed | mean ± std (%) |",
            "|---|---|---|---|---|---|", *lines]


def _pct(ok: int, n: int) -> str:
    lo, hi = wilson_interval(ok, n)
    return f"{ok}/{n} = {100 * ok / n:.0f} % [{lo:.0f}-{hi:.0f}]"


def beside_paper(rows: Sequence[Row]) -> list[str]:
    """Our cells (x/n, %, Wilson interval) beside the paper's figure of the same model family."""
    lines = ["| row | task | condition | ours: successes = % [95 % Wilson] | paper |", "|---|---|---|---|---|"]
    for row in rows:
        for cond in ("training", "new-town-weather"):
            for task in TABLE_TASKS:
                ok, n = row.cell(task, cond)
                if n:
                    paper = paper_cell(task, cond, row.model) if row.model in PAPER_MODELS else "—"
                    lines.append(f"| {row.label} | {TASKS[task].title} | {CONDITIONS[cond].title} | {_pct(ok, n)} "
                                 f"| {paper} |")
    return lines


def shared_episodes(ra: Row, rb: Row, task: str, condition: str) -> tuple[tuple[int, int], tuple[int, int]]:
    """(successes, episodes) of each row in one cell, over the episodes (route, weather, benchmark seed) both
    drove, every training seed's copy kept: a difference over the same episodes, so a row that also drove more
    seeds of an easy task does not weigh that task more than the other row does."""
    a, b = ra.episodes(task, condition), rb.episodes(task, condition)
    both = {episode_key(r) for r in a} & {episode_key(r) for r in b}
    return _successes([r for r in a if episode_key(r) in both]), _successes([r for r in b if episode_key(r) in both])


def judge(claim: Claim, rows: Sequence[Row]) -> tuple[str, list[str]]:
    """(status, evidence lines) of a claim: held / not held / not established / not tested."""
    a_rows = [r for r in rows if r.model == claim.a]
    if claim.b is None:
        evidence, verdicts = [], []
        for row in a_rows:
            for task in claim.tasks:
                ok, n = row.cell(task, claim.condition)
                if not n:
                    continue
                level = TABLE_III[(task, claim.condition, claim.a)][0]
                _, hi = wilson_interval(ok, n)
                verdicts.append("held" if hi >= level else "not held")  # at or above the level, or within reach
                evidence.append(f"{row.label}: {_pct(ok, n)} against the paper's {level:g} "
                                f"({row.training_seeds} training seed{'s' * (row.training_seeds != 1)})")
        return _status(verdicts), evidence
    b_rows = [r for r in rows if r.model == claim.b]
    evidence, verdicts = [], []
    for ra in a_rows:
        for rb in b_rows:
            pairs = {t: shared_episodes(ra, rb, t, claim.condition) for t in claim.tasks}
            cells = [t for t, (a, _) in pairs.items() if a[1]]
            if not cells:
                continue
            a = tuple(map(sum, zip(*(pairs[t][0] for t in cells), strict=True)))
            b = tuple(map(sum, zip(*(pairs[t][1] for t in cells), strict=True)))
            d, lo, hi = difference_interval(a, b)  # type: ignore[arg-type]
            verdicts.append("held" if lo > 0 else "not held" if hi < 0 else "not established")
            evidence.append(f"{ra.label} {_pct(*a)} vs {rb.label} {_pct(*b)} on the episodes both drove in "
                            f"{', '.join(TASKS[t].title for t in cells)}: {d:+.0f} points [{lo:+.0f}, {hi:+.0f}]")
    return _status(verdicts), evidence


def _status(verdicts: Sequence[str]) -> str:
    if not verdicts:
        return "not tested"
    return verdicts[0] if len(set(verdicts)) == 1 else "mixed (" + ", ".join(verdicts) + ")"


def headline_block(rows: Sequence[Row], task: str = "dense", condition: str = "new-town-weather") -> str:
    """README's headline table: the paper's hardest cell, every column that drove it beside the paper's figure
    of its model family."""
    lines = [f"| agent | {TASKS[task].title}, {CONDITIONS[condition].title}: successes [95 % Wilson] | paper, "
             "same model family | training seeds |", "|---|---|---|---|"]
    for row in columns(rows):
        ok, n = row.cell(task, condition)
        if n:
            paper = paper_cell(task, condition, row.model) if row.model in PAPER_MODELS else "—"
            lines.append(f"| {row.label} | **{_pct(ok, n)}** | {paper} | {row.training_seeds or '—'} |")
    return "\n".join(lines) + "\n"


def render(rows: Sequence[Row], notes: str, manifest: str, attention: Mapping[str, Any] | None = None) -> str:
    """The whole page as Markdown."""
    from yawil.bench.report import ResultSet, success_table, violations_table

    cols = columns(rows)
    sets = [ResultSet(c.label, c.folder, list(c.records)) for c in cols]
    md = [TITLE, "",
          f"Made by `yawil results {manifest} --out docs/results.md` from the committed records it lists "
          "(docs/benchmark.md says how episodes are driven and judged); edit the manifest, not this page. A "
          "difference between two rows counts only when its 95 % interval excludes zero.", "",
          "## Rows", "", "| row | model | training seeds | role | column | episodes | records | command | note |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r.label} | {r.model} | {r.training_seeds or '—'} | {r.role} | {r.column or '—'} | {len(r.records)} | "
                  f"`{r.folder.parent.name}/{r.folder.name}` | `{r.command}` | {r.note} |")
    md += ["", "Role *test*: a cell run once per shipped model (New Town02 & Weather is the test of the training-"
           "town models); *selection*: training-town episodes that chose a recipe or checkpoint. *Column*: the agent "
           "whose column of Tables III and IV the row fills (—: an earlier model or drive, listed here and beside the "
           "paper only).", ""]
    if sets:
        md += ["## Table III and IV (the columns: one agent each)", "", success_table(sets, protocol=True).markdown(),
               violations_table(sets).markdown()]
        spread = seed_spread(rows)
        if spread:
            md += ["### Training-seed spread", "", *spread, "",
                   "A column with several training seeds pools their episodes in the tables above; here each "
                   "seed's model alone (success rate over its episodes), then mean ± population std over the seeds.", ""]
    md += ["## Beside the paper", "", *beside_paper(rows), "",
           "The paper's static tasks are the best of 5 evaluation seeds, its dynamic tasks mean ± std over 3; "
           "ours pool the cell's episodes.", "", "## The paper's claims", ""]
    for claim in CLAIMS:
        status, evidence = judge(claim, cols)
        md.append(f"- **{status}**: {claim.text}.")
        missing = "no column in these cells" if claim.b is None else "no columns of both families in these cells"
        md += [f"  - {e}" for e in evidence] or [f"  - {missing}"]
    if attention is not None and "by_class" in attention:
        md += ["", f"## The paper's heat-map claims: {attention['label']}", "",
               f"From `{attention['command']}` (docs/explain.md says what lift and prior mean; the frames are the "
               "expert's, the maps the model's on the same observations).", ""]
        for status, text, evidence in attention_claims(attention["by_class"]):
            md.append(f"- **{status}**: {text}.")
            md += [f"  - {e}" for e in evidence]
        if "faithfulness" in attention:
            md += ["", "Are the maps faithful (the deletion test, not a claim of the paper; top 5 % of a map's pixels "
                   "masked against 5 % in random blobs; 95 % bootstrap intervals over frames):", ""]
            md += [f"- {line}" for line in faithfulness_lines(attention["faithfulness"])]
    md += ["", "Claims of Tables I and II (yaw guidance against XY and commands on the square scene) are "
           "measured by `yawil experiment`, not by these rows (docs/experiments.md)."]
    if notes.strip():
        md += ["", "## Measured elsewhere", "", notes.strip()]
    return "\n".join(md) + "\n"


# The paper's attention claims, judged on `yawil explain --by-class` (lift = attention mass / pixel share; prior =
# the lift of the layer's mean map, where it looks anyway) with 95 % intervals over episodes.
DETAILS = ("vehicle", "pedestrian", "pole", "lights")
OBSTACLES = (("brake_vehicle", "vehicle"), ("brake_pedestrian", "pedestrian"), ("brake_light", "light_red"))


def _lift(doc: Mapping[str, Any], layer: int, situation: str, cls: str) -> tuple[float, float, float, float] | None:
    """(lift, lo, hi, prior) of a class for a layer (1-based) and situation, or None where it is absent."""
    name = doc["layers"][layer - 1]
    for row in doc["rows"]:
        if row["layer"] == name and row["situation"] == situation:
            lift, ci, prior = row["lift"].get(cls), (row.get("lift_ci95") or {}).get(cls), row["prior"].get(cls)
            if lift is None or ci is None or prior is None or None in ci:
                return None
            return float(lift), float(ci[0]), float(ci[1]), float(prior)
    return None


def _fmt(v: tuple[float, float, float, float]) -> str:
    return f"lift {v[0]:.2f} [{v[1]:.2f}-{v[2]:.2f}], prior {v[3]:.2f} (lift/prior {v[0] / v[3]:.2f})"


def attention_claims(doc: Mapping[str, Any]) -> list[tuple[str, str, list[str]]]:
    """(status, claim, evidence) of the paper's heat-map claims on a by-class table. Rules: a layer attends to a
    class when the interval of its lift lies above 1; it *follows* the class when the lift also exceeds the
    layer's prior (else the mass lands there because of where the layer always looks)."""
    out: list[tuple[str, str, list[str]]] = []
    for layer, cls, text in ((1, "passable", "Layer 1 attends to the passable area (road, lane markings, crossings)"),
                             (2, "lane_marking", "Layer 2 attends to lane lines")):
        v = _lift(doc, layer, "all", cls)
        status = "not tested" if v is None else "held" if v[1] > 1 else "not held" if v[2] < 1 else "not established"
        out.append((status, text, [] if v is None else [f"layer {layer}, {cls}, all frames: {_fmt(v)}"]))
    vs = {c: _lift(doc, 3, "all", c) for c in DETAILS}
    shown = {c: v for c, v in vs.items() if v is not None}
    held = bool(shown) and all(v[1] > 1 and v[0] > v[3] for v in shown.values())
    out.append(("held" if held else "not held" if shown else "not tested",
                "Layer 3 attends to details (each of vehicles, pedestrians, poles and lights above 1 and above the "
                "layer's prior)", [f"layer 3, {c}: {_fmt(v)}" for c, v in shown.items()]))
    evidence, verdicts = [], []
    for situation, cls in OBSTACLES:
        per_layer = [(i, _lift(doc, i, situation, cls)) for i in range(1, len(doc["layers"]) + 1)]
        found = [(i, v) for i, v in per_layer if v is not None]
        if not found:
            continue
        follows = [i for i, v in found if v[1] > 1 and v[0] > v[3]]
        verdicts.append("held" if follows else "not held")
        evidence += [f"{situation} ({cls}), layer {i}: {_fmt(v)}" for i, v in found]
    out.append((_status(verdicts), "When the car brakes, the maps attend to the obstacle (a layer's lift on the "
                "vehicle, pedestrian or red light above 1 and above its prior)", evidence))
    return out


def faithfulness_lines(doc: Mapping[str, Any], k: float = 5.0,
                       outputs: Sequence[str] = ("target_speed", "steer")) -> list[str]:
    """The deletion test's top/random ratios at `k` % (above 1: the output reads what the map points at)."""
    lines = []
    for r in doc["results"]:
        if r["k"] == k and r["output"] in outputs:
            lines.append(f"{r['map']}, {r['output']}: top/random {r['ratio']:.2f} [{r['ratio_lo']:.2f}-"
                         f"{r['ratio_hi']:.2f}] ({'faithful' if r['ratio_lo'] > 1 else 'not faithful' if r['ratio_hi'] < 1 else 'not established'})")
    return lines
