"""yawil: yaw-guided end-to-end imitation learning for urban driving.

The loop, one way through the code:
sim -> expert/agent -> data -> train -> agent -> bench -> report.
"""

__version__ = "0.1.0"
