"""Training loop of every registered model, with the paper's settings as defaults (docs/training.md).

    cfg = TrainConfig(model="yilratt", data=["data/town01"], out="runs/yilratt")
    result = train(cfg)                  # runs/yilratt/{best.pt,last.pt,config.yaml,metrics.csv,loss.png,tb/}
    result = train(cfg, resume=True)     # continues from runs/yilratt/last.pt, exactly

Determinism: the data order of epoch e is drawn from (seed, e) (a permutation, or draws with replacement
with `brake_fraction`), the augmentation of step s
uses a generator seeded from (seed, s), the model is built with `seed`, and the torch/numpy/python RNG
states are saved, so a stopped run resumed gives the weights an uninterrupted run would have.

Under `torchrun` (WORLD_SIZE > 1) the same loop runs on every rank with DistributedDataParallel, each rank
on its slice of every global batch; rank 0 validates and writes (yawil.learn.distributed, docs/training.md).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from yawil.fileio import write_atomic
from yawil.learn import distributed
from yawil.learn.artifacts import link_or_copy, plot_losses, write_metrics
from yawil.learn.augment import augment_batch
from yawil.learn.config import TrainConfig, auto_threads
from yawil.learn.distributed import Dist
from yawil.learn.ema import ema_state, make_ema, restore_ema
from yawil.learn.loss import compute_loss
from yawil.learn.resident import ResidentData, load_splits
from yawil.learn.sampling import (
    brake_weights,
    drop_speed,
    epoch_batches,
    label_arrays,
    label_columns,
    prepare_batch,
    reason_weights,
    sequential_batches,
    step_generator,
)
from yawil.learn.setup import (
    build_model,
    check_budget,
    check_model_fits,
    check_resumable,
    make_loader,
    open_splits,
)
from yawil.learn.state import Position, rng_states, seed_globals, set_rng_states
from yawil.learn.stop import STOP, StopRequested, check_stop, stop_between_steps, stopped
from yawil.learn.validate import VAL_KEYS, validate
from yawil.policy.checkpoint import Norm, cpu_state_dict, load_checkpoint, make_checkpoint, save_checkpoint
from yawil.policy.runtime import Runtime, resolve_runtime


@dataclass
class TrainResult:
    out: Path
    epochs_done: int
    steps: int
    best_val: float
    metrics: list[dict[str, float]]
    stopped_by: str  # "epochs" | "max_steps" | "max_minutes"


def train(
    cfg: TrainConfig, resume: bool = False, splits: tuple[Any, Any, Mapping[str, Any]] | None = None,
    dist_backend: str | None = None,
) -> TrainResult:  # fmt: skip
    """Train (or resume) a run in `cfg.out`; returns when the epochs or a budget are used up.

    `splits` = (train dataset, validation dataset, guidance config dict) replaces the datasets that
    `cfg.data` names, for data already in memory; the datasets follow yawil.data.DrivingDataset's contract
    (sample dicts, and `labels(name)` giving a label array without decoding images). One process at a time
    writes a run folder (yawil.locking). Under torchrun (WORLD_SIZE > 1) every rank calls this; the process
    group is initialised here unless the caller did (`dist_backend`: gloo or nccl; default by the device).
    """
    from yawil.locking import folder_lock

    check_model_fits(cfg)  # before folder_lock makes the folder
    world = distributed.world_from_env()
    if world is None:
        with folder_lock(cfg.out, "training run"):
            return _train(cfg, resume, splits)
    distributed.check_batch_size(cfg.batch_size, world[1])
    d = distributed.start(resolve_runtime(cfg.device, cfg.precision, cfg.channels_last).device.type, dist_backend)
    try:
        if not d.main:
            return _train(cfg, resume, splits, d)
        with folder_lock(cfg.out, "training run"):  # rank 0 writes the folder
            return _train(cfg, resume, splits, d)
    finally:
        distributed.stop(d)


def _train(
    cfg: TrainConfig, resume: bool, splits: tuple[Any, Any, Mapping[str, Any]] | None, d: Dist | None = None
) -> TrainResult:
    torch.set_num_threads(cfg.threads or (auto_threads(cfg.workers) if d is None else distributed.auto_threads(d, cfg.workers)))
    main = d is None or d.main  # the process that validates and writes
    out = Path(cfg.out)
    runtime = resolve_runtime(cfg.device, cfg.precision, cfg.channels_last)
    if d is not None and runtime.device.type == "cuda":
        runtime = replace(runtime, device=torch.device("cuda", d.local_rank))
    ckpt: dict[str, Any] | None = None
    if resume:  # checked before any data is read or anything written
        ckpt = load_checkpoint(out / "last.pt", map_location=runtime.device)
        check_resumable(ckpt["train_config"], cfg, out / "last.pt")
        check_budget(ckpt, cfg, out)
    train_ds, val_ds, guidance_config = open_splits(cfg) if splits is None else splits
    guidance_config = dict(guidance_config)
    from yawil.guidance import GuidanceConfig

    dims = GuidanceConfig.from_dict(guidance_config).dims()
    model = build_model(cfg, dims)
    kind: str | None = model.guidance
    uses_command = bool(model.uses_command)

    if ckpt is not None:
        model.load_state_dict(ckpt.get("raw_state_dict", ckpt["state_dict"]))  # with EMA, state_dict is the average
        norm = Norm.from_dict(ckpt["norm"])
    elif cfg.init_from is not None:
        init = load_checkpoint(cfg.init_from, map_location="cpu")
        if init["model_name"] != cfg.model:
            raise ValueError(f"init_from {cfg.init_from}: a {init['model_name']} checkpoint, but the model is {cfg.model}")
        if dict(init["guidance_config"]) != guidance_config:
            raise ValueError(f"init_from {cfg.init_from}: guidance config {init['guidance_config']} differs from the "
                             f"data's {guidance_config}")
        try:
            result = model.load_state_dict(init["state_dict"], strict=not init.get("omitted"))
            stray = [k for k in result.missing_keys if not any(k.startswith(f"{m}.") for m in init.get("omitted", []))]
            if stray or result.unexpected_keys:  # a zoo model leaves out only the modules no output uses
                raise RuntimeError(f"missing {stray[:3]}, unexpected {result.unexpected_keys[:3]}")
        except RuntimeError as err:
            raise ValueError(f"init_from {cfg.init_from}: weights do not fit model {cfg.model} "
                             f"with model_args {cfg.model_args}: {str(err).splitlines()[0]}") from None
        norm = Norm.from_dict(init["norm"])  # the inputs keep the scale the weights learned
    else:
        norm = Norm.from_arrays(*label_arrays(train_ds, kind))
    if d is not None:  # W ranks of B / W samples then compute the batch statistics of one process with B
        model = distributed.sync_batchnorm(model, runtime.device.type)
    model.to(runtime.device)
    if runtime.channels_last:
        model.to(memory_format=torch.channels_last)  # type: ignore[call-arg]
    trainee = model if d is None else distributed.wrap(model, d, runtime.device)  # what the steps run
    # With cfg.ema the checkpoints' state_dict (what drives and what validation measures) is the average
    # (yawil.learn.ema); the weights the optimiser moves are kept beside it as raw_state_dict, for --resume.
    ema = make_ema(model, cfg.ema) if cfg.ema > 0 else None
    if ema is not None and ckpt is not None:
        restore_ema(ema, ckpt["state_dict"], ckpt["ema"])
    driven = model if ema is None else ema.module  # the weights a checkpoint drives with
    # foreach: one kernel per step for all tensors, measured 2x faster than the per-tensor loop on the CPU
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=True)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=cfg.lr_step_epochs, gamma=cfg.lr_gamma)
    scaler = torch.amp.GradScaler("cuda", enabled=runtime.precision == "fp16")
    pos = Position()
    metrics: list[dict[str, float]] = []
    if ckpt is not None:
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        if "scaler" in ckpt and runtime.precision == "fp16":
            scaler.load_state_dict(ckpt["scaler"])
        pos = Position(**ckpt["position"])
        metrics = list(ckpt["metrics"])
        ranks = ckpt.get("rng_ranks")
        if d is None:
            set_rng_states(ckpt["rng"])
        elif ranks is not None and len(ranks) == d.world:  # each rank goes on with its own generators
            set_rng_states(ranks[d.rank])
        else:  # another world size saved it: each rank's generators from (seed, rank, step)
            seed_globals(int(np.random.SeedSequence([cfg.seed, d.rank, pos.step]).generate_state(1)[0]))
    else:
        if out.joinpath("last.pt").exists():
            raise FileExistsError(f"{out} already holds a run (last.pt); use --resume or another --out")
        # Dropout draws from the global generators: seed them so that a fresh run is reproducible.
        seed_globals(cfg.seed if d is None else distributed.rank_seed(cfg.seed, d.rank))
    if main:
        write_atomic(out / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False))

    from tqdm import tqdm

    if main:
        from torch.utils.tensorboard import SummaryWriter

        writer: Any = SummaryWriter(str(out / "tb"), purge_step=pos.step if resume else None)
    else:
        writer = distributed.NoWriter()
    if len(train_ds) == 0:
        raise ValueError("the training split is empty: the dataset roots hold no training frames")
    resident: ResidentData | None = None
    resident_val: ResidentData | None = None
    if cfg.data_on_device:  # both splits read once into tensors on the device (yawil.learn.resident)
        resident, resident_val = load_splits(train_ds, val_ds, kind, cfg, runtime, announce=main)
    val_batches = sequential_batches(len(val_ds), cfg.batch_size)
    val_loader: Any = (make_loader(val_ds, val_batches, cfg, runtime) if resident is None or resident_val is None
                       else resident_val.batches(val_batches))

    def loader_of(batches: list[list[int]]) -> Any:
        """This rank's batches from the device-resident split, or from the dataset through a DataLoader."""
        return make_loader(train_ds, batches, cfg, runtime) if resident is None else resident.batches(batches)

    started = time.monotonic()
    stopped_by = "epochs"

    def save(path: Path) -> None:
        """The checkpoint of this position; under torchrun every rank calls it (their RNG states are
        gathered: `rng_ranks`) and rank 0 writes it."""
        rng = rng_states()
        extra: dict[str, Any] = {}
        if d is not None:
            extra["rng_ranks"] = distributed.gather_objects(rng, d)
            if not d.main:
                return
        if ema is not None:
            extra["raw_state_dict"] = cpu_state_dict(model)
            extra["ema"] = ema_state(ema)
        save_checkpoint(make_checkpoint(
            driven, norm, guidance_config, cfg.to_dict(), pos.epoch, pos.step, metrics,
            optimizer=optimizer.state_dict(),
            scheduler=scheduler.state_dict(),
            scaler=scaler.state_dict(),
            rng=rng,
            position=asdict(pos),
            runtime={"device": runtime.device.type, "precision": runtime.precision, "channels_last": runtime.channels_last},
            **extra,
        ), path)  # fmt: skip

    def sync() -> None:
        """Under torchrun: no rank leaves before rank 0 has written (torchrun stops the others when one exits)."""
        if d is not None:
            distributed.barrier(d)

    def end_of_period(partial: bool, scheduled: bool = True) -> None:
        """Validate, log, keep best and last. `partial`: a budget stopped the epoch midway. Without a validation
        split the metrics' validation columns are NaN and best.pt follows last.pt. `scheduled=False` (a stop by
        Ctrl-C, SIGTERM or a data error): the validation is recorded (its row says `interrupted`) but does not
        enter the choice of best.pt, so that an interrupted and resumed run keeps an uninterrupted run's best."""
        val = None
        if main:
            val = validate(driven, val_loader, norm, kind, cfg, runtime) if len(val_ds) else dict.fromkeys(VAL_KEYS, math.nan)
        if d is not None:
            val = distributed.broadcast_object(val, d)  # every rank keeps the same metrics and best_val
        assert val is not None
        row: dict[str, float] = {
            "epoch": pos.epoch + (pos.batch / max(1, n_batches) if partial else 1),
            "step": pos.step,
            "train_loss": pos.loss_sum / max(1, pos.samples),
            **val,
            "lr": optimizer.param_groups[0]["lr"],
            "time": pos.seconds,
            "samples_per_s": pos.samples / max(pos.seconds, 1e-9),
        }
        if not scheduled:
            row["interrupted"] = 1.0
        metrics.append(row)
        for key in ("train_loss", *val):
            writer.add_scalar(f"epoch/{key}", row[key], pos.step)
        improved = scheduled and (row["val_loss"] < pos.best_val or not len(val_ds))
        if improved and len(val_ds):
            pos.best_val = row["val_loss"]
        if not partial:
            scheduler.step()
            pos.epoch += 1
            pos.batch, pos.loss_sum, pos.samples, pos.seconds = 0, 0.0, 0, 0.0
        save(out / "last.pt")
        if main:
            if improved:
                link_or_copy(out / "last.pt", out / "best.pt")
            write_metrics(out, metrics)
        writer.flush()

    keep_at = set(cfg.keep_steps)

    def after_step(step: int) -> None:
        """After step `step`: the average moves, and the checkpoint is kept apart when asked for (its position
        resumes mid-epoch like last.pt)."""
        if ema is not None:
            ema.update_parameters(model)
        if step in keep_at:
            save(out / f"step_{step:06d}.pt")

    if main:  # the checkpoints must fit before a step is spent: a failed save loses every step since the last one
        from yawil.fileio import require_free_space

        weights = sum(v.numel() * v.element_size() for v in model.state_dict().values())
        # last.pt (weights, two optimiser moments, the averaged copy) twice while it is replaced, one per kept step
        require_free_space(out, weights * (8 + 4 * len(keep_at)) + (64 << 20), "for this run's checkpoints")
    model.train()
    n_batches = 0
    p = None
    if cfg.brake_fraction is not None:
        brake, speed = label_columns(train_ds, ["brake", "speed"])
        p = brake_weights(brake, speed, cfg.brake_fraction)
    elif cfg.reason_fractions:
        (reason,) = label_columns(train_ds, ["speed_reason"])
        p = reason_weights(reason, cfg.reason_fractions)
    while pos.epoch < cfg.epochs:
        if cfg.max_steps is not None and pos.step >= cfg.max_steps:
            stopped_by = "max_steps"
            break
        batches = epoch_batches(len(train_ds), cfg.batch_size, cfg.seed, pos.epoch, p)
        sizes: list[int] | None = None  # global batch sizes, under torchrun
        if d is None:
            loader = loader_of(batches[pos.batch :])
        else:
            batches = distributed.usable_batches(batches, d.world)
            mine, sizes = distributed.rank_batches(batches[pos.batch :], d)
            loader = loader_of(mine)
        n_batches = len(batches)
        bar = tqdm(
            total=n_batches, initial=pos.batch, desc=f"epoch {pos.epoch + 1}/{cfg.epochs}",
            disable=not cfg.progress or not main, unit="batch", dynamic_ncols=True,
        )  # fmt: skip
        try:
            with stop_between_steps(announce=main):
                stop = _train_epoch(trainee, loader, optimizer, scaler, norm, kind, uses_command, cfg, runtime, pos,
                                    writer, bar, started, after_step, d, sizes)
        except StopRequested:
            # Ctrl-C or SIGTERM, taken between two steps: the state saved is exactly that after pos.step steps,
            # so --resume gives the weights of an uninterrupted run
            bar.close()
            if pos.batch > 0:
                end_of_period(partial=True, scheduled=False)
            writer.close()
            if main:
                plot_losses(out, metrics)
                print(f"interrupted at step {pos.step}; the same command resumes it (yawil train: --resume)",
                      file=sys.stderr)
            sync()
            raise stopped(f"stopped at step {pos.step}") from None
        except _DataError as err:
            # the weights are those after pos.step whole steps: save them, then name the data problem
            bar.close()
            if pos.batch > 0:
                end_of_period(partial=True, scheduled=False)
            writer.close()
            sync()
            raise ValueError(f"cannot read a training batch ({err}); the run is saved at step {pos.step}: "
                             "check the data (yawil data check; a resumed collect re-collects damaged episodes), "
                             "then --resume") from None
        except KeyboardInterrupt:
            # a second Ctrl-C stops mid-step: the weights may be half-updated, so nothing is saved
            bar.close()
            writer.close()
            print(f"stopped at once; --resume continues from {out / 'last.pt'} as last saved", file=sys.stderr)
            raise
        bar.close()
        if stop:
            stopped_by = stop
            if pos.batch > 0:
                end_of_period(partial=True)
            break
        end_of_period(partial=False)
    writer.close()
    if main:
        plot_losses(out, metrics)
    sync()
    return TrainResult(out, pos.epoch, pos.step, pos.best_val, metrics, stopped_by)


