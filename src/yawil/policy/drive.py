"""Drive-time behaviours: what happens between a network's outputs and a Control, and what an episode keeps.

    settings = DriveSettings(speed_control="stop", stop_release=10.0)   # checked once, against the model
    state = settings.episode(seed)        # one per episode: projection hint, noise streams, controllers
    control = settings.control(raw, state, ego_speed)

Each behaviour is a small piece with its own state, composed by `DriveSettings` (Gymnasium composes wrappers the
same way): yaw noise and command noise (the noise experiment, Table II; `yawil.guidance`), target-speed control
(`SpeedControl`, with the "lead" cap and the "stop" class), the stop release (`StopRelease`), post-processing
(`PostProcess`). The network itself runs elsewhere (`yawil.policy.engine`), on a batch: nothing here depends on
which episodes share a batch, so an episode drives the same alone or among others.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from yawil.data.schema import LEAD_RANGE
from yawil.expert import ExpertConfig, hazard_speed
from yawil.guidance import COMMAND_NOISE_MODES, YAW_NOISE_MODES, CommandNoise
from yawil.models.base import AUX_NAMES, LEAD_STOP_FIRES
from yawil.policy.speed import (
    check_light_hold,
    check_stop_creep,
    check_stop_gate,
    check_stop_hold,
    check_stop_release,
    speed_control_mode,
)
from yawil.sim.types import DT, Control


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
LIGHT_OUTPUT = AUX_NAMES.index("light_ahead")
LEAD_STOP_OUTPUT = len(AUX_NAMES)  # the lead-stop logit follows the aux outputs (models.base.aux_width)
LIGHT_FIRES = 0.5  # the light output's probability over which it fires, as the lead-stop class's
STANDING = 0.1  # m/s: under this the car counts as standing (carla_garage's stuck detector uses the same)


@dataclass
class StopRelease:
    """When to ignore the lead-stop class: it fired where no car stands (a false alarm seen on a straight
    empty road, docs/experiments.md 2026-12-02) and, the picture frozen once the car stands, it keeps firing
    for ever. After `patience` seconds standing with the class the only reason to stand (the head's own target
    speed would drive), the car drives by the head's target for `creep` seconds, so the picture changes; a
    real standing car ahead is found again by the class once the creep ends.
    Why a timer: a single frame cannot tell a false alarm from a real queue; TransFuser++ and TCP restart
    stuck agents the same way (a stuck detector, then a forced creep)."""

    patience: float
    creep: float = STOP_CREEP
    creep_distance: float = 0.0  # m: the creep also ends once the car has moved this far (0: time only)
    dt: float = DT
    stood: int = 0  # steps standing held by the class alone
    creep_left: int = 0  # steps of the creep still to drive
    moved: float = 0.0  # m driven in the current creep

    def reset(self) -> None:
        self.stood = self.creep_left = 0
        self.moved = 0.0

    def released(self, speed: float, holding: bool, clear: bool = True) -> bool:
        """One step: whether the class is ignored now. `holding`: it fires while the head would drive; `clear`:
        the head's lead-distance regression sees no car close (`DriveSettings.stop_gate`): a standing step that is
        not clear neither counts toward the patience nor resets it (the regression's odd frame on a false alarm
        must not restart the wait)."""
        if self.creep_left > 0:
            self.moved += max(0.0, speed) * self.dt
            if self.creep_distance > 0 and self.moved >= self.creep_distance:
                self.creep_left = 0  # moved enough for a new picture: the class is armed again from this step
            else:
                self.creep_left -= 1
                return True
        if not (holding and speed < STANDING):
            self.stood = 0
        elif clear:
            self.stood += 1
        if self.stood >= round(self.patience / self.dt):
            self.stood, self.creep_left, self.moved = 0, round(self.creep / self.dt) - 1, 0.0
            return True
        return False


@dataclass
class StopHold:
    """The "stop" class's hysteresis: once it fires, the stop holds until it has been off for `hold` seconds.
    Why: a single-frame class flickers off for a frame or two while a standing car fills the picture at close
    range (traced: a rear-end on the selection set, docs/experiments.md 2026-12-07), and the target-speed
    controller then drives into the car; a brake signal held for a moment is the usual cure (hysteresis)."""

    hold: float
    dt: float = DT
    left: int = 0  # steps the stop still holds after the class went off

    def reset(self) -> None:
        self.left = 0

    def __call__(self, fires: bool) -> bool:
        if fires:
            self.left = round(self.hold / self.dt)
            return True
        if self.left > 0:
            self.left -= 1
            return True
        return False


@dataclass
class LightHold:
    """A car the head itself stopped does not start while the aux head's light output fires (a red or yellow stop
    line within LIGHT_RANGE m), for at most `limit` seconds of one stand. Why: traced on town01, the head's target
    speed rises seconds before the light turns green (it starts from the scene, crossing traffic stopping), and the
    car drove into the crossing's pedestrians or traffic; the light output, trained on the light itself, says
    when to wait. Only a stand the head made (its target under the controller's stop speed at some standing step):
    one the lead-stop class made may be 30 m short of the line, where the expert would drive on (traced: static
    timeouts when every stand was held). The limit bounds what a false alarm costs."""

    limit: float
    dt: float = DT
    held: int = 0  # steps this stand has been held by the light
    armed: bool = False  # the head itself stopped the car in this stand

    def reset(self) -> None:
        self.held, self.armed = 0, False

    def __call__(self, speed: float, fires: bool, head_stops: bool = True) -> bool:
        """One step: whether the car is kept standing now. `head_stops`: the head's own target says stop."""
        if speed >= STANDING:
            self.held, self.armed = 0, False  # moving: the rule is for starts only
            return False
        self.armed = self.armed or head_stops
        if not (fires and self.armed) or self.held >= round(self.limit / self.dt):
            return False
        self.held += 1
        return True


@dataclass
class EpisodeState:
    """What one episode keeps between steps: the route-projection hint, its noise stream (seeded per episode),
    a command-noise burst, the speed controller's integral and the stop release's timers."""

    rng: np.random.Generator
    command_noise: CommandNoise | None = None
    speed_control: SpeedControl | None = None
    stop_release: StopRelease | None = None
    stop_hold: StopHold | None = None
    light_hold: LightHold | None = None
    hint: int | None = None


@dataclass(frozen=True)
class Decision:
    """One row's longitudinal reading of the aux head (m/s and m; None where the model has no such output)."""

    actions: np.ndarray  # (3,) steer, throttle, brake before post-processing (throttle and brake from the
    # speed controller when one drives)
    target_speed: float | None = None  # after any cap or stop
    head_target_speed: float | None = None  # the aux head's own
    lead_distance: float | None = None
    lead_speed: float | None = None
    lead_stop: float | None = None
    light: float | None = None  # the light output's probability (a red or yellow stop line within LIGHT_RANGE m)


@dataclass(frozen=True)
class DriveSettings:
    """How a trained model is driven: the one place these settings are named and checked.

    `speed_control`: None (the network's throttle and brake), "target", "lead" or "stop" (`yawil.policy.speed`);
    `stop_release`: seconds (with "stop"); `stop_creep`: metres after which a release's creep ends (0: its 2 s);
    `stop_hold`: seconds the stop outlasts the class (`StopHold`); `stop_gate`: metres of predicted lead distance
    under which a stand does not count toward the release (0: every stand counts); `light_hold`: seconds a standing
    car at most waits while the light output fires (`LightHold`; 0: off); `yaw_noise_deg` / `command_noise_p` with their readings (Table II,
    `yawil.guidance`); `post`: the clipping rules. A zoo model's card names the settings its figures were
    measured with (`card.json` "drive"), and `yawil.agent.Agent.from_checkpoint("zoo:NAME")` uses them.
    """

    speed_control: str | None = None
    stop_release: float = 0.0
    stop_creep: float = 0.0
    stop_hold: float = 0.0
    stop_gate: float = 0.0
    light_hold: float = 0.0
    yaw_noise_deg: float = 0.0
    command_noise_p: float = 0.0
    yaw_noise_mode: str = "raw"
    command_noise_mode: str = "burst-start"
    post: PostProcess = field(default_factory=PostProcess)

    def __post_init__(self) -> None:
        object.__setattr__(self, "speed_control", speed_control_mode(self.speed_control))  # True -> "target"
        object.__setattr__(self, "stop_release", check_stop_release(self.stop_release, self.speed_control))
        object.__setattr__(self, "stop_creep", check_stop_creep(self.stop_creep, self.stop_release))
        object.__setattr__(self, "stop_hold", check_stop_hold(self.stop_hold, self.speed_control))
        object.__setattr__(self, "stop_gate", check_stop_gate(self.stop_gate, self.stop_release))
        object.__setattr__(self, "light_hold", check_light_hold(self.light_hold, self.speed_control))
        if isinstance(self.yaw_noise_deg, bool) or not float(self.yaw_noise_deg) >= 0.0:
            raise ValueError(f"yaw_noise_deg={self.yaw_noise_deg!r}: expected >= 0 degrees")
        if isinstance(self.command_noise_p, bool) or not 0.0 <= float(self.command_noise_p) <= 1.0:
            raise ValueError(f"command_noise_p={self.command_noise_p!r}: expected a probability in [0, 1]")
        if self.yaw_noise_mode not in YAW_NOISE_MODES:
            raise ValueError(f"yaw_noise_mode={self.yaw_noise_mode!r}: expected one of {', '.join(YAW_NOISE_MODES)}")
        if self.command_noise_mode not in COMMAND_NOISE_MODES:
            raise ValueError(f"command_noise_mode={self.command_noise_mode!r}: "
                             f"expected one of {', '.join(COMMAND_NOISE_MODES)}")
        if not isinstance(self.post, PostProcess):
            raise ValueError(f"post={self.post!r}: expected a PostProcess")

    @classmethod
    def from_options(cls, options: dict[str, Any]) -> DriveSettings:
        """From keyword options (speed_control, stop_release, yaw_noise_deg, ...): an unknown name is refused."""
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"unknown drive option(s) {', '.join(unknown)}: expected {', '.join(sorted(known))}")
        speed = options.get("speed_control")
        return cls(**{**options, "speed_control": None if speed is False else speed})

    def replace(self, **changes: Any) -> DriveSettings:
        return replace(self, **changes)

    def check(self, model: Any) -> DriveSettings:
        """Refuse, in one line, a setting this model cannot take (noise on an input it lacks, a speed control
        without the aux head it reads)."""
        name = getattr(model, "name", type(model).__name__)
        kind = getattr(model, "guidance", None)
        if self.yaw_noise_deg > 0 and kind not in ("yaw", "sim_yaw"):
            raise ValueError(f"yaw noise perturbs yaw guidance; {name} takes {kind or 'no'} guidance")
        if self.command_noise_p > 0 and not getattr(model, "uses_command", False):
            raise ValueError(f"command noise perturbs the high-level command; {name} takes no command")
        if self.speed_control is not None and getattr(model, "aux_head", None) is None:
            raise ValueError(f"speed_control needs a model with an aux head (trained with --model-arg aux=true); "
                             f"{name} has none")
        if self.speed_control == "stop" and not getattr(model, "lead_stop", False):
            raise ValueError(f"speed_control 'stop' needs a model with the lead-stop output "
                             f"(--model-arg lead_stop=true); {name} has none")
        return self

    def as_dict(self) -> dict[str, Any]:
        """The settings that differ from the defaults, by name (a card's "drive", a record's options)."""
        out: dict[str, Any] = {}
        for name in ("speed_control", "stop_release", "stop_creep", "stop_hold", "stop_gate", "light_hold", "yaw_noise_deg",
                     "command_noise_p"):
            if getattr(self, name):
                out[name] = getattr(self, name)
        if self.yaw_noise_deg:
            out["yaw_noise_mode"] = self.yaw_noise_mode
        if self.command_noise_p:
            out["command_noise_mode"] = self.command_noise_mode
        return out

    def episode(self, seed: int) -> EpisodeState:
        """A fresh episode's state; its noise stream is a numpy Generator seeded with `seed`."""
        rng = np.random.default_rng(int(seed))
        return EpisodeState(
            rng=rng,
            command_noise=CommandNoise(self.command_noise_p, rng, mode=self.command_noise_mode)
            if self.command_noise_p > 0 else None,
            speed_control=SpeedControl() if self.speed_control is not None else None,
            stop_release=StopRelease(self.stop_release, creep_distance=self.stop_creep) if self.stop_release else None,
            stop_hold=StopHold(self.stop_hold) if self.stop_hold else None,
            light_hold=LightHold(self.light_hold) if self.light_hold else None,
        )

    def command(self, option: int, state: EpisodeState) -> int:
        """The road option the network is given: the true one, or a burst of wrong ones (command noise)."""
        return state.command_noise(option) if state.command_noise is not None else option

    def decide(self, actions: np.ndarray, aux: np.ndarray | None, speed_of: Any, state: EpisodeState,
               ego_speed: float) -> Decision:
        """Throttle and brake of one row: the network's own, or the speed controller's on the aux head's target
        (with the "lead" cap or the "stop" class and its release). `speed_of` turns a normalised speed output
        into m/s (the checkpoint's `Norm.speed_inverse`)."""
        if aux is None:
            return Decision(actions)
        target = head = max(0.0, float(speed_of(aux[0])))
        lead_distance = max(0.0, float(aux[1]) * LEAD_RANGE)
        lead_speed = max(0.0, float(speed_of(aux[2])))
        lead_stop: float | None = None
        light = float(1.0 / (1.0 + np.exp(-np.float64(aux[LIGHT_OUTPUT]))))  # a logit (BCE, yawil.learn.loss)
        if self.speed_control == "lead" and lead_distance < LEAD_SEEN:
            target = min(target, hazard_speed(lead_distance, lead_speed, LEAD_DECEL))
        if len(aux) > LEAD_STOP_OUTPUT:
            lead_stop = float(1.0 / (1.0 + np.exp(-np.float64(aux[LEAD_STOP_OUTPUT]))))
            fires = self.speed_control == "stop" and lead_stop > LEAD_STOP_FIRES
            if state.stop_hold is not None:  # before the release: a creep also ignores a held stop
                fires = state.stop_hold(fires)
            if state.stop_release is not None:  # ticked on every step, so a creep runs its course
                alone = fires and head >= SpeedControl.stop_speed  # the head itself would drive
                clear = lead_distance >= self.stop_gate  # the regression sees no car close (0: always)
                fires = fires and not state.stop_release.released(ego_speed, alone, clear)
            if fires:
                target = 0.0
        if state.light_hold is not None and state.light_hold(ego_speed, light > LIGHT_FIRES,
                                                             head < SpeedControl.stop_speed):
            target = 0.0
        if state.speed_control is not None:
            throttle, brake = state.speed_control(target, ego_speed)
            actions = np.array([actions[0], throttle, brake], dtype=np.float32)
        return Decision(actions, target, head, lead_distance, lead_speed, lead_stop, light)
