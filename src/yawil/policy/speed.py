"""How a learned agent makes throttle and brake (`speed_control`) and where its network runs (`--engine`), named
without torch so that the command lines and the benchmark's records can use the names; the controllers are in
`yawil.policy.drive`, the engines in `yawil.policy.engine`.

None: the network's own throttle and brake; "target": a PI controller on the aux head's target speed;
"lead": the same with the target capped by the expert's braking rule on the aux head's predicted lead vehicle;
"stop": the same with the target set to 0 while the lead-stop output (a model built with lead_stop=true) says a
standing vehicle is close ahead (probability over 0.5); with a release (`stop_release` seconds, 0 = never) the
output is ignored for a short creep once it alone has held the car standing that long (`yawil.agent.StopRelease`);
with a hold (`stop_hold` seconds) the stop outlasts the output by that long (`yawil.policy.drive.StopHold`); with
a gate (`stop_gate` metres) a stand counts toward the release only while the predicted lead distance is that far.
With a light hold (`light_hold` seconds, any speed control) a standing car does not start while the aux head's
light output fires (a red or yellow stop line within 30 m), for at most that long a stand
(`yawil.policy.drive.LightHold`).
"""

from __future__ import annotations

import argparse
import math
from typing import Any

SPEED_CONTROLS: tuple[str, ...] = ("target", "lead", "stop")
# the drive options a DAgger learner takes (a card names them too: yawil.zoo.DRIVE_KEYS, kept apart by the import rule)
DRIVE_OPTIONS: tuple[str, ...] = ("speed_control", "stop_release", "stop_creep", "stop_hold", "stop_gate", "light_hold")
ENGINES: tuple[str, ...] = ("auto", "torch", "openvino", "onnxruntime", "openvino-int8")


def speed_control_mode(value: bool | str | None) -> str | None:
    """Normalise the option: False/None -> None, True -> "target" (its meaning before "lead" existed)."""
    if value is None or value is False:
        return None
    if value is True:
        return "target"
    if value not in SPEED_CONTROLS:
        raise ValueError(f"speed_control={value!r}: expected one of {', '.join(SPEED_CONTROLS)} (or true / false)")
    return str(value)


def _stop_seconds(name: str, seconds: float, mode: str | None, zero: str) -> float:
    """A "stop" mode timer as a float, refused in one line unless >= 0 s and (when > 0) with the "stop" mode."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"{name}={seconds!r}: expected seconds >= 0 (0: {zero})")
    if seconds and mode != "stop":
        raise ValueError(f"{name}={seconds!r} applies to --speed-control stop, not {mode!r}")
    return float(seconds)


def check_stop_release(seconds: float, mode: str | None) -> float:
    """`stop_release` as a float (`_stop_seconds`)."""
    return _stop_seconds("stop_release", seconds, mode, "never release")


def _release_metres(name: str, metres: float, release: float, zero: str) -> float:
    """A setting of the stop release in metres as a float, refused in one line unless >= 0 m and (when > 0) with
    a release."""
    if isinstance(metres, bool) or not isinstance(metres, (int, float)) or not (math.isfinite(metres) and metres >= 0):
        raise ValueError(f"{name}={metres!r}: expected metres >= 0 (0: {zero})")
    if metres and not release:
        raise ValueError(f"{name}={metres!r} applies to a stop release (--stop-release SECONDS > 0)")
    return float(metres)


def check_stop_creep(metres: float, release: float) -> float:
    """`stop_creep` as a float (`_release_metres`)."""
    return _release_metres("stop_creep", metres, release, "the creep lasts its 2 s")


def check_stop_hold(seconds: float, mode: str | None) -> float:
    """`stop_hold` as a float (`_stop_seconds`)."""
    return _stop_seconds("stop_hold", seconds, mode, "no hold")


def check_light_hold(seconds: float, mode: str | None) -> float:
    """`light_hold` as a float: seconds >= 0 (0: off), > 0 only with a speed control (it reads the aux head)."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"light_hold={seconds!r}: expected seconds >= 0 (0: off)")
    if seconds and mode is None:
        raise ValueError(f"light_hold={seconds!r} applies to a speed control (--speed-control), which reads the aux "
                         "head's light output")
    return float(seconds)


