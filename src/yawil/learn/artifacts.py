"""The files of a run folder besides the checkpoints: metrics.csv, loss.png, and best.pt as a link."""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from yawil.fileio import write_atomic
from yawil.learn.validate import METRIC_FIELDS


def link_or_copy(src: Path, dst: Path) -> None:
    """Make `dst` the same file as `src` atomically: a hard link (no copy; a later replace of `src` by
    rename leaves `dst` intact), or a copy where links are not supported."""
    import shutil

    dst.parent.mkdir(parents=True, exist_ok=True)  # as every atomic writer does
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def write_metrics(out: Path, metrics: Sequence[Mapping[str, float]]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(METRIC_FIELDS), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for row in metrics:
        w.writerow({k: f"{row.get(k, math.nan):.6g}" for k in METRIC_FIELDS})  # older rows lack newer columns
    write_atomic(out / "metrics.csv", buf.getvalue())


def plot_losses(out: Path, metrics: Sequence[Mapping[str, float]]) -> None:
    """loss.png: train and validation loss per epoch (log scale), written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    x = [m["epoch"] for m in metrics]
    ax.plot(x, [m["train_loss"] for m in metrics], marker="o", label="train")
    ax.plot(x, [m["val_loss"] for m in metrics], marker="o", label="validation")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    if metrics and min(min(m["train_loss"], m["val_loss"]) for m in metrics) > 0:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    write_atomic(out / "loss.png", buf.getvalue())
