"""`yawil train`: train a model on collected episodes with the paper's settings as defaults.

Settings come from, in order of precedence: the command line, `--config file.yaml`, the saved
`config.yaml` of the run when resuming, then the defaults of `yawil.learn.config.TrainConfig`.
Only argparse is imported here; torch comes in with `run`.

Under torchrun (`torchrun --nproc_per_node N -m yawil.cli train ...`) every rank runs this command; rank 0
validates, writes the run folder and prints (docs/training.md, "Training on several processes or GPUs").
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any


def _true_false(text: str) -> bool:
    """'true' / 'false' (a YAML-like 'yes' or '1' is refused, as in config files)."""
    if text not in ("true", "false"):
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")
    return text == "true"


# option -> (TrainConfig field, type, help). Every TrainConfig field has one (tests/learn/test_train.py checks).
_OPTIONS: tuple[tuple[str, str, Any, str], ...] = (
    ("--epochs", "epochs", int, "epochs (paper: 100)"),
    ("--batch-size", "batch_size", int, "mini-batch size (paper: 512)"),
    ("--lr", "lr", float, "initial learning rate of Adam (paper: 1e-3)"),
    ("--lr-step-epochs", "lr_step_epochs", int, "epochs between learning-rate decays (paper: 10)"),
    ("--lr-gamma", "lr_gamma", float, "learning-rate decay factor (paper: 0.5)"),
    ("--weight-decay", "weight_decay", float, "Adam weight decay (default 0)"),
    ("--alpha", "alpha", float, "weight of the action loss (paper: 1.0)"),
    ("--beta", "beta", float, "weight of the speed loss (paper: 0.1)"),
    ("--loss", "loss", str, "l1 (default) | mse | smooth_l1"),
    ("--val-fraction", "val_fraction", float, "share of episodes held out for validation (default 0.1; 0: none, best.pt = last.pt; a one-episode dataset trains without)"),
    ("--seed", "seed", int, "seed of the split, data order, augmentation and initial weights (default 0)"),
    ("--workers", "workers", int, "DataLoader worker processes (default 0: load in the main process)"),
    ("--threads", "threads", int, "torch CPU threads (default 0: the cores left after --workers)"),
    ("--device", "device", str, "auto (default) | cpu | cuda"),
    ("--precision", "precision", str, "auto (default: bf16 on CPUs with native bf16, fp16 on CUDA) | fp32 | bf16 | fp16"),
    ("--channels-last", "channels_last", str, "auto (default) | on | off"),
    ("--max-steps", "max_steps", int, "stop after this many optimiser steps in total, with a checkpoint"),
    ("--max-minutes", "max_minutes", float, "stop after this many minutes of this invocation, with a checkpoint"),
    ("--log-every", "log_every", int, "steps between TensorBoard points (default 10)"),
    ("--brake-fraction", "brake_fraction", float,
     "share of slowing-down frames (expert brake > 0.1 at over 1 m/s) per epoch, drawn with replacement "
     "(default: the data's own)"),
    ("--speed-dropout", "speed_dropout", float,
     "probability per training sample that the speed input is replaced by its mean (inertia; default 0)"),
    ("--aux-weight", "aux_weight", float,
     "weight of the aux loss on the expert's privileged labels (needs --model-arg aux=true; default 0)"),
    ("--stop-pedestrians", "stop_pedestrians", _true_false,
     "true: the lead-stop output also learns the expert's stops for pedestrians (default false)"),
    ("--stop-reasons", "stop_reasons", lambda t: [r.strip() for r in t.split(",") if r.strip()],
     "comma-separated expert reasons (vehicle, pedestrian, junction) whose stops the lead-stop output also learns"),
    ("--aux-loss", "aux_loss", str,
     "same (default: --loss) | l1 | mse | smooth_l1: criterion of the aux head's regression terms"),
    ("--brake-loss", "brake_loss", str,
     "same (default: the brake under --loss) | bce (binary cross-entropy of the brake output)"),
    ("--ema", "ema", float,
     "decay of a moving average of the weights that the checkpoints drive with, e.g. 0.995 (default 0: off)"),
    ("--init-from", "init_from", str, "start from the weights and normalisation of this yawil checkpoint (fine-tune)"),
    ("--keep-steps", "keep_steps", lambda t: _step_list(t),
     "comma-separated step counts whose checkpoints are kept as step_NNNNNN.pt (learning curves)"),
    ("--pretrained", "pretrained", str, "ImageNet ResNet34 state dict for the backbone ('YILRatt (pretrained)')"),
)


def _step_list(text: str) -> list[int]:
    """'375,750' -> [375, 750]; argparse turns the ValueError into a one-line usage error."""
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated step counts, e.g. 375,750, got {text!r}") from None


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "train",
        help="train a driving model (YILRatt, CIL, CILRS, guided baselines)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model", help="model name, one of those `yawil models` lists (default yilratt)")
    p.add_argument("--data", nargs="+", metavar="DIR", help="dataset root(s) written by `yawil collect`")
    p.add_argument("--out", help="run folder (default runs/train)")
    p.add_argument("--config", metavar="YAML", help="settings file; command-line options override it")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    p.add_argument(
        "--oversample", action="append", default=[], metavar="REASON=SHARE",
        help="give the frames where the expert's target speed is set by REASON (vehicle, red_light, pedestrian, ...; "
             "schema-2 data) this share of each epoch's draws, e.g. --oversample vehicle=0.2; repeatable",
    )  # fmt: skip
    p.add_argument(
        "--model-arg", action="append", default=[], metavar="KEY=VALUE",
        help="model option (value parsed as JSON, else a string), e.g. --model-arg dropout=0.3",
    )  # fmt: skip
    p.add_argument(
        "--augment", action="append", default=[], metavar="KEY=VALUE",
        help="augmentation option, e.g. --augment enabled=false --augment blur_p=0.5",
    )  # fmt: skip
    p.add_argument("--no-augment", action="store_true", help="switch augmentation off")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--data-on-device", action="store_true", default=None,
        help="read both splits once into tensors on the training device (uint8 images) and draw every batch there: "
             "no per-batch reads or host-to-device copies (for a GPU; refused when they do not fit)",
    )  # fmt: skip
    p.add_argument(
        "--dist-backend", choices=("gloo", "nccl"), default=None,
        help="under torchrun: the process-group backend (default: nccl on CUDA, gloo on the CPU)",
    )  # fmt: skip
    for flag, dest, typ, text in _OPTIONS:
        p.add_argument(flag, dest=dest, type=typ, default=None, help=text)
    return p


def _key_values(items: list[str], option: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ValueError(f"{option}: expected KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The settings given on the command line (and only those)."""
    over: dict[str, Any] = {}
    for name in ("model", "out"):
        if getattr(args, name, None) is not None:
            over[name] = getattr(args, name)
    if getattr(args, "data", None):
        over["data"] = list(args.data)
    for _, dest, _, _ in _OPTIONS:
        if getattr(args, dest, None) is not None:
            over[dest] = getattr(args, dest)
    if args.model_arg:
        over["model_args"] = _key_values(args.model_arg, "--model-arg")
    if getattr(args, "oversample", None):
        over["reason_fractions"] = _key_values(args.oversample, "--oversample")
    augment = _key_values(args.augment, "--augment")
    if args.no_augment:
        augment["enabled"] = False
    if augment:
        over["augment"] = augment
    if args.no_progress:
        over["progress"] = False
    if getattr(args, "data_on_device", None):
        over["data_on_device"] = True
    return over


