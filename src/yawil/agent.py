"""A trained model as a driver: Observation in, Control out, with exactly the training preprocessing.

    agent = Agent.from_checkpoint("runs/yilratt/best.pt")
    agent.reset()
    control = agent.act(obs)       # yawil.sim.types.Control
    agent.last                     # raw outputs of that step (actions, speed, attention maps) for heat maps

Preprocessing is the model-input contract of `yawil.policy.inputs`, the one the trainer uses: image uint8 HWC
-> float [0, 1] CHW; speed and guidance normalised with the checkpoint's training statistics; guidance computed
from the observation's route with the checkpoint's GuidanceConfig (the projection hint is kept across frames);
the command as a branch index (command_index). Post-processing is `PostProcess`, documented in docs/training.md.
The benchmark needs only `reset()` and `act(obs)`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from yawil.data.schema import LEAD_RANGE
from yawil.expert import ExpertConfig, hazard_speed
from yawil.guidance import COMMAND_NOISE_MODES, YAW_NOISE_MODES, CommandNoise, GuidanceConfig
from yawil.models.base import AUX_NAMES, LEAD_STOP_FIRES
from yawil.policy.checkpoint import Norm, load_checkpoint, model_from_checkpoint
from yawil.policy.inputs import (
    InputSpec,
    ModelInputs,
    check_observation_image,
    guidance_kind,
    observation_guidance,
    takes_command,
)
from yawil.policy.runtime import Runtime, resolve_runtime
from yawil.policy.speed import check_stop_release, speed_control_mode
from yawil.sim.types import DT, Control, Observation, command_index


@dataclass(frozen=True)
class PostProcess:
    """From network outputs to a Control.

    Outputs are clipped to the control ranges; a brake below `brake_threshold` counts as no brake (the
    networks rarely output an exact 0); when braking, throttle is cut (`exclusive_brake`, as CILRS's
    agent does: the expert never presses both); above `max_speed` (m/s, None = off) throttle is cut.
    """

    brake_threshold: float = 0.1
    exclusive_brake: bool = True
    max_speed: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.brake_threshold <= 1.0:
            raise ValueError(f"brake_threshold={self.brake_threshold!r}: expected a value in [0, 1]")
        if self.max_speed is not None and not self.max_speed > 0.0:
            raise ValueError(f"max_speed={self.max_speed!r}: expected None or a speed > 0 m/s")

    def __call__(self, actions: np.ndarray, speed: float) -> Control:
        a = np.nan_to_num(np.asarray(actions, dtype=np.float64), nan=0.0)
        steer = float(np.clip(a[0], -1.0, 1.0))
        throttle = float(np.clip(a[1], 0.0, 1.0))
        brake = float(np.clip(a[2], 0.0, 1.0))
        if brake < self.brake_threshold:
            brake = 0.0
        if brake > 0.0 and self.exclusive_brake:
            throttle = 0.0
        if self.max_speed is not None and speed > self.max_speed:
            throttle = 0.0
        return Control(steer=steer, throttle=throttle, brake=brake).validate()


_EXPERT = ExpertConfig()  # the speed controller's gains are the expert's, from the one place they are set

# "lead" (yawil.policy.speed): the target capped by `hazard_speed` on the predicted lead vehicle, with these.
LEAD_DECEL = 1.5  # m/s^2: the "lead" cap's braking profile, gentler than the expert's 2.5 so that it binds earlier
LEAD_SEEN = 0.9 * LEAD_RANGE  # m: a predicted lead distance beyond this counts as no lead (the label of none is LEAD_RANGE)


@dataclass
class SpeedControl:
    """Throttle and brake from a predicted target speed: the expert's PI on the speed error (its gains).

    Why: a policy that outputs throttle directly learns inertia (it copies its own speed, CILRS); a target
    speed is a statement about the scene, and the controller turns a predicted stop into braking at once
    (TransFuser++ and TCP drive their targets through controllers the same way).
    """

    kp: float = _EXPERT.kp
    ki: float = _EXPERT.ki
    integral_limit: float = _EXPERT.integral_limit
    max_throttle: float = _EXPERT.max_throttle
    brake_gain: float = _EXPERT.brake_gain
    brake_deadband: float = _EXPERT.brake_deadband
    stop_speed: float = 0.3  # m/s: a target below this, when nearly standing, holds the brake
    dt: float = DT
    integral: float = 0.0

    def reset(self) -> None:
        self.integral = 0.0

    def __call__(self, target: float, speed: float) -> tuple[float, float]:
        if target < self.stop_speed and speed < 0.5:
            self.integral = 0.0
            return 0.0, 1.0
        error = target - speed
        u = self.kp * error + self.ki * self.integral
        if not (u >= self.max_throttle and error > 0):
            self.integral = float(np.clip(self.integral + error * self.dt, -self.integral_limit, self.integral_limit))
        if u < -self.brake_deadband:
            return 0.0, float(np.clip(-u * self.brake_gain, 0.0, 1.0))
        return float(np.clip(u, 0.0, self.max_throttle)), 0.0


# "stop" with a release (`stop_release` seconds, yawil.policy.speed): the lead-stop class is ignored for
# STOP_CREEP seconds once it alone has held the car standing that long; then it is armed again.
STOP_CREEP = 2.0  # s: TransFuser++'s creep is 1.5 s (carla_garage, sensor_agent.py); ours drives the head's target
STANDING = 0.1  # m/s: under this the car counts as standing (carla_garage's stuck detector uses the same)


@dataclass
class StopRelease:
    """When to ignore the lead-stop class: it fired where no car stands (a false alarm seen on a straight
    empty road, docs/experiments.md 2026-12-02, fourth session) and, the picture frozen once the car stands,
    it keeps firing for ever. After `patience` seconds standing with the class the only reason to stand (the
    head's own target speed would drive), the car drives by the head's target for `creep` seconds, so the
    picture changes; a real standing car ahead is found again by the class once the creep ends.
    Why a timer: a single frame cannot tell a false alarm from a real queue; TransFuser++ and TCP restart
    stuck agents the same way (a stuck detector, then a forced creep)."""

    patience: float
    creep: float = STOP_CREEP
    dt: float = DT
    stood: int = 0  # steps standing held by the class alone
    creep_left: int = 0  # steps of the creep still to drive

    def reset(self) -> None:
        self.stood = self.creep_left = 0

    def released(self, speed: float, holding: bool) -> bool:
        """One step: whether the class is ignored now. `holding`: it fires while the head would drive."""
        if self.creep_left > 0:
            self.creep_left -= 1
            return True
        self.stood = self.stood + 1 if (holding and speed < STANDING) else 0
        if self.stood >= round(self.patience / self.dt):
            self.stood, self.creep_left = 0, round(self.creep / self.dt) - 1
            return True
        return False


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


class Agent:
    """Drives with a trained model. Options for the noise experiment (Table II): yaw_noise_deg and
    command_noise_p with their readings yaw_noise_mode and command_noise_mode (`yawil.guidance`: compute_guidance,
    CommandNoise), seed (the noise is drawn from a numpy Generator seeded with it)."""

    def __init__(
        self,
        model: torch.nn.Module,
        norm: Norm,
        guidance_config: GuidanceConfig,
        *,
        device: str = "cpu",
        precision: str = "auto",
        channels_last: str = "auto",
        post: PostProcess | None = None,
        yaw_noise_deg: float = 0.0,
        command_noise_p: float = 0.0,
        seed: int = 0,
        speed_control: bool | str | None = False,
        yaw_noise_mode: str = "raw",
        command_noise_mode: str = "burst-start",
        stop_release: float = 0.0,
    ) -> None:
        if yaw_noise_deg < 0.0:
            raise ValueError(f"yaw_noise_deg={yaw_noise_deg!r}: expected >= 0 degrees")
        if yaw_noise_mode not in YAW_NOISE_MODES:
            raise ValueError(f"yaw_noise_mode={yaw_noise_mode!r}: expected one of {', '.join(YAW_NOISE_MODES)}")
        if command_noise_mode not in COMMAND_NOISE_MODES:
            raise ValueError(f"command_noise_mode={command_noise_mode!r}: expected one of {', '.join(COMMAND_NOISE_MODES)}")
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
        name = getattr(model, "name", type(model).__name__)
        if yaw_noise_deg > 0 and self.kind not in ("yaw", "sim_yaw"):
            raise ValueError(f"yaw noise perturbs yaw guidance; {name} takes {self.kind or 'no'} guidance")
        if command_noise_p > 0 and not self.uses_command:
            raise ValueError(f"command noise perturbs the high-level command; {name} takes no command")
        self.post = post or PostProcess()
        self.speed_mode = speed_control_mode(speed_control)
        if self.speed_mode is not None and getattr(model, "aux_head", None) is None:
            raise ValueError(f"speed_control needs a model with an aux head (trained with --model-arg aux=true); "
                             f"{getattr(model, 'name', type(model).__name__)} has none")
        if self.speed_mode == "stop" and not getattr(model, "lead_stop", False):
            raise ValueError(f"speed_control 'stop' needs a model with the lead-stop output (--model-arg lead_stop=true); "
                             f"{getattr(model, 'name', type(model).__name__)} has none")
        self.speed_control: SpeedControl | None = SpeedControl() if self.speed_mode is not None else None
        release = check_stop_release(stop_release, self.speed_mode)
        self.stop_release: StopRelease | None = StopRelease(release) if release else None
        self.yaw_noise_deg = float(yaw_noise_deg)
        self.command_noise_p = float(command_noise_p)
        self.yaw_noise_mode = yaw_noise_mode
        self.command_noise_mode = command_noise_mode
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        self._command_noise = self._new_command_noise() if self.command_noise_p > 0 else None
        self._hint: int | None = None
        self.last: StepOutput | None = None
        self.checkpoint_path: str | None = None

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike[str], device: str = "cpu", **options: Any) -> Agent:
        """Rebuild model, normalisation and guidance config from a yawil checkpoint (best.pt or last.pt)."""
        ckpt = load_checkpoint(path, map_location="cpu")
        model = model_from_checkpoint(ckpt)
        config = GuidanceConfig.from_dict(ckpt["guidance_config"])
        agent = cls(model, Norm.from_dict(ckpt["norm"]), config, device=device, **options)
        agent.checkpoint_path = str(path)
        return agent

    @property
    def name(self) -> str:
        return str(getattr(self.model, "name", type(self.model).__name__))

    def reset(self, seed: int | None = None) -> None:
        """Start an episode: forget the route projection and any command-noise burst.

        The noise stream carries on across episodes unless `seed` restarts it.
        """
        self._hint = None
        self.last = None
        if self.speed_control is not None:
            self.speed_control.reset()
        if self.stop_release is not None:
            self.stop_release.reset()
        if seed is not None:
            self.seed = int(seed)
            self._rng = np.random.default_rng(self.seed)
            if self._command_noise is not None:
                self._command_noise = self._new_command_noise()
        if self._command_noise is not None:
            self._command_noise.reset()

    def _new_command_noise(self) -> CommandNoise:
        return CommandNoise(self.command_noise_p, self._rng, mode=self.command_noise_mode)

    @property
    def spec(self) -> InputSpec:
        """How this agent's model takes its inputs (`yawil.policy.inputs`): normalisation, kind, command, runtime."""
        return InputSpec(self.norm, self.kind, self.uses_command, self.runtime)

    def model_inputs(self, obs: Observation) -> tuple[ModelInputs, np.ndarray | None, int | None]:
        """The network inputs of one observation (batch of 1), plus the raw guidance and command index.

        The noise stream is drawn in a fixed order: the yaw noise of the guidance, then the command noise.
        """
        img = check_observation_image(obs)
        guidance_raw: np.ndarray | None = None
        if self.kind is not None:
            guidance_raw, self._hint = observation_guidance(
                obs,
                self.guidance_config,
                self.kind,
                hint=self._hint,
                yaw_noise_deg=self.yaw_noise_deg,
                rng=self._rng,
                yaw_noise_mode=self.yaw_noise_mode,
            )
        option: int | None = None
        command_idx: int | None = None
        if self.uses_command:
            option = int(obs.command)
            if self._command_noise is not None:
                option = self._command_noise(option)
            command_idx = command_index(option)
        return self.spec.from_frame(img, obs.speed, guidance_raw, option), guidance_raw, command_idx

    def inputs(self, obs: Observation) -> tuple[dict[str, torch.Tensor | None], np.ndarray | None, int | None]:
        """`model_inputs` with the inputs as a dict by name (image, speed, guidance, command)."""
        x, guidance_raw, command_idx = self.model_inputs(obs)
        return x.as_dict(), guidance_raw, command_idx

    @torch.inference_mode()
    def act(self, obs: Observation) -> Control:
        x, guidance_raw, command_idx = self.model_inputs(obs)
        with self.runtime.autocast():
            out = x.forward(self.model)
        actions = out.actions[0].float().cpu().numpy()
        speed = float(self.norm.speed_inverse(out.speed[0, 0].float()).cpu())
        target_speed = head_target = lead_distance = lead_speed = lead_stop = None
        ego_speed = max(float(obs.speed), 0.0)
        if out.aux is not None:
            aux = out.aux[0].float().cpu()
            target_speed = head_target = max(0.0, float(self.norm.speed_inverse(aux[0])))
            lead_distance = max(0.0, float(aux[1]) * LEAD_RANGE)
            lead_speed = max(0.0, float(self.norm.speed_inverse(aux[2])))
            if self.speed_mode == "lead" and lead_distance < LEAD_SEEN:
                target_speed = min(target_speed, hazard_speed(lead_distance, lead_speed, LEAD_DECEL))
            if len(aux) > len(AUX_NAMES):
                lead_stop = float(torch.sigmoid(aux[len(AUX_NAMES)]))
                fires = self.speed_mode == "stop" and lead_stop > LEAD_STOP_FIRES
                if self.stop_release is not None:  # ticked on every step, so a creep runs its course
                    alone = fires and head_target >= SpeedControl.stop_speed  # the head itself would drive
                    fires = fires and not self.stop_release.released(ego_speed, alone)
                if fires:
                    target_speed = 0.0
        if self.speed_control is not None and target_speed is not None:
            throttle, brake = self.speed_control(target_speed, ego_speed)
            actions = np.array([actions[0], throttle, brake], dtype=np.float32)
        control = self.post(actions, float(obs.speed))
        self.last = StepOutput(
            actions=actions,
            speed=speed,
            attention=[a[0].float().cpu().numpy() for a in out.attention],
            branches=None if out.branches is None else out.branches[0].float().cpu().numpy(),
            guidance=guidance_raw,
            command=command_idx,
            control=control,
            target_speed=target_speed,
            head_target_speed=head_target,
            lead_distance=lead_distance,
            lead_speed=lead_speed,
            lead_stop=lead_stop,
        )
        return control
