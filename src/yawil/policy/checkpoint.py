"""Training checkpoints: what a trained model needs to drive again, and to resume training exactly.

A checkpoint is a plain dict saved with `torch.save` (written to a temporary file, then renamed, so an
interrupted save never destroys the previous one). Its keys are in `REQUIRED_KEYS`; the normalisation
statistics and the guidance configuration travel with the weights, so that `yawil.agent` rebuilds the
exact training preprocessing without the dataset.
"""

from __future__ import annotations

import errno
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from yawil.fileio import atomic_file

FORMAT = "yawil-checkpoint"
FORMAT_VERSION = 1

REQUIRED_KEYS: tuple[str, ...] = (
    "format",
    "format_version",
    "yawil_version",
    "model_name",
    "model_config",
    "state_dict",
    "norm",
    "guidance_config",
    "guidance_kind",
    "train_config",
    "epoch",
    "step",
    "metrics",
)
# Present in checkpoints written by the trainer (needed by --resume only).
RESUME_KEYS: tuple[str, ...] = ("optimizer", "scheduler", "rng", "position")


@dataclass(frozen=True)
class Norm:
    """Mean and standard deviation of the measurement inputs over the training split.

    Components with (near) zero spread keep std 1 so that a constant input (the first yaw of the
    route-referenced guidance is always 0) is centred, never divided by zero.
    """

    speed_mean: float
    speed_std: float
    guidance_mean: tuple[float, ...] = ()
    guidance_std: tuple[float, ...] = ()

    @staticmethod
    def from_arrays(speed: np.ndarray, guidance: np.ndarray | None) -> Norm:
        speed = np.asarray(speed, dtype=np.float64).reshape(-1)
        if speed.size == 0:
            raise ValueError("cannot compute normalisation statistics from an empty training split")
        g_mean: tuple[float, ...] = ()
        g_std: tuple[float, ...] = ()
        if guidance is not None:
            g = np.asarray(guidance, dtype=np.float64)
            g = g.reshape(g.shape[0], -1)
            g_mean = tuple(float(v) for v in g.mean(axis=0))
            g_std = tuple(float(v) for v in _safe_std(g.std(axis=0)))
        return Norm(
            speed_mean=float(speed.mean()),
            speed_std=float(_safe_std(np.array([speed.std()]))[0]),
            guidance_mean=g_mean,
            guidance_std=g_std,
        )

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Norm:
        try:
            return Norm(
                speed_mean=float(d["speed_mean"]),
                speed_std=float(d["speed_std"]),
                guidance_mean=tuple(float(v) for v in d.get("guidance_mean", ())),
                guidance_std=tuple(float(v) for v in d.get("guidance_std", ())),
            )
        except KeyError as err:
            raise ValueError(f"checkpoint norm is missing the key {err.args[0]!r}") from None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["guidance_mean"] = list(self.guidance_mean)
        d["guidance_std"] = list(self.guidance_std)
        return d

    def speed(self, speed: torch.Tensor) -> torch.Tensor:
        return (speed - self.speed_mean) / self.speed_std

    def speed_inverse(self, speed_n: torch.Tensor) -> torch.Tensor:
        return speed_n * self.speed_std + self.speed_mean

    def guidance(self, guidance: torch.Tensor) -> torch.Tensor:
        if guidance.shape[-1] != len(self.guidance_mean):
            raise ValueError(
                f"guidance has {guidance.shape[-1]} components, the normalisation has {len(self.guidance_mean)}"
            )
        mean = torch.tensor(self.guidance_mean, dtype=guidance.dtype, device=guidance.device)
        std = torch.tensor(self.guidance_std, dtype=guidance.dtype, device=guidance.device)
        return (guidance - mean) / std


