"""Runs benchmark episodes and appends one JSON line per finished episode to the results folder.

- One world and one agent per worker; `workers > 1` (or Ray) runs episodes on workers (yawil.executor: spawned
  processes or Ray actors) while the calling process alone writes the file (so lines never interleave).
- Resume: episodes whose key is already in the file are skipped; see `yawil.bench.records`.
- The camera is on for learned agents and off for the expert (it drives from privileged state and needs no
  pixels); `camera=True` forces it (e.g. to record videos of the expert).
- Agent and world seeds per episode come from `Episode.world_seed`, so a rerun gives the same records.
"""

from __future__ import annotations

import inspect
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from yawil.bench.metrics import EpisodeTracker, subsample_route
from yawil.bench.records import PROTOCOL, EpisodeLog, check_run_info, episode_key
from yawil.bench.suites import Episode
from yawil.executor import ExecutorConfig, for_worker, open_executor
from yawil.locking import folder_lock
from yawil.policy.speed import (
    check_light_hold,
    check_stop_creep,
    check_stop_gate,
    check_stop_hold,
    check_stop_release,
    given_drive,
    speed_control_mode,
)
from yawil.sim.types import Control, Observation, World

EXPERT = "expert"
# K when none is given: 1. Batched evaluation (K > 1) is opt-in until its records are shown to equal K=1's on long
# episodes: on the 16-episode throughput set K=4 changed 2 (OpenVINO) and 11 (torch) of the 16 records, although
# the engines' rows are batch-invariant and one episode drives the same alone and among others; and on a CPU
# without AMX it was at most 1.07x faster (docs/performance.md "Evaluation throughput").
EPISODES_PER_WORKER = 1


class DrivingAgent(Protocol):
    def reset(self) -> None: ...

    def act(self, obs: Observation) -> Control: ...