def _train_epoch(
    model: Any, loader: Any, optimizer: torch.optim.Optimizer, scaler: torch.amp.GradScaler, norm: Norm,
    kind: str | None, uses_command: bool, cfg: TrainConfig, runtime: Runtime, pos: Position, writer: Any,
    bar: Any, started: float, after_step: Callable[[int], None] | None = None, d: Dist | None = None,
    sizes: Sequence[int] | None = None,
) -> str | None:  # fmt: skip
    """Run the rest of the current epoch; return the name of the budget that stopped it, or None.

    Under torchrun (`d`; `sizes` the global batch sizes) the ranks agree after each step on the loss of the
    global batch, a stop request and the time budget, so that every rank stops after the same step."""
    tick = time.perf_counter()
    for i, raw in enumerate(_iterate(loader) if d is None else distributed.agreed(_iterate(loader), d, _DataError)):
        if cfg.max_steps is not None and pos.step >= cfg.max_steps:
            return "max_steps"
        b = prepare_batch(raw, norm, kind, uses_command, runtime)
        gen = step_generator(cfg.seed, pos.step, runtime.device, None if d is None else d.rank)
        b.image = augment_batch(b.image, cfg.augment, gen, inplace=True)
        if cfg.speed_dropout > 0.0:
            b.speed = drop_speed(b.speed, cfg.speed_dropout, gen)
        with runtime.autocast():
            loss, _, _ = compute_loss(model, b, cfg, norm)
        size = b.image.shape[0]
        weighted = loss
        if d is not None and sizes is not None and size * d.world != sizes[i]:
            # a short last batch split unevenly: DDP's mean over the ranks must be the mean over its samples
            weighted = loss * (size * d.world / sizes[i])
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(weighted).backward()
        scaler.step(optimizer)
        scaler.update()
        value = float(loss.detach())
        stop_all = over_all = False
        if d is not None:
            over = cfg.max_minutes is not None and (time.monotonic() - started) / 60.0 >= cfg.max_minutes
            total, n, stops, overs = distributed.sum_across([value * size, size, STOP["requested"], over], d)
            value, size, stop_all, over_all = total / n, int(n), stops > 0, overs > 0
        if not math.isfinite(value):
            raise FloatingPointError(f"training loss became {value} at step {pos.step} (epoch {pos.epoch + 1})")
        now = time.perf_counter()
        pos.seconds += now - tick
        tick = now
        pos.step += 1
        pos.batch += 1
        pos.loss_sum += value * size
        pos.samples += size
        if after_step is not None:
            after_step(pos.step)
        bar.update(1)
        bar.set_postfix(loss=f"{value:.4f}", sps=f"{pos.samples / max(pos.seconds, 1e-9):.0f}")
        if pos.step % cfg.log_every == 0:
            writer.add_scalar("train/loss", value, pos.step)
            writer.add_scalar("train/lr", optimizer.param_groups[0]["lr"], pos.step)
        if d is not None:
            if over_all:
                return "max_minutes"
            if stop_all:
                raise StopRequested
            continue
        if cfg.max_minutes is not None and (time.monotonic() - started) / 60.0 >= cfg.max_minutes:
            return "max_minutes"
        check_stop()
    return None


class _DataError(Exception):
    """A batch could not be read (a corrupt or vanished episode file); raised before its step began."""


def _iterate(loader: Any) -> Iterator[Any]:
    it = iter(loader)
    while True:
        try:
            raw = next(it)
        except StopIteration:
            return
        except (OSError, ValueError) as err:  # h5py's checksum or decode errors, a file gone
            raise _DataError(str(err).strip().splitlines()[-1]) from err
        except RuntimeError as err:  # a loader worker killed by the signal that stopped the run (a group SIGTERM)
            if STOP["requested"]:
                raise StopRequested from err
            raise
        yield raw
