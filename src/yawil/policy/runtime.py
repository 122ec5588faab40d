"""Device and precision: where and how tensors are computed, resolved once (training and inference alike).

    runtime = resolve_runtime("auto", "auto", "auto")   # cuda + fp16, or cpu + bf16 where it is native, else fp32
    with runtime.autocast():
        out = model(...)
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any

import torch

PRECISIONS = ("auto", "fp32", "bf16", "fp16")
DEVICES = ("auto", "cpu", "cuda")
SWITCHES = ("auto", "on", "off")  # channels_last; auto: on (measured faster on the CPU and CUDA)


@dataclass(frozen=True)
class Runtime:
    """Where and how tensors are computed, resolved once from the config."""

    device: torch.device
    precision: str  # fp32 | bf16 | fp16
    channels_last: bool

    def autocast(self) -> AbstractContextManager[Any]:
        if self.precision == "fp32":
            return nullcontext()
        dtype = torch.bfloat16 if self.precision == "bf16" else torch.float16
        return torch.autocast(self.device.type, dtype=dtype)


def cpu_has_fast_bf16() -> bool:
    """oneDNN reports native bf16 (AVX512-BF16 / AMX); elsewhere bf16 is emulated and slower than fp32."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def resolve_runtime(device: str = "auto", precision: str = "auto", channels_last: str | bool = "auto") -> Runtime:
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device='cuda' but torch sees no CUDA device; use --device cpu or auto")
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device: expected one of {DEVICES}, got {device!r}")
    if precision == "auto":
        precision = "fp16" if device == "cuda" else ("bf16" if cpu_has_fast_bf16() else "fp32")
    if precision == "fp16" and device == "cpu":
        raise ValueError("precision='fp16' needs CUDA; on the CPU use bf16 or fp32")
    if precision not in ("fp32", "bf16", "fp16"):
        raise ValueError(f"precision: expected one of {PRECISIONS}, got {precision!r}")
    if isinstance(channels_last, bool):  # a Python caller's natural spelling of on/off
        channels_last = "on" if channels_last else "off"
    if channels_last not in SWITCHES:  # "maybe" was taken for "on" without a word
        raise ValueError(f"channels_last: expected one of {SWITCHES} or true/false, got {channels_last!r}")
    return Runtime(torch.device(device), precision, channels_last != "off")
