"""What a run starts from: the dataset splits (by episode) and their loaders, the network (with the
dataset's guidance width), and the check that a resumed run continues the same run."""

from __future__ import annotations

import sys
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from yawil.learn.config import RESUMABLE_CHANGES, TrainConfig
from yawil.policy.runtime import Runtime


def make_loader(dataset: Any, batches: list[list[int]], cfg: TrainConfig, runtime: Runtime) -> Any:
    from torch.utils.data import DataLoader

    return DataLoader(
        dataset,
        batch_sampler=batches,
        num_workers=cfg.workers,
        pin_memory=runtime.device.type == "cuda",
        generator=torch.Generator().manual_seed(cfg.seed),  # keeps the global RNG untouched
        persistent_workers=False,
        worker_init_fn=_ignore_stop_signals if cfg.workers else None,
    )


def _ignore_stop_signals(worker_id: int) -> None:
    """A loader worker leaves SIGTERM and SIGHUP to the main process: a scheduler's signal to the whole process
    group killed the workers mid-step, and torch's handler then raised in the main process before it could save
    (the main process stops after its step and ends the workers itself). Ctrl-C they already ignore."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)


def open_splits(cfg: TrainConfig) -> tuple[Any, Any, dict[str, Any]]:
    """Train and validation datasets (split by episode) and the guidance config they were written with."""
    from yawil import data

    if not cfg.data:
        raise ValueError("train config: data is empty; give at least one dataset root (--data DIR)")
    for root in cfg.data:
        if not Path(root).exists():
            raise FileNotFoundError(f"dataset root {root} does not exist")
    fraction = cfg.val_fraction
    n = len(data.split_episodes(cfg.data, 0.0, cfg.seed)[0])
    if fraction > 0 and n < 2:  # the smallest natural first run (`collect --frames 400`) must train
        print(f"warning: {n} episode in {', '.join(map(str, cfg.data))}: too few to hold one out, training without "
              "validation (best.pt is the last checkpoint); collect more episodes for a validation loss",
              file=sys.stderr)
        fraction = 0.0
    train_eps, val_eps = data.split_episodes(cfg.data, fraction, cfg.seed)
    with warnings.catch_warnings():  # a skipped file is refused below in one line, not warned about first
        warnings.simplefilter("ignore", RuntimeWarning)
        train_ds = data.DrivingDataset(cfg.data, episodes=train_eps)
        val_ds = data.DrivingDataset(cfg.data, episodes=val_eps)
    skipped = train_ds.skipped + val_ds.skipped
    if skipped:  # training on what is left would silently be another run (half the data, or no validation)
        path, why = skipped[0]
        raise ValueError(f"{len(skipped)} episode file(s) listed in the manifest cannot be read, the first {path}: "
                         f"{why}; repair the dataset (yawil data check names them; a resumed yawil collect "
                         "re-collects them) before training")
    return train_ds, val_ds, dataset_guidance_config(train_ds)


def dataset_guidance_config(dataset: Any) -> dict[str, Any]:
    gc = dataset.guidance_config
    return dict(gc.to_dict() if hasattr(gc, "to_dict") else gc)


def build_model(cfg: TrainConfig, guidance_dims: Mapping[str, int]) -> Any:
    """Create the network; a guided model gets the guidance width of the dataset unless told otherwise."""
    from yawil import models

    args = dict(cfg.model_args)
    model = models.create(cfg.model, seed=cfg.seed, **args)
    kind = model.guidance
    if kind is not None and "guidance_dim" not in args and model.guidance_dim != guidance_dims[kind]:
        model = models.create(cfg.model, seed=cfg.seed, guidance_dim=guidance_dims[kind], **args)
    if kind is not None and model.guidance_dim != guidance_dims[kind]:
        raise ValueError(
            f"model_args.guidance_dim={model.guidance_dim} but the dataset's {kind} guidance has {guidance_dims[kind]} values"
        )
    if cfg.pretrained is not None:
        if not Path(cfg.pretrained).is_file():
            raise FileNotFoundError(f"pretrained weights {cfg.pretrained} do not exist")
        model.load_pretrained(cfg.pretrained)
    return model


def check_resumable(saved: Mapping[str, Any], cfg: TrainConfig, path: Path) -> None:
    """Refuse a resume whose settings differ from the run's. A setting the run's checkpoint does not name is
    newer than the run, which trained with that setting's default (e.g. `reason_fractions`, `aux_loss`)."""
    now = cfg.to_dict()
    defaults = TrainConfig().to_dict()
    for key, value in now.items():
        if key in RESUMABLE_CHANGES or key == "out":
            continue
        was = saved[key] if key in saved else defaults.get(key)
        if was != value:
            raise ValueError(
                f"cannot resume {path}: setting {key!r} was {was!r}, now {value!r} "
                f"(only {sorted(RESUMABLE_CHANGES)} may change on resume)"
            )


def check_budget(ckpt: Mapping[str, Any], cfg: TrainConfig, out: Path) -> None:
    """Refuse a resume whose step budget is already spent past: it would train nothing, yet rewrite the run's
    config.yaml with the smaller budget and exit 0. A budget equal to the step is a finished run (a pipeline
    resumes it and gets it back unchanged)."""
    step = int(ckpt.get("position", {}).get("step", ckpt.get("step", 0)))
    if cfg.max_steps is not None and cfg.max_steps < step:
        raise ValueError(f"--max-steps {cfg.max_steps}: the run at {out} is already at step {step}; give more steps")


def check_model_fits(cfg: TrainConfig) -> None:
    """What the settings ask of the model, checked from its options before the run folder is made (the first
    step found it, after config.yaml, tb/ and the lock were written)."""
    from yawil import models

    if cfg.aux_weight > 0 and not models.registry.has_aux_head(cfg.model, **cfg.model_args):
        raise ValueError(f"aux_weight={cfg.aux_weight} but model {cfg.model} has no aux head (--model-arg aux=true)")
    if cfg.stop_label_reasons() and not cfg.model_args.get("lead_stop", False):
        raise ValueError("stop_reasons (or stop_pedestrians) label the lead-stop output: build the model with "
                         "--model-arg lead_stop=true")
