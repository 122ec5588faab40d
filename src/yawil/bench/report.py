"""Tables shaped as the paper's (III: success rate; IV: lane and light violations) and plots, in Markdown and
in one self-contained HTML page (images embedded as base64 PNG), and the same figures as numbers in
summary.json.

Each results folder is one column (one agent). Cells follow the protocol: static tasks are the best of their
seeds, dynamic tasks mean +- std over seeds; violations count successful episodes only (yawil.bench.metrics).
Every output says what made it: the yawil version, the git commit, the command line and the date (UTC).
"""

from __future__ import annotations

import base64
import functools
import io
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from yawil.bench.metrics import (
    FAILURE_REASONS,
    Stat,
    failure_counts,
    task_success,
    task_violations,
    wilson_interval,
)
from yawil.bench.records import RUN_FILE, iter_results
from yawil.bench.suites import CONDITIONS, TASKS
from yawil.fileio import write_atomic
from yawil.provenance import provenance, provenance_markdown


@dataclass
class ResultSet:
    """The records of one results folder, labelled for the table columns."""

    label: str
    folder: Path
    records: list[dict[str, Any]]

    def select(self, task: str, condition: str) -> list[dict[str, Any]]:
        return [r for r in self.records if r["task"] == task and r["condition"] == condition]


def load_results(folder: str | Path) -> ResultSet:
    folder = Path(folder)
    records = list(iter_results(folder))
    label = folder.name
    info = folder / RUN_FILE
    if info.exists():
        try:
            label = str(json.loads(info.read_text(encoding="utf-8")).get("label") or label)
        except ValueError as err:
            raise ValueError(f"{info}: not valid JSON ({err})") from None
    return ResultSet(label, folder, records)


def _unique_labels(sets: Sequence[ResultSet]) -> None:
    seen: dict[str, int] = {}
    for rs in sets:
        n = seen.get(rs.label, 0)
        seen[rs.label] = n + 1
        if n:
            rs.label = f"{rs.label} ({n + 1})"


def _present(sets: Sequence[ResultSet]) -> tuple[list[str], list[str]]:
    """Conditions and tasks that have at least one record, in the order of CONDITIONS and TASKS (the paper's first)."""
    conds = [c for c in CONDITIONS if any(r["condition"] == c for rs in sets for r in rs.records)]
    tasks = [t for t in TASKS if any(r["task"] == t for rs in sets for r in rs.records)]
    return conds, tasks


@dataclass
class Table:
    """A table as formatted text (`rows`, for Markdown and HTML) and as numbers (`records`, for summary.json)."""

    title: str
    header: list[str]
    rows: list[list[str]]
    note: str = ""
    key: str = ""  # its name in summary.json
    records: list[dict[str, Any]] = field(default_factory=list)

    def markdown(self) -> str:
        def line(cells: Sequence[str]) -> str:
            return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

        lines = [f"### {self.title}", "", line(self.header), "|" + "---|" * len(self.header)]
        lines += [line(r) for r in self.rows]
        if self.note:
            lines += ["", self.note]
        return "\n".join(lines) + "\n"

    def summary(self) -> dict[str, Any]:
        return {"title": self.title, "note": self.note, "rows": self.records}


def _num(v: float | None) -> float | None:
    """JSON has no NaN: an undefined figure is null."""
    return None if v is None or math.isnan(v) else float(v)


def _stat(st: Stat) -> dict[str, Any]:
    return {"value": _num(st.value), "std": _num(st.std), "n_seeds": st.n_seeds,
            "per_seed": [_num(v) for v in st.per_seed]}


def _columns(sets: Sequence[ResultSet], conds: Sequence[str]) -> list[tuple[str, ResultSet]]:
    return [(c, rs) for c in conds for rs in sets]


def _header(first: Sequence[str], cols: Sequence[tuple[str, ResultSet]]) -> list[str]:
    return [*first, *(f"{CONDITIONS[c].title}: {rs.label}" for c, rs in cols)]


