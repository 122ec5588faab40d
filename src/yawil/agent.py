"""A trained model as a driver: Observation in, Control out, with exactly the training preprocessing.

    agent = Agent.from_checkpoint("zoo:yilratt-dagger-dense3")   # a zoo model drives as its card says
    agent.reset()
    control = agent.act(obs)       # yawil.sim.types.Control
    agent.last                     # raw outputs of that step (actions, speed, attention maps) for heat maps

    agent = Agent.from_checkpoint("runs/yilratt/best.pt", slots=8, attention=False)  # a batch of episodes
    agent.reset(seed=s, slot=i)                      # each episode its own slot and state
    controls = agent.act_batch([obs_a, obs_b], slots=[0, 3])   # one forward for all of them

The agent is three parts composed: the model-input contract (`yawil.policy.inputs`, the trainer's: image uint8
HWC -> float [0, 1] CHW; speed and guidance normalised with the checkpoint's statistics; guidance computed from
the observation's route with the checkpoint's GuidanceConfig; the command as a branch index), the engine that
runs the network on a batch (`yawil.policy.engine`), and the drive-time behaviours with their per-episode state
(`yawil.policy.drive`: noise, target-speed control, stop release, post-processing). An episode's controls depend
only on its own observations and seed, never on which episodes share its batch.
The benchmark needs only `reset()` and `act(obs)`, or `reset(seed, slot)` and `act_batch`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from yawil.guidance import GuidanceConfig
from yawil.policy.checkpoint import Norm, load_checkpoint, model_from_checkpoint
from yawil.policy.drive import (  # noqa: F401  (re-exported: the names users and tests know from here)
    LEAD_DECEL,
    LEAD_SEEN,
    STANDING,
    STOP_CREEP,
    DriveSettings,
    EpisodeState,
    PostProcess,
    SpeedControl,
    StopRelease,
)
from yawil.policy.engine import Calibration, Engine, make_engine
from yawil.policy.inputs import (
    InputSpec,
    ModelInputs,
    check_observation,
    guidance_kind,
    observation_guidance,
    takes_command,
)
from yawil.policy.runtime import Runtime, resolve_runtime
from yawil.sim.types import Control, Observation, command_index


@dataclass
class StepOutput:
    """What the network said at the last step, before post-processing (numpy, batch dimension removed)."""

    actions: np.ndarray  # (3,) steer, throttle, brake as output
    speed: float  # predicted speed, m/s
    attention: list[np.ndarray]  # one (h, w) map per attended layer; empty for models without attention
    branches: np.ndarray | None  # (4, 3) for branched models
    guidance: np.ndarray | None  # the guidance vector given (before normalisation)
    command: int | None  # the branch index given
    control: Control = field(default_factory=Control)
    target_speed: float | None = None  # m/s, from the aux head (models built with aux=true), after any cap or stop
    head_target_speed: float | None = None  # m/s, the aux head's own target speed, before any cap or stop
    lead_distance: float | None = None  # m to the lead vehicle's stop point, from the aux head
    lead_speed: float | None = None  # m/s of the lead vehicle, from the aux head
    lead_stop: float | None = None  # probability of a standing vehicle close ahead (models built with lead_stop=true)
    light: float | None = None  # probability of a red or yellow stop line within 30 m, from the aux head


class Agent:
    """Drives with a trained model, one episode per slot (`slots`, default 1).

    `drive`: the drive-time settings (`DriveSettings`); instead, its fields may be given as keywords
    (speed_control="stop", stop_release=10, yaw_noise_deg=..., post=...). `engine`: where the network runs
    (`yawil.policy.engine`: auto, torch, openvino, onnxruntime, openvino-int8). `attention`: keep the attention maps in `last`
    (heat maps, videos); the benchmark leaves them. `seed`: the noise stream of slot 0 (the benchmark gives each
    episode its own with `reset(seed=...)`)."""

    def __init__(
        self,
        model: torch.nn.Module,
        norm: Norm,
        guidance_config: GuidanceConfig,
        *,
        device: str = "cpu",
        precision: str = "auto",
        channels_last: str | bool = "auto",
        engine: str = "auto",
        drive: DriveSettings | None = None,
        seed: int = 0,
        slots: int = 1,
        attention: bool = True,
        **options: Any,
    ) -> None:
        if drive is not None and options:
            raise ValueError(f"give the drive settings as drive=DriveSettings(...) or as keywords, not both "
                             f"({', '.join(sorted(options))})")
        self.drive: DriveSettings = (drive or DriveSettings.from_options(options)).check(model)
        if isinstance(slots, bool) or not isinstance(slots, int) or slots < 1:
            raise ValueError(f"slots={slots!r}: expected an integer >= 1")
        self.runtime: Runtime = resolve_runtime(device, precision, channels_last)
        self.model = model.to(self.runtime.device).eval()
        if self.runtime.channels_last:
            self.model.to(memory_format=torch.channels_last)  # type: ignore[call-arg]
        self.norm = norm
        self.guidance_config = guidance_config
        self.kind: str | None = guidance_kind(model)
        self.uses_command = takes_command(model)
        if self.kind is not None and len(norm.guidance_mean) != getattr(model, "guidance_dim", -1):
            raise ValueError(
                f"the normalisation has {len(norm.guidance_mean)} guidance values, "
                f"the model expects {getattr(model, 'guidance_dim', '?')}"
            )
        self.engine: Engine = make_engine(self.model, self.runtime, engine, self._calibration())
        self.attention = bool(attention)
        self.seed = int(seed)
        self.states: list[EpisodeState] = [self.drive.episode(self.seed) for _ in range(slots)]
        self.outputs: list[StepOutput | None] = [None] * slots
        self.checkpoint_path: str | None = None

    def _calibration(self) -> Calibration:
        """What an int8 engine calibrates on: frames the expert drives, prepared as this agent prepares its own
        (`yawil.policy.quantize.expert_calibration`); made only if the engine needs them and has none cached."""
        from yawil.policy.quantize import CALIBRATION_FRAMES, CALIBRATION_SEED, expert_calibration

        about = {"frames": CALIBRATION_FRAMES, "seed": CALIBRATION_SEED, "norm": self.norm.to_dict(),
                 "guidance": self.guidance_config.to_dict(), "kind": self.kind, "command": self.uses_command}
        return (lambda: expert_calibration(self.spec, self.guidance_config)), about

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike[str], device: str = "cpu", **options: Any) -> Agent:
        """Rebuild model, normalisation and guidance config from a yawil checkpoint (best.pt or last.pt) or a zoo
        model (`zoo:NAME`). A zoo model given no drive setting drives as its card says (`card.json` "drive"),
        the settings its figures were measured with."""
        from yawil.zoo import PREFIX, card_drive, resolve_checkpoint

        given = {k for k in options if k in DriveSettings.__dataclass_fields__ or k == "drive"}
        if str(path).startswith(PREFIX) and not given:
            options.update(card_drive(str(path)))
        ckpt = load_checkpoint(resolve_checkpoint(path), map_location="cpu")
        model = model_from_checkpoint(ckpt)
        config = GuidanceConfig.from_dict(ckpt["guidance_config"])
        agent = cls(model, Norm.from_dict(ckpt["norm"]), config, device=device, **options)
        agent.checkpoint_path = str(path)
        return agent

    @property
    def name(self) -> str:
        return str(getattr(self.model, "name", type(self.model).__name__))

    @property
    def slots(self) -> int:
        return len(self.states)

    @property
    def post(self) -> PostProcess:
        return self.drive.post

    @property
    def last(self) -> StepOutput | None:
        """What the network said at slot 0's last step (the batch-of-1 case)."""
        return self.outputs[0]

    def reset(self, seed: int | None = None, slot: int = 0) -> None:
        """Start an episode in `slot`: forget the route projection, the controllers' state and any command-noise
        burst. The slot's noise stream carries on across episodes unless `seed` restarts it."""
        old = self.states[slot]
        state = self.drive.episode(self.seed if seed is None else seed)
        if seed is None:  # the same stream, carried on
            state.rng = old.rng
            if old.command_noise is not None:
                old.command_noise.reset()
                state.command_noise = old.command_noise
        elif slot == 0:
            self.seed = int(seed)
        self.states[slot] = state
        self.outputs[slot] = None

    @property
    def spec(self) -> InputSpec:
        """How this agent's model takes its inputs (`yawil.policy.inputs`): normalisation, kind, command, runtime."""
        return InputSpec(self.norm, self.kind, self.uses_command, self.runtime)

    def _row(self, obs: Observation, state: EpisodeState) -> tuple[np.ndarray, np.ndarray | None, int | None]:
        """One observation's image, raw guidance and road option, drawn from its episode's noise stream in a fixed
        order: the yaw noise of the guidance, then the command noise."""
        img = check_observation(obs)  # speed, command and image, before any is used
        guidance_raw: np.ndarray | None = None
        if self.kind is not None:
            guidance_raw, state.hint = observation_guidance(
                obs, self.guidance_config, self.kind, hint=state.hint, yaw_noise_deg=self.drive.yaw_noise_deg,
                rng=state.rng, yaw_noise_mode=self.drive.yaw_noise_mode,
            )  # fmt: skip
        option = self.drive.command(int(obs.command), state) if self.uses_command else None
        return img, guidance_raw, option

    def model_inputs(self, obs: Observation, slot: int = 0) -> tuple[ModelInputs, np.ndarray | None, int | None]:
        """The network inputs of one observation (batch of 1), plus the raw guidance and command index."""
        img, guidance_raw, option = self._row(obs, self.states[slot])
        command_idx = None if option is None else command_index(option)
        return self.spec.from_frame(img, obs.speed, guidance_raw, option), guidance_raw, command_idx

    def inputs(self, obs: Observation) -> tuple[dict[str, torch.Tensor | None], np.ndarray | None, int | None]:
        """`model_inputs` with the inputs as a dict by name (image, speed, guidance, command)."""
        x, guidance_raw, command_idx = self.model_inputs(obs)
        return x.as_dict(), guidance_raw, command_idx

    def act(self, obs: Observation) -> Control:
        return self.act_batch([obs], [0])[0]

    def act_batch(self, observations: Sequence[Observation], slots: Sequence[int] | None = None) -> list[Control]:
        """One control per observation, the i-th of the episode in `slots[i]` (default 0, 1, ...): one forward
        pass for all of them."""
        slots = list(range(len(observations))) if slots is None else list(slots)
        if len(slots) != len(observations) or len(set(slots)) != len(slots):
            raise ValueError(f"act_batch: {len(observations)} observations for slots {slots}: one distinct slot each")
        rows = [self._row(obs, self.states[s]) for obs, s in zip(observations, slots, strict=True)]
        x = self.spec.from_frames([r[0] for r in rows], [o.speed for o in observations], [r[1] for r in rows],
                                  [r[2] for r in rows])
        out = self.engine.run(x, attention=self.attention)
        speeds = self.norm.speed_inverse(out.speed)  # type: ignore[arg-type]  # x * std + mean, numpy too
        controls = []
        for i, (obs, slot) in enumerate(zip(observations, slots, strict=True)):
            ego = max(float(obs.speed), 0.0)
            d = self.drive.decide(out.actions[i], None if out.aux is None else out.aux[i], self._speed_of,
                                  self.states[slot], ego)
            control = self.drive.post(d.actions, float(obs.speed))
            option = rows[i][2]
            self.outputs[slot] = StepOutput(
                actions=d.actions, speed=float(speeds[i]), attention=[a[i] for a in out.attention],
                branches=None if out.branches is None else out.branches[i], guidance=rows[i][1],
                command=None if option is None else command_index(option), control=control,
                target_speed=d.target_speed, head_target_speed=d.head_target_speed, lead_distance=d.lead_distance,
                lead_speed=d.lead_speed, lead_stop=d.lead_stop, light=d.light,
            )  # fmt: skip
            controls.append(control)
        return controls

    def _speed_of(self, value: float) -> float:
        return float(self.norm.speed_inverse(np.float32(value)))  # type: ignore[arg-type]


