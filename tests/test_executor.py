"""The executors (yawil.executor): local processes and Ray actors give the same records and datasets; a Ray
worker killed mid-task has its task run again, once; an error in the caller stops the workers; bad choices
are one line. The Ray tests share one local Ray of 2 CPUs (starting Ray costs seconds); dev installs Ray,
so a missing Ray fails them, it does not skip them."""

from __future__ import annotations

import functools
import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from yawil.executor import ExecutorConfig, RayExecutor, for_worker, open_executor

TESTS = str(Path(__file__).resolve().parent)
RAY = ExecutorConfig("ray")


@pytest.fixture(scope="module")
def ray_session() -> Iterator[None]:
    """One local Ray for this module's tests; its workers import this folder's modules (the test doubles)."""
    import ray

    from yawil.executor import init_ray

    path = os.pathsep.join(p for p in (TESTS, os.environ.get("PYTHONPATH", "")) if p)
    assert init_ray(None, 2, runtime_env={"env_vars": {"PYTHONPATH": path}})
    yield
    ray.shutdown()


# ------------------------------------------------------------------------------------------ test doubles
class Sleeper:
    """A worker whose task (seconds, folder) marks its start in folder/<pid>, sleeps, and returns its pid."""

    def __init__(self, rank: int, report: Any) -> None:
        self.rank, self.report = rank, report

    def run(self, task: tuple[float, str]) -> tuple[int, int]:
        seconds, folder = task
        if folder:
            Path(folder, str(os.getpid())).touch()
        self.report(self.rank)
        if seconds < 0:
            raise ValueError(f"a bad task: {seconds}")
        time.sleep(seconds)
        return self.rank, os.getpid()

    def close(self) -> None:
        pass


def _dead(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] in ("Z", "X")  # a zombie has ended too
    except FileNotFoundError:
        return True