def short_seeds(recs: Sequence[Mapping[str, Any]]) -> list[str]:
    """The evaluation seeds of one cell (one task, one condition) that hold fewer episodes than the protocol drives
    per seed (every route in every weather of the condition), as "seed S: N of M": a run stopped part-way pools
    into a cell whose figure would otherwise read as the protocol's."""
    first = recs[0]
    try:
        full = _protocol_episodes(first["suite"], first["condition"], first["task"])
    except (KeyError, ValueError):
        return []  # a suite or task this checkout does not know: nothing to compare with
    per: dict[tuple[str, int], int] = {}  # by model too: a column may pool several training seeds' runs
    for r in recs:
        key = (str(r.get("agent", "")), int(r["seed"]))
        per[key] = per.get(key, 0) + 1
    agents, seeds = {a for a, _ in per}, {s for _, s in per}
    for a in agents:  # a seed the other models of the column drove and this one did not
        for s in seeds:
            per.setdefault((a, s), 0)
    several = len(agents) > 1
    return [f"seed {s}{' of ' + _run_name(a) if several else ''}: {n} of {full}"
            for (a, s), n in sorted(per.items()) if n < full]


@functools.cache
def _protocol_episodes(suite: str, condition: str, task: str) -> int:
    """Episodes the protocol drives per seed in one cell (read from the town's route file once per cell kind)."""
    from yawil.bench.suites import episodes

    return len(episodes(suite, [condition], [task], seeds=1))


def _run_name(agent: str) -> str:
    """A record's agent as a short name: a zoo model's name, or the run folder of a DAgger or training checkpoint
    (RUN/train/round_03/last.pt, RUN/last.pt)."""
    if agent.startswith("zoo:"):
        return agent[4:]
    parts = Path(agent).parts
    if len(parts) >= 4 and parts[-3] == "train":
        return parts[-4]
    return parts[-2] if len(parts) >= 2 else agent


def success_table(sets: Sequence[ResultSet], protocol: bool = False) -> Table:
    """Table III: success rate (%) per task and condition, one column per agent. `protocol`: the columns are
    protocol runs (docs/results.md), so a seed with fewer episodes than the protocol's is named in its cell."""
    conds, tasks = _present(sets)
    cols = _columns(sets, conds)
    rows = []
    records: list[dict[str, Any]] = []
    for t in tasks:
        task = TASKS[t]
        row = [task.title]
        for c, rs in cols:
            recs = rs.select(t, c)
            if not recs:
                row.append("—")
                continue
            stat = task_success(recs, task.dynamic)
            extra = "" if stat.n_seeds == task.default_seeds else f" ({stat.n_seeds} seed{'s' * (stat.n_seeds > 1)})"
            short = short_seeds(recs) if protocol else []
            extra += f" (short: {'; '.join(short)})" if short else ""
            ok = sum(bool(r["success"]) for r in recs)
            lo, hi = wilson_interval(ok, len(recs))
            row.append(f"{stat.format(2)} [{lo:.0f}-{hi:.0f}]{extra}")
            records.append({"task": t, "condition": c, "agent": rs.label,
                            "over_seeds": "mean" if task.dynamic else "best", "success_pct": _stat(stat),
                            "episodes": len(recs), "successes": ok, "wilson95_pct": [round(lo, 2), round(hi, 2)]})
        rows.append(row)
    note = (
        "Success rate in %. Static tasks: best of 5 seeds; dynamic tasks: mean ± population std over 3 seeds; "
        "a cell with another number of seeds says so (one seed: no ±). [lo-hi]: the 95 % Wilson interval of the "
        "success rate over all the cell's episodes, seeds pooled. —: not run."
        + (" short: a seed of the cell with fewer episodes than the protocol drives (a run stopped part-way)."
           if protocol else "")
    )
    return Table("Table III: navigation success rate (%)", _header(["Task"], cols), rows, note, "success", records)


