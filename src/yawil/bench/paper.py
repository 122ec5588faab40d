"""The paper's published figures (Tables III and IV), to print beside ours; nothing here is measured by yawil.

Keys: (task, condition, model) with yawil's task and condition names (`yawil.bench.suites`) and the model
names of the registry, `yilratt-pretrained` for the paper's "YILRatt (pretrained)" column. Static tasks are
the best of 5 seeds, dynamic tasks mean ± std over 3 (the paper's protocol); std is None where it gives none.
"""

from __future__ import annotations

PAPER_MODELS: tuple[str, ...] = ("cil", "cilrs", "yilratt", "yilratt-pretrained")

_Cell = float | tuple[float, float]  # a best-of-5 static figure, or a dynamic (mean, std)
_T3: dict[str, tuple[tuple[_Cell, ...], tuple[_Cell, ...]]] = {  # task: (training: CIL, CILRS, YILRatt,
    # pretrained), (new-town-weather: the same four)
    "straight": ((97, 98, 99, 97), (100, 100, 100, 100)),
    "one_turn": ((95, 100, 99, 100), (100, 94, 100, 100)),
    "navigation": ((41, 50, 92, 86), (64, 44, 88, 94)),
    "regular": (((67.33, 4.92), (48.0, 16.27), (92.33, 2.05), (92.0, 2.16)),
                ((46.67, 1.89), (35.33, 6.18), (76.66, 0.94), (87.33, 6.80))),
    "dense": (((55.33, 2.49), (66.67, 0.94), (88.67, 1.70), (93.67, 2.62)),
              ((25.33, 5.00), (34.0, 4.32), (76.0, 3.27), (82.67, 0.94))),
}


def _cells() -> dict[tuple[str, str, str], tuple[float, float | None]]:
    out: dict[tuple[str, str, str], tuple[float, float | None]] = {}
    for task, by_cond in _T3.items():
        for cond, values in zip(("training", "new-town-weather"), by_cond, strict=True):
            for model, v in zip(PAPER_MODELS, values, strict=True):
                out[(task, cond, model)] = (v[0], v[1]) if isinstance(v, tuple) else (float(v), None)
    return out


TABLE_III: dict[tuple[str, str, str], tuple[float, float | None]] = _cells()  # success %, (mean, std)

# Table IV, New Town02 & Weather only: (task, model) -> (lane violations per km, red-light ratio), each (mean, std)
TABLE_IV: dict[tuple[str, str], tuple[tuple[float, float], tuple[float, float]]] = {
    ("regular", "cil"): ((4.70, 0.22), (0.50, 0.03)),
    ("regular", "cilrs"): ((4.65, 0.30), (0.52, 0.08)),
    ("regular", "yilratt"): ((3.23, 0.36), (0.31, 0.04)),
    ("regular", "yilratt-pretrained"): ((2.91, 0.93), (0.36, 0.04)),
    ("dense", "cil"): ((4.53, 0.54), (0.63, 0.27)),
    ("dense", "cilrs"): ((4.42, 0.39), (0.35, 0.14)),
    ("dense", "yilratt"): ((3.38, 0.04), (0.34, 0.07)),
    ("dense", "yilratt-pretrained"): ((1.94, 0.01), (0.35, 0.10)),
}


def paper_cell(task: str, condition: str, model: str) -> str:
    """The paper's Table III figure as printed ('76.0 ± 3.27'), or '—' where it has none."""
    v = TABLE_III.get((task, condition, model))
    if v is None:
        return "—"
    return f"{v[0]:g}" if v[1] is None else f"{v[0]:g} ± {v[1]:g}"