@dataclass(frozen=True)
class AgentSpec:
    """What drives: 'expert' or a checkpoint path, plus the noise options of the robustness experiment."""

    agent: str
    yaw_noise_deg: float = 0.0
    command_noise_p: float = 0.0
    speed_control: bool | str = False  # throttle and brake from the aux head: True/"target" or "lead" (yawil.agent)
    yaw_noise_mode: str = "raw"  # readings of the two noises (yawil.guidance.YAW_NOISE_MODES, COMMAND_NOISE_MODES)
    command_noise_mode: str = "burst-start"
    expert_args: tuple[str, ...] = ()  # KEY=VALUE settings of the expert's ExpertConfig (`--expert-arg`)
    # Where a learned agent's model runs: cpu or cuda (`--device`; `agent_device` resolves auto). Each worker
    # process loads its own copy. The expert has no model and ignores it.
    device: str = "cpu"
    stop_release: float = 0.0  # s standing before the "stop" mode's lead-stop class is ignored (yawil.agent.StopRelease)
    engine: str = "auto"  # where a learned agent's network runs (yawil.policy.engine: auto, torch, openvino, ..., ENGINES)
    stop_creep: float = 0.0  # m after which the release's creep ends (yawil.policy.drive.StopRelease; 0: its 2 s)
    stop_hold: float = 0.0  # s the "stop" mode's stop outlasts its class (yawil.policy.drive.StopHold; 0: none)
    stop_gate: float = 0.0  # m of predicted lead distance under which a stand does not count toward the release
    light_hold: float = 0.0  # s a standing car at most waits while the light output fires (LightHold; 0: off)

    @property
    def is_expert(self) -> bool:
        return self.agent == EXPERT

    @property
    def checkpoint(self) -> Path:
        """The checkpoint file of a learned agent: the path given, or a zoo model's (`zoo:NAME`)."""
        if self.agent.startswith("zoo:"):
            from yawil.zoo import resolve_checkpoint

            return resolve_checkpoint(self.agent)
        return Path(self.agent)

    def options(self) -> dict[str, Any]:
        opts: dict[str, Any] = {"yaw_noise_deg": self.yaw_noise_deg, "command_noise_p": self.command_noise_p}
        if self.yaw_noise_deg:  # a reading only where its noise is on: noiseless runs of either are one run
            opts["yaw_noise_mode"] = self.yaw_noise_mode
        if self.command_noise_p:
            opts["command_noise_mode"] = self.command_noise_mode
        if self.speed_control:  # only when set, so the records of earlier runs still match ("target" stays True)
            mode = speed_control_mode(self.speed_control)
            opts["speed_control"] = True if mode == "target" else mode
        if self.stop_release:  # only when set, so the records of earlier runs still match
            opts["stop_release"] = float(self.stop_release)
        if self.stop_creep:  # only when set, so the records of earlier runs still match
            opts["stop_creep"] = float(self.stop_creep)
        if self.stop_hold:  # only when set, so the records of earlier runs still match
            opts["stop_hold"] = float(self.stop_hold)
        if self.stop_gate:  # only when set, so the records of earlier runs still match
            opts["stop_gate"] = float(self.stop_gate)
        if self.light_hold:  # only when set, so the records of earlier runs still match
            opts["light_hold"] = float(self.light_hold)
        if self.device != "cpu" and not self.is_expert:  # only when set, so the records of earlier runs still match
            opts["device"] = self.device
        if not self.is_expert:  # the engine and its precision change the numbers, so a resume must use the same
            opts["engine"] = self.engine_label()
        if self.expert_args:  # the settings that differ from the default expert, by name
            from yawil.expert import ExpertConfig

            opts["expert"] = ExpertConfig.from_items(self.expert_args).changes()
        return opts

    def validate(self, build: bool = True) -> AgentSpec:
        """Every option checked before any episode; `build` also loads the agent once (the checkpoint, the
        engine: seconds), which run_benchmark does after the cheap check of the results folder."""
        if not self.is_expert and not self.checkpoint.is_file():
            raise ValueError(f"--agent {self.agent!r}: expected 'expert', zoo:NAME or the path of a checkpoint file")
        if self.is_expert and (self.yaw_noise_deg or self.command_noise_p or self.speed_control):
            raise ValueError("noise and speed-control options apply to learned agents, not to the expert")
        release = check_stop_release(self.stop_release, speed_control_mode(self.speed_control))
        check_stop_creep(self.stop_creep, release), check_stop_gate(self.stop_gate, release)
        check_stop_hold(self.stop_hold, speed_control_mode(self.speed_control))
        check_light_hold(self.light_hold, speed_control_mode(self.speed_control))
        if self.expert_args and not self.is_expert:
            raise ValueError("--expert-arg applies to --agent expert only")
        if self.is_expert and self.engine != "auto":  # it would be accepted and change nothing
            raise ValueError(f"--engine {self.engine}: applies to learned agents; the expert runs no network")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"--device {self.device!r}: expected cpu or cuda (auto is resolved by agent_device)")
        if self.device == "cuda" and not self.is_expert:
            agent_device("cuda")  # no CUDA device here: one line, before any episode
        if not self.is_expert:
            self.engine_label()  # an unknown engine, or one this device cannot run, fails here
        if self.expert_args:
            from yawil.expert import ExpertConfig

            ExpertConfig.from_items(self.expert_args)  # an unknown or invalid setting fails before any episode
        from yawil.guidance import COMMAND_NOISE_MODES, YAW_NOISE_MODES

        if self.yaw_noise_mode not in YAW_NOISE_MODES or self.command_noise_mode not in COMMAND_NOISE_MODES:
            raise ValueError(f"--yaw-noise {self.yaw_noise_mode!r} / --command-noise {self.command_noise_mode!r}: "
                             f"expected one of {', '.join(YAW_NOISE_MODES)} / {', '.join(COMMAND_NOISE_MODES)}")
        if self.yaw_noise_deg < 0 or not 0 <= self.command_noise_p <= 1:
            raise ValueError(
                f"yaw_noise_deg must be >= 0 and command_noise_p in [0, 1], got {self.yaw_noise_deg}, {self.command_noise_p}"
            )
        if build and not self.is_expert:
            self.build(0)  # an unreadable checkpoint, or an option its model cannot take, fails before any episode
        return self

    def engine_label(self) -> str:
        """engine-precision of a learned agent on the machine it runs on (e.g. openvino-bf16; yawil.policy.engine)."""
        import torch

        from yawil.policy.engine import resolve_engine
        from yawil.policy.runtime import Runtime, resolve_runtime

        # on CUDA the precision resolve_runtime picks (fp16), named without asking for a device the local machine may lack
        runtime = Runtime(torch.device("cuda"), "fp16", True) if self.device == "cuda" else resolve_runtime(self.device)
        return "-".join(resolve_engine(self.engine, runtime))

    def identity(self) -> str:
        """What records name the agent by: 'expert', `zoo:NAME` (the same on every machine; the weights' hash is
        recorded beside it), or the checkpoint's path: relative to the working folder when it lies under it (a
        repository's records then read the same on every clone), else absolute. A resume compares the weights'
        hash, so a moved checkpoint still resumes its folder."""
        if self.is_expert or self.agent.startswith("zoo:"):
            return self.agent
        path = self.checkpoint.resolve()
        try:
            return str(path.relative_to(Path.cwd().resolve()))
        except ValueError:
            return str(path)

    def content_hash(self) -> str | None:
        """SHA-256 of the checkpoint file (None for the expert): a resume must drive the same weights, even
        when another checkpoint was written to the same path in between."""
        if self.is_expert or not self.checkpoint.is_file():  # the expert, or a custom agent_factory's name
            return None
        if self.agent.startswith("zoo:"):
            from yawil.zoo import weights_sha256

            return weights_sha256(self.agent[len("zoo:"):])  # checked against its card once, not hashed again
        from yawil.fileio import file_sha256

        return file_sha256(self.checkpoint)

    def drive(self) -> dict[str, Any]:
        """The drive settings of a learned agent, as keyword options of `yawil.agent.Agent.from_checkpoint`."""
        return {"speed_control": self.speed_control, "stop_release": self.stop_release, "stop_creep": self.stop_creep,
                "stop_hold": self.stop_hold, "stop_gate": self.stop_gate, "light_hold": self.light_hold,
                "yaw_noise_deg": self.yaw_noise_deg,
                "command_noise_p": self.command_noise_p,
                "yaw_noise_mode": self.yaw_noise_mode, "command_noise_mode": self.command_noise_mode}

    def build(self, seed: int, slots: int = 1) -> DrivingAgent:
        """A fresh agent; learned agents get the episode's seed for their noise and `slots` episodes at once."""
        if self.is_expert:
            from yawil.expert import Expert, ExpertConfig

            return Expert(ExpertConfig.from_items(self.expert_args))
        from yawil.agent import Agent

        return Agent.from_checkpoint(  # type: ignore[no-any-return]
            self.checkpoint, seed=seed, device=self.device, engine=self.engine, slots=slots, attention=False,
            **self.drive(),
        )


