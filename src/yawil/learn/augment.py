"""Photometric augmentation of training batches (the paper: blur, noise, brightness; plus contrast and
pixel dropout as CIL/CILRS did), vectorised over the batch with per-sample random parameters.

Three colour operations are off by default (probability 0) and can be switched on: saturation, a gain per
colour channel (a colour cast, CIL's `Multiply((0.8, 1.2), per_channel)`) and gamma. Why: a learned agent's
failures were seen to gather in the sunset weathers, whose dark orange road the brightness and contrast
factors do not imitate (docs/training.md, "Augmentation", says how far that is measured). Their parameters
are drawn after every draw of the other operations, so a configuration that leaves them off augments exactly
as before, bit for bit.

torchvision.transforms.v2 draws one set of parameters per call, so applied to a batch it would give every
sample the same blur and brightness. Here the parameters are drawn per sample from a seeded
`torch.Generator` and the operations are the same formulas as `torchvision.transforms.v2.functional`
(`adjust_brightness`, `adjust_contrast`, `gaussian_blur` with reflect padding); tests check the two agree
sample by sample. One batch of 512 images 88x200 costs a few tens of milliseconds on two CPU cores
(see benchmarks/agent.py and docs/performance.md), negligible next to a ResNet34 step.

Images are float tensors [B, 3, H, W] in [0, 1]; the result stays in [0, 1].
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F

CHUNK = 64  # samples augmented together
# ITU-R 601-2 luma, the weights torchvision's rgb_to_grayscale uses.
_LUMA = (0.2989, 0.587, 0.114)


@dataclass(frozen=True)
class AugmentConfig:
    """Probability and strength of each operation; every sample draws its own."""

    enabled: bool = True
    brightness_p: float = 0.5
    brightness: float = 0.4  # factor drawn in [1 - b, 1 + b]
    contrast_p: float = 0.5
    contrast: float = 0.4  # factor drawn in [1 - c, 1 + c]
    blur_p: float = 0.3
    blur_sigma: float = 1.5  # sigma drawn in [0.1, blur_sigma] pixels
    blur_kernel: int = 5  # odd kernel size
    noise_p: float = 0.3
    noise_std: float = 0.05  # std drawn in [0, noise_std], in [0, 1] pixel units
    dropout_p: float = 0.2
    dropout: float = 0.1  # fraction of pixels zeroed, drawn in [0, dropout]
    saturation_p: float = 0.0
    saturation: float = 0.5  # factor drawn in [1 - s, 1 + s] (0: grey, 1: unchanged)
    gain_p: float = 0.0
    gain: float = 0.2  # one factor per colour channel, each drawn in [1 - g, 1 + g]
    gamma_p: float = 0.0
    gamma: float = 0.4  # exponent drawn in [1 - g, 1 + g] (> 1 darkens the mid-tones)

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "enabled":
                continue
            value = getattr(self, f.name)
            if f.name.endswith("_p") and not 0.0 <= float(value) <= 1.0:
                raise ValueError(f"augment.{f.name}={value!r}: a probability must be in [0, 1]")
        if not 0.0 <= self.brightness < 1.0 or not 0.0 <= self.contrast < 1.0:
            raise ValueError(
                f"augment.brightness={self.brightness!r}, augment.contrast={self.contrast!r}: must be in [0, 1)"
            )
        if self.blur_sigma < 0.1:
            raise ValueError(f"augment.blur_sigma={self.blur_sigma!r}: must be >= 0.1")
        if self.blur_kernel < 3 or self.blur_kernel % 2 == 0:
            raise ValueError(f"augment.blur_kernel={self.blur_kernel!r}: must be an odd integer >= 3")
        for name in ("saturation", "gain", "gamma"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"augment.{name}={getattr(self, name)!r}: must be in [0, 1)")
        if self.noise_std < 0.0 or not 0.0 <= self.dropout <= 1.0:
            raise ValueError(
                f"augment.noise_std={self.noise_std!r} must be >= 0 and augment.dropout={self.dropout!r} in [0, 1]"
            )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def gaussian_kernels(sigma: torch.Tensor, size: int) -> torch.Tensor:
    """1-D Gaussian kernels [B, size], one per sigma, built as torchvision builds them."""
    half = (size - 1) * 0.5
    x = torch.linspace(-half, half, steps=size, dtype=sigma.dtype, device=sigma.device)
    pdf = torch.exp(-0.5 * (x[None, :] / sigma[:, None]) ** 2)
    return pdf / pdf.sum(dim=1, keepdim=True)


def blur(images: torch.Tensor, sigma: torch.Tensor, size: int) -> torch.Tensor:
    """Separable Gaussian blur with one sigma per sample: a grouped convolution over B*C channels."""
    b, c, h, w = images.shape
    k = gaussian_kernels(sigma.to(images.dtype), size).repeat_interleave(c, dim=0)  # [B*C, size]
    x = images.reshape(1, b * c, h, w)
    pad = size // 2
    x = F.pad(x, (pad, pad, pad, pad), mode="reflect")
    x = F.conv2d(x, k[:, None, None, :], groups=b * c)  # along width
    x = F.conv2d(x, k[:, None, :, None], groups=b * c)  # along height
    return x.reshape(b, c, h, w)


def augment_batch(
    images: torch.Tensor, cfg: AugmentConfig, generator: torch.Generator, inplace: bool = False
) -> torch.Tensor:
    """Augment a float batch in [0, 1]. The same generator state gives the same result, bit for bit.

    The per-sample parameters are drawn first, all of them, as one [10, B] uniform tensor (rows: chosen?
    and strength of brightness, contrast, blur, noise, dropout); then the pixel noise and dropout masks of
    the chosen samples; then, only when a colour operation is on, their [8, B] uniforms (rows: chosen? and
    strength of saturation, chosen? and three channel gains, chosen? and exponent of gamma). Whole-batch
    passes are in place: at 512 x 3 x 88 x 200 (108 MB) allocation, not arithmetic, is what costs.
    """
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"augment_batch expects images [B, 3, H, W], got shape {tuple(images.shape)}")
    if not images.is_floating_point():
        raise ValueError(f"augment_batch expects float images in [0, 1], got dtype {images.dtype}")
    if not cfg.enabled or images.shape[0] == 0:
        return images
    out = images if inplace else images.clone()
    b = out.shape[0]
    u = torch.rand((10, b), generator=generator, device=out.device, dtype=torch.float32)
    for lo in range(0, b, CHUNK):  # chunks that stay in the CPU caches: faster than whole-batch passes at 512
        _augment_chunk(out[lo : lo + CHUNK], u[:, lo : lo + CHUNK], cfg, generator)
    if max(cfg.saturation_p, cfg.gain_p, cfg.gamma_p) > 0.0:
        v = torch.rand((8, b), generator=generator, device=out.device, dtype=torch.float32)
        for lo in range(0, b, CHUNK):
            _colour_chunk(out[lo : lo + CHUNK], v[:, lo : lo + CHUNK], cfg)
    return out


def _colour_chunk(out: torch.Tensor, v: torch.Tensor, cfg: AugmentConfig) -> None:
    """Saturation, channel gains and gamma, in place, with the per-sample uniforms `v` [8, b]."""
    b = out.shape[0]
    view = (b, 1, 1, 1)
    # saturation: adjust_saturation = clamp(factor * img + (1 - factor) * grayscale(img)), per pixel
    factor = torch.where(v[0] < cfg.saturation_p, 1 - cfg.saturation + 2 * cfg.saturation * v[1], 1.0).to(out.dtype)
    luma = torch.tensor(_LUMA, dtype=out.dtype, device=out.device).view(1, 3, 1, 1)
    gray = (out * luma).sum(dim=1, keepdim=True)
    out.mul_(factor.view(view)).add_(gray * (1 - factor).view(view)).clamp_(0.0, 1.0)
    # channel gains: a colour cast, one factor per channel
    gains = torch.where(v[2] < cfg.gain_p, 1 - cfg.gain + 2 * cfg.gain * v[3:6], 1.0).to(out.dtype)  # [3, b]
    out.mul_(gains.t().reshape(b, 3, 1, 1)).clamp_(0.0, 1.0)
    # gamma: adjust_gamma = img ** gamma (gain 1)
    idx = (v[6] < cfg.gamma_p).nonzero().squeeze(1)
    if idx.numel():
        exponent = (1 - cfg.gamma + 2 * cfg.gamma * v[7][idx]).view(-1, 1, 1, 1).to(out.dtype)
        out[idx] = out[idx].pow(exponent).clamp_(0.0, 1.0)


def _augment_chunk(out: torch.Tensor, u: torch.Tensor, cfg: AugmentConfig, gen: torch.Generator) -> None:
    """Augment `out` in place with the per-sample uniforms `u` [10, b]."""
    b, _, h, w = out.shape
    dev = out.device
    view = (b, 1, 1, 1)

    # brightness: adjust_brightness = clamp(img * factor)
    factor = torch.where(u[0] < cfg.brightness_p, 1 - cfg.brightness + 2 * cfg.brightness * u[1], 1.0)
    out.mul_(factor.view(view).to(out.dtype)).clamp_(0.0, 1.0)

    # contrast: adjust_contrast = clamp(factor * img + (1 - factor) * mean(grayscale(img)))
    factor = torch.where(u[2] < cfg.contrast_p, 1 - cfg.contrast + 2 * cfg.contrast * u[3], 1.0).to(out.dtype)
    luma = torch.tensor(_LUMA, dtype=out.dtype, device=dev)
    gray_mean = (out.mean(dim=(2, 3)) * luma).sum(dim=1)  # mean of the grayscale image, per sample
    out.mul_(factor.view(view)).add_(((1 - factor) * gray_mean).view(view)).clamp_(0.0, 1.0)

    # blur, only on the chosen samples (any sigma > 0 smooths)
    idx = (u[4] < cfg.blur_p).nonzero().squeeze(1)
    if idx.numel():
        sigma = 0.1 + (cfg.blur_sigma - 0.1) * u[5]
        out[idx] = blur(out[idx], sigma[idx], cfg.blur_kernel).clamp_(0.0, 1.0)  # kernel sums round to 1 + 1e-7

    # additive Gaussian noise
    idx = (u[6] < cfg.noise_p).nonzero().squeeze(1)
    if idx.numel():
        std = (cfg.noise_std * u[7][idx]).view(-1, 1, 1, 1).to(out.dtype)
        noise = torch.randn((idx.numel(), 3, h, w), generator=gen, device=dev, dtype=out.dtype)
        out[idx] = noise.mul_(std).add_(out[idx]).clamp_(0.0, 1.0)

    # pixel dropout: a pixel (all channels) set to black
    idx = (u[8] < cfg.dropout_p).nonzero().squeeze(1)
    if idx.numel():
        frac = (cfg.dropout * u[9][idx]).view(-1, 1, 1, 1)
        keep = torch.rand((idx.numel(), 1, h, w), generator=gen, device=dev) >= frac
        out[idx] = out[idx] * keep.to(out.dtype)