def violations_table(sets: Sequence[ResultSet]) -> Table:
    """Table IV: lane violations per km and traffic-light violation ratio, successful episodes only."""
    conds, tasks = _present(sets)
    cols = _columns(sets, conds)
    rows = []
    for metric in ("Lane violations (per km)", "Traffic-light violations (red / passed)"):
        for t in tasks:
            row = [metric, TASKS[t].title]
            for c, rs in cols:
                recs = rs.select(t, c)
                if not recs:
                    row.append("—")
                    continue
                lanes, lights = task_violations(recs)
                row.append((lanes if metric.startswith("Lane") else lights).format(2))
            rows.append(row)
    records: list[dict[str, Any]] = []
    for t in tasks:
        for c, rs in cols:
            recs = rs.select(t, c)
            if recs:
                lanes, lights = task_violations(recs)
                records.append({"task": t, "condition": c, "agent": rs.label,
                                "lane_violations_per_km": _stat(lanes), "red_light_ratio": _stat(lights)})
    note = (
        "Successful episodes only, pooled per seed (entries into the opposite lane or off the road / km driven; "
        "red lights crossed / signalised stop lines passed), then mean ± population std over seeds; "
        "n/a: no successful episode (or no light passed)."
    )
    return Table("Table IV: lane and traffic-light violations", _header(["Metric", "Task"], cols), rows, note,
                 "violations", records)


def outcome_table(sets: Sequence[ResultSet]) -> Table:
    """How the episodes ended, all seeds together: the failure reasons behind Table III."""
    conds, tasks = _present(sets)
    rows = []
    records: list[dict[str, Any]] = []
    for c in conds:
        for t in tasks:
            for rs in sets:
                recs = rs.select(t, c)
                if not recs:
                    continue
                counts = failure_counts(recs)
                km = sum(float(r["km_driven"]) for r in recs)
                rows.append(
                    [CONDITIONS[c].title, TASKS[t].title, rs.label, str(len(recs)), str(counts["success"])]
                    + [str(counts.get(k, 0)) for k in FAILURE_REASONS]
                    + [str(counts["rear_end"]), f"{km:.1f}"]
                )
                records.append({"condition": c, "task": t, "agent": rs.label, "episodes": len(recs),
                                "success": counts["success"], "failures": _failures(counts),
                                "rear_end": counts["rear_end"], "km_driven": km})
    header = ["Condition", "Task", "Agent", "Episodes", "Success", *FAILURE_REASONS, "of which rear-end", "km driven"]
    return Table("Episode outcomes (all seeds)", header, rows, key="outcomes", records=records)


def _failures(counts: Mapping[str, int]) -> dict[str, int]:
    """Episodes per failure reason, every reason named (0 where none), in FAILURE_REASONS' order."""
    return {k: counts.get(k, 0) for k in FAILURE_REASONS}


def weather_table(sets: Sequence[ResultSet]) -> Table:
    """Successes and failure reasons per condition and weather, every task and seed together.

    Why: a learned agent's failures can gather in one light (the sunset weathers' dark, orange roads) while
    Table III, per task, spreads them out; the protocol drives every route in every weather, so each weather
    of a condition holds the same routes and the rows compare like with like.
    """
    conds, _ = _present(sets)
    rows = []
    records: list[dict[str, Any]] = []
    for c in conds:
        order = CONDITIONS[c].weathers
        driven = {r["weather"] for rs in sets for r in rs.records if r["condition"] == c}
        for w in sorted(driven, key=lambda w: (order.index(w) if w in order else len(order), w)):
            for rs in sets:
                recs = [r for r in rs.records if r["condition"] == c and r["weather"] == w]
                if not recs:
                    continue
                counts = failure_counts(recs)
                failures = _failures(counts)
                rows.append([CONDITIONS[c].title, w, rs.label, str(len(recs)), str(counts["success"]),
                             f"{100.0 * counts['success'] / len(recs):.1f}", *map(str, failures.values())])
                records.append({"condition": c, "weather": w, "agent": rs.label, "episodes": len(recs),
                                "success": counts["success"], "failures": failures})
    header = ["Condition", "Weather", "Agent", "Episodes", "Success", "Success %", *FAILURE_REASONS]
    return Table("Episode outcomes per weather (all tasks and seeds)", header, rows, key="weathers", records=records)