def drive_options(args: Any) -> dict[str, Any]:
    """--speed-control and the stop release's options as given (keyword options of `AgentSpec`); for a zoo model
    given none of them, its card's `drive` (so that `--agent zoo:NAME` drives as the card's figures were
    measured), said in one line."""
    given = given_drive(args)
    if any(given.values()) or not str(args.agent).startswith("zoo:"):
        return given
    from yawil.zoo import card_drive, drive_flags

    drive = card_drive(args.agent)
    if drive:
        print(f"{args.agent}: driven as its card says: {drive_flags(drive)}")
    return {**given, **drive}


def agent_device(name: str) -> str:
    """The device of `--device` for a learned agent: cpu, cuda, or auto (cuda when torch sees one, else cpu);
    cuda without a CUDA device is refused in one line."""
    if name not in ("cpu", "cuda", "auto"):
        raise ValueError(f"--device {name!r}: expected cpu, cuda or auto")
    if name == "cpu":
        return "cpu"
    import torch

    if torch.cuda.is_available():
        return "cuda"
    if name == "auto":
        return "cpu"
    raise ValueError("--device cuda: torch sees no CUDA device here; use --device cpu (or auto)")


@dataclass
class _Live:
    """An episode being driven in one slot of an EpisodeDriver."""

    ep: Episode
    world: World
    obs: Observation
    tracker: EpisodeTracker
    recorder: _Recorder | None
    wall0: float
    attempt: int = 1