def load_agent(checkpoint: str | os.PathLike[str], *, threads: int | None = None, **options: Any) -> Agent:
    """A trained model as a driving agent, the one call a Python user needs: a checkpoint path or `zoo:NAME` (then
    driven as its card says unless drive options are given), on the CPU unless `device=` says otherwise.

    Sets torch's threads for this process (`threads`, default min(4, cores)): torch's default of one per core
    made `act` take ~2 s on a busy 2-core machine (55-60 ms with one thread), and a batch of one gains little
    beyond four. Other keywords go to `Agent.from_checkpoint` (engine, precision, drive settings, seed, slots)."""
    n = threads if threads is not None else min(4, os.cpu_count() or 1)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"threads={threads!r}: expected an integer >= 1")
    torch.set_num_threads(n)
    return Agent.from_checkpoint(checkpoint, **options)


def gym_action(agent: Any, env: Any) -> np.ndarray:
    """The agent's action for a yawil Gymnasium env's current step, as the env's action array (steer, throttle,
    brake). The agent reads the simulator observation the env keeps (`last_observation`), so it computes its
    guidance as its model was trained, whatever the env's own guidance settings (a zoo model trained with the
    `ego` reference fed a default env's `route` guidance would steer up to 0.5 differently, silently)."""
    obs = getattr(getattr(env, "unwrapped", env), "last_observation", None)
    if obs is None:
        raise ValueError("gym_action needs a yawil env (yawil/Town01-v0, ...) after reset()")
    c = agent.act(obs)
    return np.array([c.steer, c.throttle, c.brake], dtype=np.float32)
