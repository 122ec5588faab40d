"""How a learned agent makes throttle and brake (`speed_control`), named without torch so that the command
lines and the benchmark's records can use the names; the controllers themselves are in `yawil.agent`.

None: the network's own throttle and brake; "target": a PI controller on the aux head's target speed;
"lead": the same with the target capped by the expert's braking rule on the aux head's predicted lead vehicle;
"stop": the same with the target set to 0 while the lead-stop output (a model built with lead_stop=true) says a
standing vehicle is close ahead (probability over 0.5).
"""

from __future__ import annotations

SPEED_CONTROLS: tuple[str, ...] = ("target", "lead", "stop")


def speed_control_mode(value: bool | str | None) -> str | None:
    """Normalise the option: False/None -> None, True -> "target" (its meaning before "lead" existed)."""
    if value is None or value is False:
        return None
    if value is True:
        return "target"
    if value not in SPEED_CONTROLS:
        raise ValueError(f"speed_control={value!r}: expected one of {', '.join(SPEED_CONTROLS)} (or true / false)")
    return str(value)