@dataclass
class EpisodeDriver:
    """Worlds and one agent kept for many episodes of one process.

    `slots` episodes are driven at once, one world each, in lockstep: one batched forward of the agent per
    step (`Agent.act_batch`), a finished slot refilled with the next episode. An agent without `act_batch`
    (the expert, a custom one) drives its episodes one after the other. Each episode's record depends only on
    the episode (its world seed, the agent's engine), never on which episodes shared its steps.
    """

    spec: AgentSpec
    camera: bool
    record_dir: Path | None = None
    world_factory: Callable[[], World] | None = None
    agent_factory: Callable[[int], DrivingAgent] | None = None
    slots: int = 1
    _worlds: dict[int, World] = field(default_factory=dict)
    _agent: DrivingAgent | None = None
    _reset_takes_seed: bool = False
    _noisy: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        self._noisy = bool(self.spec.yaw_noise_deg or self.spec.command_noise_p)

    def world(self, slot: int = 0) -> World:
        if slot not in self._worlds:
            if self.world_factory is not None:
                self._worlds[slot] = self.world_factory()
            else:
                from yawil.sim import make_world

                self._worlds[slot] = make_world(backend="embedded")
        return self._worlds[slot]

    def agent(self, seed: int, slot: int = 0) -> DrivingAgent:
        """Reuse the agent; rebuild it per episode only when its noise needs a per-episode seed it cannot take."""
        if self._agent is None or (self._noisy and not self._reset_takes_seed):
            self._agent = self.agent_factory(seed) if self.agent_factory else self.spec.build(seed, self.slots)
            self._reset_takes_seed = "seed" in inspect.signature(self._agent.reset).parameters
        if slot:
            self._agent.reset(seed=seed, slot=slot)  # type: ignore[call-arg]
        elif self._reset_takes_seed:
            self._agent.reset(seed=seed)  # type: ignore[call-arg]
        else:
            self._agent.reset()
        return self._agent

    def batched(self) -> bool:
        """Whether the agent drives several episodes per forward pass."""
        if self.slots == 1:
            return False
        if self._agent is None:
            self.agent(0)
        return hasattr(self._agent, "act_batch") and getattr(self._agent, "slots", 1) >= self.slots

    def run(self, task: Episode | Sequence[Episode]) -> dict[str, Any] | list[dict[str, Any]]:
        """Drive one episode (its record) or a list of them (their records, in the list's order)."""
        if isinstance(task, Episode):
            return self.drive_one(task)
        if not self.batched():
            return [self.drive_one(ep) for ep in task]
        return self.drive_many(task)

    def drive_one(self, ep: Episode, attempts: int = 3) -> dict[str, Any]:
        """Drive one episode; when the simulator (not the agent) fails, reconnect and drive it again."""
        from yawil.sim.types import SimulatorError

        for attempt in range(1, attempts + 1):
            try:
                live = self._start(ep, 0)
                while not self._step(live, self._agent.act(live.obs)):  # type: ignore[union-attr]
                    pass
                return self._finish(live)
            except SimulatorError as err:
                self._failed(ep, 0, err, attempt, attempts)
        raise AssertionError("unreachable")

    def drive_many(self, episodes: Sequence[Episode], attempts: int = 3) -> list[dict[str, Any]]:
        """Drive the episodes `slots` at a time in lockstep (module docstring); a slot whose simulator fails
        drives its episode again from the start."""
        from yawil.sim.types import SimulatorError

        queue = list(reversed(episodes))
        live: dict[int, _Live] = {}
        done: dict[str, dict[str, Any]] = {}
        while queue or live:
            for slot in range(self.slots):
                if slot not in live and queue:
                    live[slot] = self._start(queue.pop(), slot)
            slots = sorted(live)
            controls = self._agent.act_batch([live[s].obs for s in slots], slots)  # type: ignore[union-attr]
            for slot, control in zip(slots, controls, strict=True):
                run = live[slot]
                try:
                    if self._step(run, control):
                        done[run.ep.key] = self._finish(live.pop(slot))
                except SimulatorError as err:
                    self._failed(run.ep, slot, err, run.attempt, attempts)
                    attempt = run.attempt + 1
                    live[slot] = self._start(run.ep, slot)
                    live[slot].attempt = attempt
        return [done[ep.key] for ep in episodes]

    def _failed(self, ep: Episode, slot: int, err: Exception, attempt: int, attempts: int) -> None:
        print(f"{ep.key}: simulator error ({err}); attempt {attempt} of {attempts}", file=sys.stderr)
        self._drop_world(slot)
        if attempt >= attempts:
            raise err

    def _drop_world(self, slot: int = 0) -> None:
        """Forget a failed world so that the next episode opens a fresh one (a new connection)."""
        world = self._worlds.pop(slot, None)
        if world is not None:
            try:
                world.close()
            except Exception as err:  # a dead server cannot be closed cleanly; the new world replaces it
                print(f"closing the failed world: {err}", file=sys.stderr)

    def _start(self, ep: Episode, slot: int) -> _Live:
        world = self.world(slot)
        wall0 = time.perf_counter()
        obs = world.reset(ep.scenario(self.camera), seed=ep.world_seed)
        self.agent(ep.world_seed, slot)
        goal = obs.route.xy[-1]
        tracker = EpisodeTracker(goal_xy=(float(goal[0]), float(goal[1])), timeout_s=ep.timeout_s)
        tracker.start(obs)
        return _Live(ep, world, obs, tracker, _Recorder(obs) if self.record_dir is not None else None, wall0)

    def _step(self, live: _Live, control: Control) -> bool:
        """One step of one slot's world; True when its episode has ended."""
        if live.recorder is not None:
            live.recorder.add(live.obs)
        live.obs = live.world.step(control)
        return live.tracker.update(live.obs)

    def _finish(self, live: _Live) -> dict[str, Any]:
        ep, obs = live.ep, live.obs
        video = None
        if live.recorder is not None and self.record_dir is not None:
            live.recorder.add(obs)
            video = live.recorder.write(self.record_dir / ep.key.replace("/", "_"))
        return {
            "protocol": PROTOCOL,
            "suite": ep.suite,
            "task": ep.task,
            "condition": ep.condition,
            "route_id": ep.route_id,
            "town": ep.town,
            "weather": ep.weather,
            "seed": ep.seed,
            "world_seed": ep.world_seed,
            "agent": self.spec.identity(),
            "agent_options": self.spec.options(),
            "camera": self.camera,
            "vehicles": ep.vehicles,
            "pedestrians": ep.pedestrians,
            "route_length_m": ep.route.length_m,
            "planned_length_m": round(obs.route.length, 2),
            "timeout_s": round(ep.timeout_s, 2),
            **live.tracker.result(),
            "route_xy": subsample_route(obs.route.xy),
            "wall_s": round(time.perf_counter() - live.wall0, 3),
            "video": video,
        }

    def close(self) -> None:
        for slot in list(self._worlds):
            self._worlds.pop(slot).close()