def _wait_dead(pids: list[int], seconds: float = 20.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if all(_dead(p) for p in pids):
            return True
        time.sleep(0.1)
    return False


def dying_line_world(flag: str) -> Any:
    """The collector's scripted world, except that the first worker to reach frame 30 of an episode kills its
    own process (the flag file makes it happen once in the whole run): a worker lost mid-episode."""
    from scripted_world import LineWorld

    class Dying(LineWorld):
        def step(self, control: Any) -> Any:
            obs = super().step(control)
            if self.frame == 30:
                try:
                    fd = os.open(flag, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    return obs
                os.write(fd, str(os.getpid()).encode())
                os.close(fd)
                os.kill(os.getpid(), signal.SIGKILL)
            return obs

    return Dying()


def _h5_contents(path: Path) -> dict[str, Any]:
    import h5py

    with h5py.File(path) as f:
        return {"attrs": {k: f.attrs[k] for k in f.attrs}, **{name: f[name][:] for name in f}}


def _same_h5(a: Path, b: Path) -> None:
    import numpy as np

    ca, cb = _h5_contents(a), _h5_contents(b)
    assert ca.keys() == cb.keys()
    assert {k: str(v) for k, v in ca["attrs"].items()} == {k: str(v) for k, v in cb["attrs"].items()}
    for name in ca.keys() - {"attrs"}:
        assert np.array_equal(ca[name], cb[name]), name


def _one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """`yawil ARGV`'s exit code and its lines on stderr (some commands end with their own SystemExit line)."""
    from yawil.cli import main

    try:
        rc = main(argv)
    except SystemExit as exit_:
        rc = exit_.code if isinstance(exit_.code, int) else 2
        if not isinstance(exit_.code, int):
            print(exit_.code, file=sys.stderr)
    return rc, capsys.readouterr().err.strip().splitlines()


# ------------------------------------------------------------------------------------------ no Ray needed
def test_the_choice_is_checked_in_one_line() -> None:
    with pytest.raises(ValueError, match="--executor 'dask': expected one of local, ray"):
        ExecutorConfig("dask")
    with pytest.raises(ValueError, match="applies to --executor ray only"):
        ExecutorConfig("local", "auto")
    with pytest.raises(ValueError, match="expected auto, HOST:PORT"):
        ExecutorConfig("ray", "head-node")
    assert ExecutorConfig("ray", "10.0.0.1:6379").ray_address and ExecutorConfig("ray", "ray://h:10001").ray_address
    assert for_worker(("a", "b"), 1) == "b" and for_worker("a", 1) == "a"
    with pytest.raises(ValueError, match="--workers must be >= 1"):
        open_executor(ExecutorConfig(), 0, Sleeper)


def test_a_missing_ray_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails, find_spec finds nothing
    for argv in (["bench", "--suite", "square", "--out", str(tmp_path / "b")],
                 ["collect", "--episodes", "1", "--out", str(tmp_path / "c")]):
        rc, lines = _one_line([*argv, "--executor", "ray"], capsys)
        assert rc == 2 and lines == [f"yawil {argv[0]}: --executor ray: Ray is not installed; pip install 'yawil[ray]'"]
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()
    with pytest.raises(ValueError, match=r"pip install 'yawil\[ray\]'"):
        open_executor(RAY, 2, Sleeper)


def test_local_workers_have_their_ranks_report_and_raise(tmp_path: Path) -> None:
    reports: list[int] = []
    got: dict[Any, tuple[int, int]] = {}
    with open_executor(ExecutorConfig(), 2, Sleeper, on_report=reports.append) as ex:
        for key in range(4):
            ex.submit(key, (0.2, ""))
        while len(ex):
            got.update(ex.results())
    assert sorted(got) == [0, 1, 2, 3]
    assert len({rank for rank, _ in got.values()}) == len({pid for _, pid in got.values()})  # a rank per process
    assert sorted(reports) == sorted(rank for rank, _ in got.values())  # each task's report reached the caller
    with pytest.raises(ValueError, match="a bad task: -1"), open_executor(ExecutorConfig(), 2, Sleeper) as ex:
        ex.submit("bad", (-1.0, ""))
        while len(ex):
            ex.results()


def test_an_error_in_the_caller_stops_the_local_workers(tmp_path: Path) -> None:
    with pytest.raises(KeyboardInterrupt), open_executor(ExecutorConfig(), 2, Sleeper) as ex:
        ex.submit(0, (60.0, str(tmp_path)))
        ex.submit(1, (60.0, str(tmp_path)))
        while len(list(tmp_path.iterdir())) < 2:
            time.sleep(0.05)
        raise KeyboardInterrupt
    assert _wait_dead([int(p.name) for p in tmp_path.iterdir()], 10.0)


def test_one_server_per_worker(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--carla-servers: checked in one line, worker r gets the r-th server and its own Traffic Manager port,
    under either executor (the factory of each worker picks by its rank)."""
    from yawil.bench.runner import AgentSpec, DriverFactory
    from yawil.data.collect import CollectConfig, EpisodeWork
    from yawil.expert import ExpertConfig
    from yawil.guidance import GuidanceConfig
    from yawil.sim.carla.servers import TM_PORT, parse_servers, server_worlds

    assert parse_servers("a:2000, b:2002") == (("a", 2000), ("b", 2002))
    worlds = server_worlds(parse_servers("a:2000,b:2002"), timeout=5.0)
    assert [(w.keywords["host"], w.keywords["port"], w.keywords["tm_port"]) for w in worlds] == [  # type: ignore[attr-defined]
        ("a", 2000, TM_PORT), ("b", 2002, TM_PORT + 1)]
    assert DriverFactory(AgentSpec("expert"), False, world_factory=worlds)(1, print).world_factory is worlds[1]
    made: list[str] = []
    work = EpisodeWork(None, CollectConfig(), GuidanceConfig(), ExpertConfig(), 0,
                       (functools.partial(made.append, "w0"), functools.partial(made.append, "w1")))  # type: ignore[arg-type]
    work(1, print)
    assert made == ["w1"]
    bad = [
        (["--workers", "2", "--carla-servers", "a:2000"], "--carla-servers lists 1 server(s) for --workers 2"),
        (["--carla-servers", "a"], "'a' is not HOST:PORT"),
        (["--workers", "2", "--carla-servers", "a:1,a:1"], "a:1 is given twice"),
        (["--workers", "2"], "give one server per worker with --carla-servers"),
    ]
    for command in ("collect", "bench"):
        for flags, text in bad:
            argv = [command, "--backend", "carla", *flags, "--out", str(tmp_path / command)]
            rc, lines = _one_line(argv, capsys)
            assert rc == 2 and len(lines) == 1 and text in lines[0], (argv, lines)
    rc, lines = _one_line(["collect", "--carla-servers", "a:1", "--episodes", "1", "--out", str(tmp_path / "e")], capsys)
    assert rc == 2 and lines == ["yawil collect: --carla-servers applies to --backend carla, not --backend embedded"]
    assert not any((tmp_path / name).exists() for name in ("collect", "bench", "e"))


def test_unpicklable_factories_on_local_workers_are_refused_before_any_episode(tmp_path: Path) -> None:
    from scripted_world import LineWorld
    from yawil.bench.runner import AgentSpec, run_benchmark
    from yawil.bench.suites import episodes

    eps = episodes("square", routes="0:2", seeds=1)
    with pytest.raises(ValueError, match="must be picklable"):
        run_benchmark(eps, AgentSpec("expert"), tmp_path / "b", workers=2, progress=False,
                      world_factory=lambda: LineWorld())
    assert not (tmp_path / "b").exists()


# --------------------------------------------------------------------------------------------------- Ray
def test_ray_bench_gives_the_records_of_local(tmp_path: Path, ray_session: None) -> None:
    """Same command, both executors, 2 workers: the same records but for the wall time."""
    from yawil.cli import main

    base = ["bench", "--suite", "square", "--routes", "0:4", "--seeds", "1", "--workers", "2", "--no-progress"]
    for name, flags in (("local", []), ("ray", ["--executor", "ray"])):
        assert main([*base, *flags, "--out", str(tmp_path / name), "--label", "x"]) == 0

    def records(name: str) -> list[dict[str, Any]]:
        lines = (tmp_path / name / "episodes.jsonl").read_text().splitlines()
        return sorted(({k: v for k, v in json.loads(x).items() if k != "wall_s"} for x in lines),
                      key=lambda r: (r["route_id"], r["seed"]))

    local, ray = records("local"), records("ray")
    assert len(local) == 4 and local == ray


def test_ray_collect_survives_a_killed_worker_and_matches_local(tmp_path: Path, ray_session: None,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A Ray worker killed in the middle of an episode: the episode is collected again on a worker, stored once,
    and the dataset is the one a local run makes, file by file; a rerun resumes (nothing left to do)."""
    from scripted_world import line_world, small_cfg
    from yawil.data.collect import collect
    from yawil.data.manifest import read_manifest

    kw: dict[str, Any] = dict(town="line", weathers="ClearNoon,WetNoon", episodes=4, progress=False, config=small_cfg())
    one = collect(tmp_path / "local", world_factory=line_world, **kw)
    flag = tmp_path / "killed"
    s = collect(tmp_path / "ray", workers=2, world_factory=functools.partial(dying_line_world, str(flag)),
                executor=RAY, **kw)
    assert flag.is_file(), "no worker was killed: the test tests nothing"
    assert "died; it runs again on the next free worker" in capsys.readouterr().err
    assert s.episodes_written == 4 and s.outcomes == one.outcomes and s.frames_written == one.frames_written
    local, ray = read_manifest(tmp_path / "local"), read_manifest(tmp_path / "ray")
    assert sorted(ray.episode_ids()) == [0, 1, 2, 3]  # none lost, none twice
    assert sorted(local.episodes, key=lambda e: e.episode) == sorted(ray.episodes, key=lambda e: e.episode)
    for e in local.episodes:
        _same_h5(local.path_of(e), ray.path_of(e))
    assert not list((tmp_path / "ray" / "episodes").glob(".*"))  # no temporary file left behind
    import tempfile

    killed = flag.read_text()  # the killed worker's episode dataset was removed by a later episode
    assert not list(Path(tempfile.gettempdir()).glob(f"yawil-episode-{killed}-*"))
    again = collect(tmp_path / "ray", workers=2, world_factory=line_world, executor=RAY, **kw)
    assert (again.episodes_written, again.episodes_skipped) == (0, 4)


def test_a_killed_ray_worker_s_task_runs_again_once(tmp_path: Path, ray_session: None) -> None:
    """The test kills an actor's process (os.kill) while it runs a task: every task's result comes back once,
    the lost one from a live worker."""
    ex = open_executor(RAY, 2, Sleeper)
    assert isinstance(ex, RayExecutor)
    with ex:
        pids = ex.pids()
        for key in range(4):
            ex.submit(key, (1.0, str(tmp_path)))
        while not (tmp_path / str(pids[0])).exists():
            time.sleep(0.02)
        os.kill(pids[0], signal.SIGKILL)
        got: dict[Any, tuple[int, int]] = {}
        while len(ex):
            for key, value in ex.results():
                assert key not in got
                got[key] = value
    assert sorted(got) == [0, 1, 2, 3]
    assert pids[0] not in {pid for _, pid in got.values()}
    assert _wait_dead(pids + [pid for _, pid in got.values()])  # closed: every actor process ends


def test_an_error_in_the_caller_stops_the_ray_workers(tmp_path: Path, ray_session: None) -> None:
    ex = open_executor(RAY, 2, Sleeper)
    assert isinstance(ex, RayExecutor)
    pids = ex.pids()
    with pytest.raises(KeyboardInterrupt), ex:
        ex.submit(0, (60.0, str(tmp_path)))
        while not list(tmp_path.iterdir()):
            time.sleep(0.02)
        raise KeyboardInterrupt
    assert _wait_dead(pids)
    with pytest.raises(ValueError, match="a bad task: -2"), open_executor(RAY, 1, Sleeper) as ex:
        ex.submit("bad", (-2.0, ""))  # a task's own error comes back as itself
        while len(ex):
            ex.results()