def summary_table(sets: Sequence[ResultSet]) -> Table:
    """One row per agent over all its episodes: the figures a recipe comparison needs (docs/experiments.md)."""
    from yawil.bench.metrics import lane_violations_per_km, light_violation_ratio

    rows = []
    records: list[dict[str, Any]] = []
    for rs in sets:
        if not rs.records:
            continue
        counts = failure_counts(rs.records)
        lanes, lights = lane_violations_per_km(rs.records), light_violation_ratio(rs.records)
        rows.append(
            [rs.label, str(len(rs.records)), str(counts["success"])]
            + [str(counts.get(k, 0)) for k in FAILURE_REASONS]
            + [str(counts["rear_end"]), f"{lanes:.2f}", f"{lights:.2f}"]
        )
        records.append({"agent": rs.label, "episodes": len(rs.records), "success": counts["success"],
                        "failures": _failures(counts), "rear_end": counts["rear_end"],
                        "lane_violations_per_km": _num(lanes), "red_light_ratio": _num(lights)})
    header = ["Agent", "Episodes", "Success", *FAILURE_REASONS, "of which rear-end",
              "lane violations / km (successful)", "red-light ratio (successful)"]
    return Table("Summary over all episodes", header, rows,
                 "Violations pooled over the successful episodes of every task and condition.", "summary", records)


# ----- plots -------------------------------------------------------------------------------------------------


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


