"""An episode's record does not depend on which episodes its process drove before (issue 38).

The episode is driven alone in a fresh process, then in this process after another episode, by one
`EpisodeDriver` (its world, renderer and agent reused, as a benchmark worker reuses them): the records agree in
every field but wall_s, and so do the camera image and the control of every step. A fresh driver in a process
that already drove is not fresh (the renderer's leak was process-wide), hence the subprocess. Episodes are cut
after STEPS steps; benchmarks/history_probe.py compares whole episodes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

BEFORE, TARGET = "dense/training/ClearNoon/0/0", "dense/training/HardRainNoon/2/0"

# run as is in the subprocess and exec'd here, so that both sides drive the same way
_DRIVE = '''
import dataclasses
import hashlib
import inspect

from yawil.bench.runner import AgentSpec, EpisodeDriver
from yawil.bench.suites import episodes

STEPS = 40


class ShortWorld:
    """The embedded world, its episodes ended (as a timeout) after STEPS steps."""

    def __init__(self):
        from yawil.sim import make_world

        self.world, self.steps = make_world(backend="embedded"), 0

    def reset(self, scenario, seed):
        self.steps = 0
        return self.world.reset(scenario, seed=seed)

    def step(self, control):
        self.steps += 1
        obs = self.world.step(control)
        return dataclasses.replace(obs, done=True) if self.steps >= STEPS else obs

    def close(self):
        self.world.close()


class Recording:
    """The agent, each step's camera image (SHA-1) and control kept."""

    def __init__(self, inner):
        self.inner, self.steps = inner, []
        self.seeded = "seed" in inspect.signature(inner.reset).parameters

    def reset(self, seed=None):
        self.steps = []
        self.inner.reset(seed=seed) if self.seeded else self.inner.reset()

    def act(self, obs):
        control = self.inner.act(obs)
        self.steps.append([hashlib.sha1(obs.image.tobytes()).hexdigest(), control.steer, control.throttle,
                           control.brake])
        return control


def drive(agent, keys):
    """[{record (but wall_s), steps}] of the episodes `keys`, driven in this order by one driver."""
    eps = {e.key: e for e in episodes("nocrash", conditions=["training"], tasks=["dense"], routes="0:3", seeds=1,
                                      weather_rule="cycle")}
    spec = AgentSpec("expert") if agent == "expert" else AgentSpec(agent, engine="onnxruntime")
    box = []

    def build(seed):
        box.append(Recording(spec.build(seed)))
        return box[-1]

    driver = EpisodeDriver(spec, camera=True, world_factory=ShortWorld, agent_factory=build)
    out = []
    for key in keys:
        rec = driver.run(eps[key])
        rec.pop("wall_s")
        out.append({"record": rec, "steps": box[-1].steps})
    driver.close()
    return out
'''


def _drive(agent: str, keys: list[str]) -> list[dict[str, Any]]:
    scope: dict[str, Any] = {}
    exec(compile(_DRIVE, "<drive>", "exec"), scope)  # noqa: S102  (the test's own code, shared with the subprocess)
    return json.loads(json.dumps(scope["drive"](agent, keys)))  # as the subprocess's JSON gives it


@pytest.mark.slow  # a general guard (66-79 s at load 5); the regression itself: tests/sim/test_render_history.py
@pytest.mark.parametrize("kind", ["expert", "learned"])
def test_an_episode_drives_the_same_alone_and_after_another(kind: str, tmp_path: Path, tiny_checkpoint: Any) -> None:
    agent = "expert" if kind == "expert" else str(tiny_checkpoint("yaw-guided", dropout=0.0).path)
    code = f"{_DRIVE}\nimport json\nprint(json.dumps(drive({agent!r}, [{TARGET!r}])))\n"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    alone = json.loads(done.stdout.strip().splitlines()[-1])[0]
    before, after = _drive(agent, [BEFORE, TARGET])
    assert len(alone["steps"]) == len(after["steps"]) > 30 and before["steps"]
    for i, (a, b) in enumerate(zip(alone["steps"], after["steps"], strict=True)):
        assert a == b, f"step {i}: image or control differs"
    assert after["record"] == alone["record"]