def drive_episode(agent: DrivingAgent, episode: Episode, camera: bool = True,
                  world: World | None = None) -> dict[str, Any]:
    """Drive one benchmark episode with any agent (`reset`/`act`: a `yawil.agent.load_agent`, the expert, your own)
    exactly as `yawil bench` drives it, and return its record: success, reason, collisions, km driven, lane and
    red-light counts, the trajectory (docs/benchmark.md). `world`: reuse one (default: a new embedded world)."""
    drive = agent.drive.as_dict() if hasattr(agent, "drive") else {}
    engine = getattr(getattr(agent, "engine", None), "option", "auto")
    name = str(getattr(agent, "checkpoint_path", None) or getattr(agent, "name", "agent"))
    spec = AgentSpec(name, engine=engine, **{k: v for k, v in drive.items() if k in AgentSpec.__dataclass_fields__})
    driver = EpisodeDriver(spec, camera, world_factory=(lambda: world) if world is not None else None,
                           agent_factory=lambda seed: agent)
    return driver.drive_one(episode)


class _Recorder:
    """Frames of one episode: camera image (if any) beside a bird's-eye view, written as MP4 (GIF fallback).

    The map is drawn once with `draw_birdseye`; per frame the ego, its trail and the nearby agents are painted
    on a copy of those pixels, which keeps recording cheap enough for whole routes.
    """

    SCALE = 3  # camera upscaling in the video

    def __init__(self, obs: Observation) -> None:
        from yawil.bench.plotting import map_figure
        from yawil.video import figure_to_array

        fig = map_figure(obs.town, obs.route.xy)
        self._background = figure_to_array(fig)
        ax = fig.axes[0]
        self._to_px = ax.transData.transform
        self._height = self._background.shape[0]
        import matplotlib.pyplot as plt

        plt.close(fig)
        self._trail: list[tuple[int, int]] = []
        self.frames: list[Any] = []

    def _px(self, x: float, y: float) -> tuple[int, int]:
        px, py = self._to_px((x, y))
        return int(round(py)), int(round(px))

    def add(self, obs: Observation) -> None:
        import numpy as np

        bev = self._background.copy()
        h, w = bev.shape[:2]

        def dot(r: int, c: int, color: tuple[int, int, int], size: int) -> None:
            r = h - r
            bev[max(0, r - size) : min(h, r + size + 1), max(0, c - size) : min(w, c + size + 1)] = color

        self._trail.append(self._px(obs.pose.x, obs.pose.y))
        for r, c in self._trail:
            dot(r, c, (255, 140, 0), 1)
        for a in obs.privileged.agents:
            dot(*self._px(a.x, a.y), (40, 90, 255) if a.kind == "vehicle" else (30, 180, 60), 3)
        dot(*self._px(obs.pose.x, obs.pose.y), (230, 20, 20), 4)
        if obs.image is not None:
            cam = np.repeat(np.repeat(obs.image, self.SCALE, axis=0), self.SCALE, axis=1)
            canvas = np.zeros((max(h, cam.shape[0]), w + cam.shape[1], 3), dtype=np.uint8)
            canvas[: cam.shape[0], : cam.shape[1]] = cam
            canvas[:h, cam.shape[1] :] = bev
            self.frames.append(canvas)
        else:
            self.frames.append(bev)

    def write(self, stem: Path) -> str:
        from yawil.video import write_video

        return str(write_video(self.frames, stem.with_suffix(".mp4"), fps=10))