def success_plot(sets: Sequence[ResultSet]) -> bytes:
    """Bars of success rate per task, one panel per condition, one bar per agent (error bars: dynamic std)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    conds, tasks = _present(sets)
    fig, axes = plt.subplots(1, max(1, len(conds)), figsize=(5.5 * max(1, len(conds)), 3.8), squeeze=False)
    width = 0.8 / max(1, len(sets))
    for ax, c in zip(axes[0], conds, strict=False):
        x = np.arange(len(tasks))
        for i, rs in enumerate(sets):
            vals, errs = [], []
            for t in tasks:
                recs = rs.select(t, c)
                if recs:
                    st = task_success(recs, TASKS[t].dynamic)
                    vals.append(st.value)
                    errs.append(st.std if st.std is not None and st.n_seeds > 1 else 0.0)
                else:  # not run: no bar (a 0 % bar would read as a result), a mark instead
                    vals.append(math.nan)
                    errs.append(0.0)
            xs = x + (i - (len(sets) - 1) / 2) * width
            ax.bar(xs, np.nan_to_num(vals), width, yerr=errs, capsize=3, label=rs.label)
            for xi, v in zip(xs, vals, strict=True):
                if math.isnan(v):
                    ax.text(xi, 2, "not run", rotation=90, ha="center", va="bottom", fontsize=6, color="0.4")
        ax.set_xticks(x, [TASKS[t].title for t in tasks], rotation=20, ha="right", fontsize=8)
        ax.set_ylim(0, 105)
        ax.set_ylabel("success rate (%)")
        ax.set_title(CONDITIONS[c].title)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


# The default episode of the trajectory plot: route 0, seed 0 of the hardest task that was run.
HARDEST_FIRST: tuple[str, ...] = ("nocrash_dense", "dense_matched", "dense", "nocrash_regular", "regular", "nav_dynamic",
                                  "navigation", "empty", "one_turn", "straight", "square")


def choose_episodes(sets: Sequence[ResultSet], condition: str,
                    spec: str | None) -> tuple[str, str | None, int, int] | None:
    """(task, weather, route id, seed) to draw: `spec` as 'task/route/seed' (the condition's first weather
    driven) or 'task/weather/route/seed', else the first weather, route and seed of the hardest task run."""
    if spec:
        parts = spec.split("/")
        if len(parts) not in (3, 4):
            raise ValueError(f"--trajectory {spec!r}: expected task/route/seed or task/weather/route/seed, "
                             "e.g. dense/3/0 or dense/WetCloudyNoon/3/0")
        try:
            rid, seed = int(parts[-2]), int(parts[-1])
        except ValueError:
            raise ValueError(f"--trajectory {spec!r}: route and seed must be integers") from None
        return parts[0], (parts[1] if len(parts) == 4 else None), rid, seed
    for t in HARDEST_FIRST:
        for rs in sets:
            hits = sorted((r["route_id"], r["seed"]) for r in rs.select(t, condition) if r.get("trajectory"))
            if hits:
                return t, None, hits[0][0], hits[0][1]
    return None


def episode_records(sets: Sequence[ResultSet], condition: str,
                    chosen: tuple[str, str | None, int, int]) -> tuple[list[tuple[str, dict[str, Any]]], str | None]:
    """(column label, record) of every set's records of the `choose_episodes` episode that hold a trajectory, in
    one weather (the chosen one, else the condition's first that was driven), and that weather."""
    task, weather, rid, seed = chosen
    recs = [
        (rs.label, r)
        for rs in sets
        for r in rs.select(task, condition)
        if r["route_id"] == rid and r["seed"] == seed and r.get("trajectory")
    ]
    if weather is None and recs:  # one weather: the condition's first that was driven
        order = CONDITIONS[condition].weathers
        weather = min((r["weather"] for _, r in recs), key=lambda w: order.index(w) if w in order else len(order))
    return [(label, r) for label, r in recs if r["weather"] == weather], weather


def check_trajectories(sets: Sequence[ResultSet], trajectories: Mapping[str, str]) -> None:
    """Refuse, in one line before anything is written, a --trajectory episode the results do not hold (its plot
    was silently left out of the report)."""
    for condition, spec in trajectories.items():
        chosen = choose_episodes(sets, condition, spec)
        if chosen is not None and episode_records(sets, condition, chosen)[0]:
            continue
        have = sorted({f"{r['task']}/{r['weather']}/{r['route_id']}/{r['seed']}" for rs in sets for r in rs.records
                       if r["condition"] == condition and r.get("trajectory")})
        some = f"e.g. {condition}={have[0]}" if have else f"none of condition {condition} holds a trajectory"
        raise ValueError(f"--trajectory {condition}={spec}: no such episode with a trajectory in the results; the "
                         "keys are TASK/[WEATHER/]ROUTE/SEED of the records in each results folder's episodes.jsonl "
                         f"({some})")


def trajectory_plot(sets: Sequence[ResultSet], condition: str, spec: str | None = None) -> bytes | None:
    """The driven paths of every agent on one episode over the bird's-eye map (as the paper's Figure 6)."""
    import matplotlib

    matplotlib.use("Agg")

    chosen = choose_episodes(sets, condition, spec)
    if chosen is None:
        return None
    task, _, rid, seed = chosen
    recs, weather = episode_records(sets, condition, chosen)
    if not recs:
        return None
    town = CONDITIONS[condition].town
    fig = _map_figure(town)
    ax = fig.axes[0]
    route = recs[0][1].get("route_xy") or []
    if route:
        xs, ys = zip(*route, strict=True)
        ax.plot(xs, ys, color="0.5", lw=4, alpha=0.6, label="planned route", zorder=5)
        ax.plot([xs[0]], [ys[0]], "o", color="green", ms=8, zorder=7)
        ax.plot([xs[-1]], [ys[-1]], "*", color="gold", ms=14, mec="k", zorder=7)
    for label, r in recs:
        xs, ys = zip(*r["trajectory"], strict=True)
        ok = "success" if r["success"] else r.get("reason")
        ax.plot(xs, ys, lw=1.8, label=f"{label} ({ok})", zorder=6)
    ax.set_title(f"{CONDITIONS[condition].title}: {TASKS[task].title}, route {rid}, {weather}, seed {seed}",
                 fontsize=9)
    ax.legend(fontsize=7, loc="best")
    return _png(fig)


def _map_figure(town: str) -> Any:
    from yawil.bench.plotting import map_figure

    return map_figure(town)


# ----- writing -----------------------------------------------------------------------------------------------

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>yawil benchmark report</title>
<style>
body { font-family: sans-serif; max-width: 1200px; margin: 2em auto; }
table { border-collapse: collapse; margin: 1em 0; }
td, th { border: 1px solid #bbb; padding: 3px 8px; text-align: center; font-size: 13px; }
th { background: #eee; }
.note, .provenance { font-size: 12px; color: #555; }
img { max-width: 100%; }
</style>
</head>
<body>
<h1>Benchmark report</h1>
<p class="provenance">Made by yawil {{ prov.yawil_version }} (commit <code>{{ prov.git_commit }}</code>)
on {{ date }} UTC with <code>{{ prov.command }}</code>.</p>
<p>Results: {% for rs in sets %}{{ rs.label }} = <code>{{ rs.folder }}</code> ({{ rs.records | length }} episodes)
{%- if not loop.last %}, {% endif %}{% endfor %}.</p>
{% for t in tables %}
<h3>{{ t.title }}</h3>
<table>
<thead><tr>{% for h in t.header %}<th>{{ h }}</th>{% endfor %}</tr></thead>
<tbody>
{% for row in t.rows %}<tr>{% for c in row %}<td>{{ c }}</td>{% endfor %}</tr>
{% endfor %}</tbody>
</table>
{% if t.note %}<p class="note">{{ t.note }}</p>{% endif %}
{% endfor %}
{% for img in images %}
<h3>{{ img.title }}</h3>
<img alt="{{ img.title }}" src="data:image/png;base64,{{ img.b64 }}">
{% endfor %}
</body>
</html>
"""


def render_html(sets: Sequence[ResultSet], tables: Sequence[Table], images: Sequence[tuple[str, str, bytes]],
                prov: Mapping[str, str]) -> str:
    """The self-contained page: Jinja2 with autoescaping, images inline as base64 PNG."""
    import jinja2

    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, keep_trailing_newline=True)
    pictures = [{"title": title, "b64": base64.b64encode(data).decode("ascii")} for _, title, data in images]
    return env.from_string(_PAGE).render(
        sets=sets, tables=tables, images=pictures, prov=prov, date=prov["date_utc"].replace("T", " ").rstrip("Z")
    )


def write_report(
    folders: Sequence[str | Path],
    out: str | Path,
    trajectories: Mapping[str, str] | None = None,
    command: str | None = None,
) -> dict[str, Path]:
    """Write report.md, report.html, the PNG plots and summary.json into `out`; returns their paths.

    `command` is the command line the reports name as their maker (default: this process's).
    """
    seen: dict[Path, str] = {}
    for f in folders:  # `R` and `R/` were two identical columns
        key = Path(f).resolve()
        if key in seen:
            raise ValueError(f"results folder {f} is given twice (also as {seen[key]})")
        seen[key] = str(f)
    sets = [load_results(f) for f in folders]
    if not sets:
        raise ValueError("report needs at least one results folder")
    for rs in sets:
        if not rs.records:
            raise ValueError(f"{rs.folder}: no episode records yet")
    _unique_labels(sets)
    check_trajectories(sets, trajectories or {})
    prov = provenance(command)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tables = [success_table(sets), violations_table(sets), outcome_table(sets), weather_table(sets), summary_table(sets)]
    images: list[tuple[str, str, bytes]] = [("success.png", "Success rate per task", success_plot(sets))]
    conds, _ = _present(sets)
    for c in conds:
        png = trajectory_plot(sets, c, (trajectories or {}).get(c))
        if png is not None:
            images.append((f"trajectories_{c}.png", f"Trajectories, {CONDITIONS[c].title}", png))
    paths: dict[str, Path] = {}
    for name, _title, data in images:
        paths[name] = write_atomic(out / name, data)
    sources = ", ".join(f"{rs.label} = `{rs.folder}` ({len(rs.records)} episodes)" for rs in sets)
    md = ["# Benchmark report", "", provenance_markdown(prov), "", f"Results: {sources}.", ""]
    md += [t.markdown() for t in tables]
    md += [f"![{title}]({name})\n" for name, title, _ in images]
    paths["report.md"] = write_atomic(out / "report.md", "\n".join(md))
    paths["report.html"] = write_atomic(out / "report.html", render_html(sets, tables, images, prov))
    summary = {
        "provenance": prov,
        "results": [{"agent": rs.label, "folder": str(rs.folder), "episodes": len(rs.records)} for rs in sets],
        **{t.key: t.summary() for t in tables},
        "plots": [name for name, _, _ in images],
    }
    text = json.dumps(summary, indent=2, allow_nan=False, ensure_ascii=False) + "\n"
    paths["summary.json"] = write_atomic(out / "summary.json", text)
    return paths
