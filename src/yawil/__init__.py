"""yawil: yaw-guided end-to-end imitation learning for urban driving.

The loop, one way through the code:
sim -> expert/agent -> data -> train -> agent -> bench -> report.

Importing this package registers the Gymnasium environments `yawil/Town01-v0`, `yawil/Town02-v0` and
`yawil/Square-v0`, so `import gymnasium as gym, yawil; gym.make("yawil/Town01-v0")` works. Registration only
imports gymnasium: the simulator (and never torch) loads on `gym.make`, through the entry point's string.
"""

__version__ = "0.1.0"

# (id, town) of each registered environment; entry point yawil.gym_env:make_env (docs/simulator.md)
GYM_ENVS: tuple[tuple[str, str], ...] = (
    ("yawil/Town01-v0", "town01"),
    ("yawil/Town02-v0", "town02"),
    ("yawil/Square-v0", "square"),
)


def _register_gym_envs() -> None:
    try:
        import gymnasium
    except ModuleNotFoundError:  # pragma: no cover - gymnasium is a hard dependency
        return
    for env_id, town in GYM_ENVS:
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point="yawil.gym_env:make_env", kwargs={"town": town})


_register_gym_envs()
