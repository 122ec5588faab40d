"""Probe frames: a few recorded camera frames with their speed, raw guidance and road option, as an agent
receives them. A zoo model keeps its own (`probe.npz`, written by `yawil zoo pack`) so that a silent change of
preprocessing or model code shows (`yawil zoo check`), and `yawil export --check` compares engines on them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from yawil.zoo import PROBE


def sample_probe(data: Path, kind: str | None, count: int = 8, seed: int = 0) -> dict[str, np.ndarray]:
    """`count` frames of a dataset, chosen with `seed`: camera, speed, the raw guidance of `kind`, command."""
    from yawil.data.reader import open_episode
    from yawil.policy.inputs import guidance_key

    files = sorted(Path(data).rglob("*.h5"))
    if not files:
        raise ValueError(f"--data {data}: no episode files (*.h5)")
    rng = np.random.default_rng(seed)
    images, speeds, guides, commands = [], [], [], []
    for fi in sorted(rng.choice(len(files), size=count, replace=len(files) < count).tolist()):
        with open_episode(files[fi]) as ep:
            rec = ep[int(rng.integers(len(ep)))]
        images.append(rec.image)
        speeds.append(rec.speed)
        guides.append(getattr(rec, guidance_key(kind)) if kind else np.zeros(0, np.float32))
        commands.append(int(rec.command))
    return {"image": np.stack(images).astype(np.uint8), "speed": np.asarray(speeds, np.float32),
            "guidance": np.stack(guides).astype(np.float32), "command": np.asarray(commands, np.int64)}


def read_probe(folder: Path) -> dict[str, np.ndarray]:
    """A zoo model's probe frames (`probe.npz` in its folder)."""
    with np.load(folder / PROBE) as z:
        return {k: z[k] for k in ("image", "speed", "guidance", "command")}
