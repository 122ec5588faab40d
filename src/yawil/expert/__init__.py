"""The privileged expert: the teacher of every learned agent and the upper bound of the benchmark (docs/expert.md).

- `config`: `ExpertConfig`, every setting
- `route`: the route as the expert reads it (arc length, curvature, junctions, projection)
- `hazards`: `Hazard` and the scan for every stop point ahead (lights, vehicles, pedestrians, junctions, goal)
- `driver`: `Expert` (pure pursuit and a speed PID towards the least target speed), `ExpertState`, `expert_info`

The names used elsewhere are importable from here: `from yawil.expert import Expert, ExpertConfig`.
"""

from yawil.expert.config import ExpertConfig
from yawil.expert.driver import Expert, ExpertState, expert_info, hazard_speed
from yawil.expert.hazards import Hazard

__all__ = ["Expert", "ExpertConfig", "ExpertState", "Hazard", "expert_info", "hazard_speed"]