def check_stop_gate(metres: float, release: float) -> float:
    """`stop_gate` as a float (`_release_metres`)."""
    return _release_metres("stop_gate", metres, release, "every stand counts")


def add_speed_control_arguments(p: argparse.ArgumentParser, what: str = "") -> None:
    """--speed-control and --stop-release, the same on bench, trace, select and dagger."""
    p.add_argument("--speed-control", nargs="?", const="target", default=False, choices=SPEED_CONTROLS,
                   help=(what or "learned agents with an aux head: ") + "throttle and brake from the predicted target "
                        "speed (target, the default of the bare flag), or that speed capped by the expert's braking "
                        "rule on the predicted lead vehicle (lead), or set to 0 while the lead-stop output fires "
                        "(stop; models built with lead_stop=true); docs/training.md")
    p.add_argument("--stop-release", type=float, default=0.0, metavar="SECONDS",
                   help="with --speed-control stop: after this many seconds standing with the lead-stop output the "
                        "only reason, ignore it for a 2 s creep (default 0: never)")
    p.add_argument("--stop-hold", type=float, default=0.0, metavar="SECONDS",
                   help="with --speed-control stop: once the lead-stop output fires, the stop holds until it has been "
                        "off this long (default 0: it ends with the output); the release still applies")
    p.add_argument("--stop-creep", type=float, default=0.0, metavar="METRES",
                   help="with --stop-release: the creep also ends, and the lead-stop output counts again, once the car "
                        "has moved this far (default 0: the creep lasts its 2 s)")
    p.add_argument("--stop-gate", type=float, default=0.0, metavar="METRES",
                   help="with --stop-release: a stand counts toward the release only while the predicted lead distance "
                        "is at least this far, so a car the net itself places close ahead is not crept into (default "
                        "0: every stand counts)")
    p.add_argument("--light-hold", type=float, default=0.0, metavar="SECONDS",
                   help="with --speed-control: a standing car does not start while the aux head's light output fires "
                        "(a red or yellow stop line within 30 m), for at most this long a stand (default 0: off)")


def given_drive(args: argparse.Namespace) -> dict[str, Any]:
    """--speed-control and the stop release's options (`add_speed_control_arguments`) exactly as given, as
    keyword options of `yawil.bench.runner.AgentSpec` and `yawil.agent.Agent.from_checkpoint`."""
    return {"speed_control": args.speed_control, "stop_release": args.stop_release,
            "stop_creep": getattr(args, "stop_creep", 0.0), "stop_hold": getattr(args, "stop_hold", 0.0),
            "stop_gate": getattr(args, "stop_gate", 0.0), "light_hold": getattr(args, "light_hold", 0.0)}


def add_engine_arguments(p: argparse.ArgumentParser, batched: bool = False) -> None:
    """--engine (and, where episodes run on workers, --episodes-per-worker), the same on every command that drives."""
    p.add_argument("--engine", default="auto", choices=ENGINES,
                   help="where a learned agent's network runs: auto (default: torch in bf16 on a CPU with native bf16 "
                        "and on CUDA, onnxruntime in fp32 on other CPUs), or one of them (openvino: opt-in, pip install "
                        "openvino; openvino-int8: int8 convolutions calibrated on expert frames, pip install openvino "
                        "nncf); the engine and its precision are part of the results (docs/decisions.md)")
    if batched:
        p.add_argument("--episodes-per-worker", type=int, default=None, metavar="K",
                       help="episodes each worker drives at once, one batched forward per step (default 1; K > 1 is "
                            "faster where a batch pays, and not yet shown to give K=1's records on long episodes: "
                            "docs/performance.md)")