def build_config(args: argparse.Namespace) -> Any:
    """TrainConfig from saved run config (on --resume), --config file and the command line."""
    from pathlib import Path

    import yaml

    from yawil.learn.config import TrainConfig, merge_settings

    over = overrides_from_args(args)
    base: dict[str, Any] = {}
    if args.resume:
        out = Path(over.get("out", TrainConfig().out))
        saved = out / "config.yaml"
        if not saved.is_file():
            raise FileNotFoundError(f"--resume: {saved} does not exist (is {out} a training run?)")
        base = yaml.safe_load(saved.read_text()) or {}
    if args.config:
        TrainConfig.from_yaml(args.config)  # validates the file on its own first, naming it in errors
        base = merge_settings(base, _file_settings(args.config), args.config)
    return TrainConfig.from_dict(merge_settings(base, over, "command line"), "command line")


def _file_settings(path: str) -> dict[str, Any]:
    from pathlib import Path

    import yaml

    return dict(yaml.safe_load(Path(path).read_text()) or {})


def run(args: argparse.Namespace) -> int:
    from yawil.learn.distributed import WorldSizeError
    from yawil.learn.loop import train

    rank = int(os.environ.get("RANK", "0") or 0) if int(os.environ.get("WORLD_SIZE", "1") or 1) > 1 else 0
    try:
        cfg = build_config(args)
        from yawil.fileio import check_not_inside_owned

        check_not_inside_owned(cfg.out, "--out")  # a run inside a dataset or another run mixes two products
        result = train(cfg, resume=bool(args.resume), dist_backend=getattr(args, "dist_backend", None))
    except (ValueError, FileNotFoundError, FileExistsError) as err:  # bad settings or data: no traceback
        if rank == 0:
            print(f"yawil train: {err}", file=sys.stderr)
        elif not isinstance(err, WorldSizeError):  # said alike by every rank: rank 0 says it
            print(f"yawil train (rank {rank}): {err}", file=sys.stderr)
        return 2
    if rank != 0:
        return 0
    last = result.metrics[-1] if result.metrics else None
    summary = f"val_loss {last['val_loss']:.4f}, best {result.best_val:.4f}" if last else "no epoch finished"
    print(
        f"{cfg.model}: {result.epochs_done}/{cfg.epochs} epochs, {result.steps} steps, {summary} "
        f"(stopped by {result.stopped_by}); checkpoints in {result.out}"
    )
    return 0