# ----- workers ---------------------------------------------------------------------------------------------
WorldFactories = Callable[[], World] | Sequence[Callable[[], World]]


@dataclass(frozen=True)
class DriverFactory:
    """Makes each worker's EpisodeDriver (picklable, for spawned processes and Ray actors): its world is the
    rank-th of `world_factory` when there is one per worker (CARLA servers); `threads` torch threads for a
    learned agent (0: leave torch's default, in the calling process)."""

    spec: AgentSpec
    camera: bool
    record_dir: str | None = None
    threads: int = 0
    world_factory: WorldFactories | None = None
    agent_factory: Callable[[int], DrivingAgent] | None = None
    slots: int = 1

    def __call__(self, rank: int, report: Callable[[Any], None]) -> EpisodeDriver:
        if self.threads and not self.spec.is_expert:
            import torch

            torch.set_num_threads(self.threads)
        world = for_worker(self.world_factory, rank) if self.world_factory is not None else None
        return EpisodeDriver(self.spec, self.camera, Path(self.record_dir) if self.record_dir else None, world,
                             self.agent_factory, self.slots)


def _check_picklable(*factories: Any) -> None:
    """Spawned processes get the factories pickled: say so in one line, before any episode, when they cannot."""
    import pickle

    try:
        pickle.dumps(factories)
    except (pickle.PicklingError, AttributeError, TypeError) as err:
        raise ValueError(f"a custom world_factory or agent_factory on several local workers must be picklable "
                         f"(a module-level function or a partial of one): {err}") from None


@dataclass
class RunSummary:
    total: int
    skipped: int
    ran: int
    successes: int
    wall_s: float
    records: list[dict[str, Any]]