def _safe_std(std: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    return np.where(std < floor, 1.0, std)


def make_checkpoint(
    model: Any,  # a yawil.models.DrivingModel
    norm: Norm,
    guidance_config: dict[str, Any],
    train_config: dict[str, Any] | None = None,
    epoch: int = 0,
    step: int = 0,
    metrics: list[dict[str, float]] | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """The checkpoint dict of a model (weights copied to the CPU); `extra` adds the resume keys."""
    from yawil import __version__

    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "yawil_version": __version__,
        "model_name": str(model.name),
        "model_config": dict(model.config),
        "state_dict": cpu_state_dict(model),
        "norm": norm.to_dict(),
        "guidance_config": dict(guidance_config),
        "guidance_kind": getattr(model, "guidance", None),
        "train_config": dict(train_config or {}),
        "epoch": int(epoch),
        "step": int(step),
        "metrics": list(metrics or []),
        **extra,
    }


def cpu_state_dict(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """A copy of the module's weights and buffers on the CPU, as checkpoints store them."""
    return {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}


def weights_digest(state_dict: dict[str, torch.Tensor]) -> str:
    """SHA-256 over the weights' names, dtypes, shapes and bytes: stored in every checkpoint and checked on load,
    so that a damaged file (flipped bytes load fine and drive nonsense) is named instead of driven."""
    import hashlib

    h = hashlib.sha256()
    for name in sorted(state_dict):
        _hash_tensor(h, name, state_dict[name])
    return h.hexdigest()


def _hash_tensor(h: Any, key: str, tensor: torch.Tensor) -> None:
    """One tensor into a digest: its key, dtype and shape, then its bytes (both digests below)."""
    t = tensor.detach().cpu().contiguous()
    h.update(f"{key}:{t.dtype}:{tuple(t.shape)};".encode())
    h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())


def resume_digest(ckpt: dict[str, Any]) -> str:
    """SHA-256 over what `--resume` reads besides the weights (optimiser moments, raw weights, the average's
    state): a flipped byte there loads, trains on and is saved again under a fresh weights digest."""
    import hashlib

    h = hashlib.sha256()

    def walk(obj: Any, key: str) -> None:
        if isinstance(obj, torch.Tensor):
            _hash_tensor(h, key, obj)
        elif isinstance(obj, dict):
            for k in sorted(obj, key=str):
                walk(obj[k], f"{key}/{k}")
        elif isinstance(obj, (list, tuple)):
            for i, v in enumerate(obj):
                walk(v, f"{key}/{i}")
        elif isinstance(obj, (int, float, str, bool)) or obj is None:
            h.update(f"{key}={obj!r};".encode())

    for name in ("optimizer", "raw_state_dict", "ema"):
        if name in ckpt:
            walk(ckpt[name], name)
    return h.hexdigest()


def save_checkpoint(ckpt: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """Save atomically (a temporary file in the same folder, then a rename), with the digests of its weights
    and of its resume state."""
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        raise ValueError(f"refusing to save a checkpoint without {missing}")
    ckpt = {k: v for k, v in ckpt.items() if k != "resume_sha256"}  # a copy's stale digest (zoo pack drops the state)
    ckpt["weights_sha256"] = weights_digest(ckpt["state_dict"])
    if any(k in ckpt for k in ("optimizer", "raw_state_dict", "ema")):
        ckpt["resume_sha256"] = resume_digest(ckpt)
    path = Path(path)
    with atomic_file(path) as f:
        try:
            torch.save(ckpt, f)
        except RuntimeError as err:  # torch reports a failed write as "enforce fail at inline_container.cc"
            free = shutil.disk_usage(path.parent).free
            raise OSError(errno.ENOSPC if free < (64 << 20) else errno.EIO,
                          f"{path}: writing the checkpoint failed ({free / 2**20:.0f} MiB free on its disk"
                          f"{': the disk is full' if free < (64 << 20) else ''}); torch said: "
                          f"{str(err).strip().splitlines()[0]}") from None
    return path


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load and validate a yawil checkpoint (a path, or `zoo:NAME`: yawil.zoo), with an error that names
    the file and what is wrong."""
    if str(path).startswith("zoo:"):
        from yawil.zoo import resolve_checkpoint

        path = resolve_checkpoint(path)
    path = Path(path)
    if path.is_dir():
        inside = [p.name for p in (path / "best.pt", path / "last.pt") if p.is_file()]
        raise ValueError(f"checkpoint {path} is a folder; expected a checkpoint file" +
                         (f" (it holds {' and '.join(inside)})" if inside else ""))
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        # Our checkpoints hold numpy RNG states and plain containers: not weights-only material.
        ckpt = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as err:  # torch raises many kinds for a bad file
        raise ValueError(f"{path} is not a readable torch checkpoint: {err}") from err
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ValueError(f"{path} is not a yawil checkpoint (no 'format': {FORMAT!r} entry)")
    if int(ckpt.get("format_version", -1)) > FORMAT_VERSION:
        raise ValueError(
            f"{path} has checkpoint format version {ckpt.get('format_version')}, this yawil reads <= {FORMAT_VERSION}"
        )
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        raise ValueError(f"{path} is a yawil checkpoint but lacks the key(s) {missing}")
    Norm.from_dict(ckpt["norm"])  # validates the nested keys
    want = ckpt.get("weights_sha256")  # checkpoints written before the digest was stored have none
    if want is not None and weights_digest(ckpt["state_dict"]) != want:
        raise ValueError(f"{path}: its weights do not match the SHA-256 stored with them: the file is damaged "
                         "(retrain, or restore it from a copy)")
    resume = ckpt.get("resume_sha256")
    if resume is not None and resume_digest(ckpt) != resume:
        raise ValueError(f"{path}: its optimiser or resume state does not match the SHA-256 stored with it: the file "
                         "is damaged (the weights may drive; --resume would train on the damage)")
    return ckpt


def model_from_checkpoint(ckpt: dict[str, Any]) -> torch.nn.Module:
    """Rebuild the network of a loaded checkpoint and load its weights (no ImageNet file needed)."""
    from yawil import models

    config = dict(ckpt["model_config"])
    config.pop("pretrained", None)  # the weights come from the checkpoint itself
    model = models.create(ckpt["model_name"], **config)
    omitted = tuple(f"{m}." for m in ckpt.get("omitted", ()))  # zoo models leave out modules no output uses
    result = model.load_state_dict(ckpt["state_dict"], strict=not omitted)  # bf16 weights are cast to float32
    stray = [k for k in result.missing_keys if not k.startswith(omitted)] + list(result.unexpected_keys)
    if stray:
        raise ValueError(f"the checkpoint's weights do not fit {ckpt['model_name']}: {stray[:5]}")
    return model