def run_benchmark(
    episodes: Sequence[Episode],
    spec: AgentSpec,
    out: str | Path,
    workers: int = 1,
    camera: bool | None = None,
    record: bool = False,
    progress: bool = True,
    label: str | None = None,
    world_factory: WorldFactories | None = None,
    agent_factory: Callable[[int], DrivingAgent] | None = None,
    on_record: Callable[[Mapping[str, Any]], None] | None = None,
    executor: ExecutorConfig = ExecutorConfig(),
    episodes_per_worker: int | None = None,
) -> RunSummary:
    """Drive every episode not yet in `out`, appending each record as soon as it is done.

    `world_factory` and `agent_factory` (seed -> agent) replace the embedded world and the agent that
    `spec` names (any object with reset() and act(obs)); `world_factory` may be a list, one per worker (CARLA
    servers). On more than one local worker they must be picklable (module-level, or partials of such).
    `executor` says where the workers run (yawil.executor); the records are the same either way.
    `episodes_per_worker` (K, default `EPISODES_PER_WORKER`): how many
    episodes each worker drives at once with one batched forward per step (`EpisodeDriver`); the records do
    not depend on it. A worker gets its episodes in chunks of up to 2K (smaller when there are few, so that no
    worker idles), so a kill loses at most those in flight.
    """
    executor.check()
    if agent_factory is None:
        spec.validate(build=False)
    if workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    k = EPISODES_PER_WORKER if episodes_per_worker is None else episodes_per_worker
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"--episodes-per-worker must be an integer >= 1, got {k!r}")
    if isinstance(world_factory, (list, tuple)) and len(world_factory) != workers:
        raise ValueError(f"{len(world_factory)} world factories for {workers} workers: give one per worker")
    if executor.kind == "local" and workers > 1:
        _check_picklable(world_factory, agent_factory)
    use_camera = (not spec.is_expert) if camera is None else camera
    out = Path(out)
    record_dir = out / "videos" if record else None
    import yawil

    info = {"agent": spec.identity(), "agent_options": spec.options(), "label": label or out.name,
            "agent_sha256": spec.content_hash(), "yawil_version": yawil.__version__}
    check_run_info(out, info, label_given=label is not None, write=False)  # another agent's folder: before the build
    if agent_factory is None:
        spec.validate()
    t0 = time.perf_counter()
    with folder_lock(out, "results folder"), EpisodeLog(out) as log:
        check_run_info(out, info, label_given=label is not None)
        todo = [ep for ep in episodes if ep.key not in log]
        skipped = len(episodes) - len(todo)
        done_now: list[dict[str, Any]] = []
        from tqdm import tqdm

        bar = tqdm(total=len(episodes), initial=skipped, disable=not progress, unit="ep", dynamic_ncols=True)
        wanted = {ep.key for ep in episodes}
        ok = sum(bool(r["success"]) for r in log.records if episode_key(r) in wanted)

        def finish(rec: dict[str, Any]) -> None:
            nonlocal ok
            log.append(rec)
            done_now.append(rec)
            ok += bool(rec["success"])
            bar.update(1)
            bar.set_postfix_str(f"success {ok}/{skipped + len(done_now)}")
            if on_record is not None:
                on_record(rec)

        n = max(1, min(workers, len(todo)))
        inline = executor.kind == "local" and n == 1
        factory = DriverFactory(spec, use_camera, str(record_dir) if record_dir else None,
                                0 if inline else max(1, (os.cpu_count() or 2) // workers), world_factory, agent_factory,
                                k)
        # chunks of up to 2K episodes (a slot refilled within its chunk), but never so few that a worker idles
        size = 1 if k == 1 else max(1, min(2 * k, -(-len(todo) // n)))
        chunks = [todo[i:i + size] for i in range(0, len(todo), size)]
        try:
            with open_executor(executor, n, factory) as pool:
                queue = list(reversed(chunks))
                while queue or len(pool):
                    while queue and len(pool) < 2 * n:  # at most 2 chunks per worker queued: a kill loses little
                        chunk = queue.pop()
                        pool.submit(chunk[0].key, chunk[0] if size == 1 else chunk)
                    for _, result in pool.results():
                        for rec in result if isinstance(result, list) else [result]:
                            finish(rec)
        finally:
            bar.close()
    return RunSummary(
        total=len(episodes),
        skipped=skipped,
        ran=len(done_now),
        successes=sum(bool(r["success"]) for r in done_now),
        wall_s=time.perf_counter() - t0,
        records=done_now,
    )
