"""Where episode-parallel work runs: in this process, in `local` processes, or on `ray` actors.

Collection and the benchmark hand an executor a picklable worker factory and their tasks (episodes). Each
worker is made once, in its own process, on its first task (its world, its agent), runs tasks one at a time
and returns each result to the one process that submitted them, which alone writes (the dataset's manifest,
the results file). So the executor changes where episodes run, never what they give.

- `local`, one worker: tasks run in the calling process (no pickling: closures and test doubles work).
- `local`, N workers: N spawned processes (concurrent.futures); progress reports come back over a queue.
- `ray`: one Ray actor per worker, on the local machine (a local Ray sized to the workers) or on a cluster
  (`--ray-address auto` or HOST:PORT). A task goes to a free actor only, so at most N run at once. An actor
  that dies (killed, out of memory, its node lost) is replaced and its task is handed to the next free actor;
  its result never reached the caller, so nothing was written for it: no episode lost, none twice.

Base layer: no yawil stage is imported here, and Ray only when it is chosen. Why actors, how results return and
how retries avoid duplicates: docs/decisions.md.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import sys
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol, TypeVar

EXECUTORS: tuple[str, ...] = ("local", "ray")
RAY_INSTALL = "pip install 'yawil[ray]'"
RAY_OBJECT_STORE_BYTES = 256 << 20  # a local Ray's shared memory: a few finished episode files in flight
MAX_ATTEMPTS = 3  # a task whose worker dies this many times is an error, not retried forever
REPORT_POLL_S = 0.25  # how often a waiting caller hears of its local workers' progress reports

T = TypeVar("T")


class Worker(Protocol):
    """What a worker factory makes: one per process, kept for all its tasks."""

    def run(self, task: Any) -> Any: ...

    def close(self) -> None: ...


Report = Callable[[Any], None]
# (rank 0..N-1, report) -> worker. Picklable (a module-level class or function, or a partial of one) unless
# it runs in the calling process. `report(item)` sends a progress item to the caller's `on_report`.
WorkerFactory = Callable[[int, Report], Worker]


def for_worker(value: T | Sequence[T], rank: int) -> T:
    """`value` itself, or its `rank`-th item when it is one per worker (a list or tuple: CARLA servers)."""
    return value[rank] if isinstance(value, (list, tuple)) else value  # type: ignore[return-value]


def _drop(item: Any) -> None:
    """The report of a worker whose progress nobody follows (Ray actors: results only)."""


# --------------------------------------------------------------------------------------------- the choice
@dataclass(frozen=True)
class ExecutorConfig:
    """Which executor: `kind` (local | ray) and, for ray, the cluster (`None`: start a local Ray)."""

    kind: str = "local"
    ray_address: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in EXECUTORS:
            raise ValueError(f"--executor {self.kind!r}: expected one of {', '.join(EXECUTORS)}")
        if self.ray_address is not None:
            if self.kind != "ray":
                raise ValueError(f"--ray-address {self.ray_address!r} applies to --executor ray only")
            if not _is_address(self.ray_address):
                raise ValueError(f"--ray-address {self.ray_address!r}: expected auto, HOST:PORT or ray://HOST:PORT")

    def check(self) -> ExecutorConfig:
        """Fail before any work when Ray is chosen but not installed."""
        if self.kind == "ray" and importlib.util.find_spec("ray") is None:
            raise ValueError(f"--executor ray: Ray is not installed; {RAY_INSTALL}")
        return self


def _is_address(text: str) -> bool:
    if text == "auto":
        return True
    host, _, port = text.removeprefix("ray://").rpartition(":")
    return bool(host) and port.isdigit() and 0 < int(port) < 65536


def add_executor_arguments(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--executor and --ray-address, the same on every command that runs episodes in parallel."""
    p.add_argument("--executor", choices=EXECUTORS, default="local",
                   help="where the --workers run: local (default) processes on the local machine, or ray actors "
                        f"(needs {RAY_INSTALL}); the results are the same either way")
    p.add_argument("--ray-address", default=None, metavar="auto|HOST:PORT",
                   help="--executor ray: the cluster to join (auto: the one `ray start` made on the local machine); "
                        "default: start a local Ray with one CPU per worker")


def executor_from_args(args: argparse.Namespace) -> ExecutorConfig:
    return ExecutorConfig(args.executor, args.ray_address).check()


# ------------------------------------------------------------------------------------------- executors
class Executor(ABC):
    """Tasks in, results out, in the order they finish. Use as a context manager: leaving it normally lets the
    workers close (their worlds too); an exception (a worker's, Ctrl-C) stops them at once."""

    def __init__(self, workers: int, on_report: Report | None) -> None:
        self.workers = workers
        self.on_report = on_report or _drop

    @abstractmethod
    def submit(self, key: Hashable, task: Any) -> None:
        """Queue a task; it runs when a worker is free."""

    @abstractmethod
    def results(self, timeout: float | None = None) -> list[tuple[Hashable, Any]]:
        """(key, result) of tasks finished, waiting up to `timeout` s (None: until one is) while any is queued
        or running. A worker's exception is raised here."""

    @abstractmethod
    def __len__(self) -> int:
        """Tasks submitted whose result has not been returned."""

    @abstractmethod
    def close(self) -> None:
        """All results are in: the workers close and end."""

    @abstractmethod
    def terminate(self) -> None:
        """Stop the workers now; their tasks are dropped."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.terminate()


def open_executor(config: ExecutorConfig, workers: int, factory: WorkerFactory,
                  on_report: Report | None = None) -> Executor:
    """The executor `config` names with `workers` workers made by `factory`."""
    if workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    if config.kind == "ray":
        return RayExecutor(workers, factory, config.ray_address, on_report)
    if workers == 1:
        return InlineExecutor(factory, on_report)
    return LocalExecutor(workers, factory, on_report)


class InlineExecutor(Executor):
    """One worker in the calling process: each task runs when its result is asked for."""

    def __init__(self, factory: WorkerFactory, on_report: Report | None = None) -> None:
        super().__init__(1, on_report)
        self._factory = factory
        self._worker: Worker | None = None
        self._queue: deque[tuple[Hashable, Any]] = deque()

    def submit(self, key: Hashable, task: Any) -> None:
        self._queue.append((key, task))

    def results(self, timeout: float | None = None) -> list[tuple[Hashable, Any]]:
        if not self._queue:
            return []
        if self._worker is None:
            self._worker = self._factory(0, self.on_report)
        key, task = self._queue.popleft()
        return [(key, self._worker.run(task))]

    def __len__(self) -> int:
        return len(self._queue)

    def close(self) -> None:
        self._queue.clear()
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.close()

    terminate = close  # the only task in progress was this process's own, and it has ended


# per-process state of a local worker process
_LOCAL: dict[str, Any] = {}


def _local_init(factory: WorkerFactory, ranks: Any, reports: Any) -> None:
    _LOCAL.update(factory=factory, rank=ranks.get(), report=reports.put if reports is not None else _drop, worker=None)


def _local_run(task: Any) -> Any:
    worker = _LOCAL["worker"]
    if worker is None:  # made on the first task, so that an error making it is that task's error
        import multiprocessing.util

        worker = _LOCAL["worker"] = _LOCAL["factory"](_LOCAL["rank"], _LOCAL["report"])
        multiprocessing.util.Finalize(worker, worker.close, exitpriority=10)  # at the pool's normal end
    return worker.run(task)


class LocalExecutor(Executor):
    """N spawned processes on the local machine; each takes a rank (0..N-1) from a queue when it starts."""

    def __init__(self, workers: int, factory: WorkerFactory, on_report: Report | None = None) -> None:
        from multiprocessing import get_context

        super().__init__(workers, on_report)
        ctx = get_context("spawn")
        ranks = ctx.Queue()
        for rank in range(workers):
            ranks.put(rank)
        self._reports = ctx.Queue() if on_report is not None else None
        self._pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_local_init,
                                         initargs=(factory, ranks, self._reports))
        self._futures: dict[Future[Any], Hashable] = {}

    def submit(self, key: Hashable, task: Any) -> None:
        self._futures[self._pool.submit(_local_run, task)] = key

    def results(self, timeout: float | None = None) -> list[tuple[Hashable, Any]]:
        import time

        end = None if timeout is None else time.monotonic() + timeout
        while self._futures:
            left = None if end is None else max(0.0, end - time.monotonic())
            step = left if self._reports is None else (REPORT_POLL_S if left is None else min(REPORT_POLL_S, left))
            done, _ = wait(self._futures, timeout=step, return_when=FIRST_COMPLETED)
            self._drain()
            if done or (end is not None and time.monotonic() >= end):
                return [(self._futures.pop(f), f.result()) for f in done]  # a worker's exception re-raised here
        return []

    def _drain(self) -> None:
        import queue

        while self._reports is not None:
            try:
                item = self._reports.get_nowait()
            except queue.Empty:
                return
            self.on_report(item)

    def __len__(self) -> int:
        return len(self._futures)

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self._drain()

    def terminate(self) -> None:
        # concurrent.futures stops no running task (terminate_workers comes with Python 3.14): end the processes.
        # The pool's manager thread may then fail reading from a dead worker's pipe and print its traceback under
        # "interrupted" (a Ctrl-C of collect, 1 try in 4): its error is the stop's own, so it is not printed.
        import threading

        manager = getattr(self._pool, "_executor_manager_thread", None)
        previous = threading.excepthook

        def quiet(args: threading.ExceptHookArgs) -> None:
            if args.thread is not manager:
                previous(args)

        threading.excepthook = quiet
        try:
            for process in list((self._pool._processes or {}).values()):
                process.terminate()
            self._pool.shutdown(wait=True, cancel_futures=True)
        finally:
            threading.excepthook = previous
        self._futures.clear()


# ------------------------------------------------------------------------------------------------ Ray
def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ValueError(f"--executor ray: Ray is not installed; {RAY_INSTALL}") from None
    return ray


def init_ray(address: str | None, workers: int, **options: Any) -> bool:
    """Connect this process to Ray, unless it is already: `address` None starts a local Ray with `workers` CPUs
    (no dashboard, a small object store, workers' logs kept off this terminal); `auto` or HOST:PORT joins a
    cluster. `options` go to `ray.init` (tests give a `runtime_env`). True when this call connected."""
    ray = _ray()
    if ray.is_initialized():
        return False
    common = {"log_to_driver": False, "logging_level": logging.WARNING, **options}
    if address is None:
        # "local": a new Ray of this process's own, even where `ray start` left one running or named in RAY_ADDRESS
        ray.init(address="local", num_cpus=workers, include_dashboard=False,
                 object_store_memory=RAY_OBJECT_STORE_BYTES, **common)
    else:
        ray.init(address=address, **common)
    return True


class _RayWorker:
    """The body of a Ray actor. The worker is made on the first task, so that an error making it (a server that
    does not answer) comes back as that task's error rather than as a dead actor restarted again and again."""

    def __init__(self, factory: WorkerFactory, rank: int) -> None:
        self._factory, self._rank = factory, rank
        self._worker: Worker | None = None

    def pid(self) -> int:
        return os.getpid()

    def run(self, task: Any) -> Any:
        if self._worker is None:
            self._worker = self._factory(self._rank, _drop)
        return self._worker.run(task)

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()
            self._worker = None


class RayExecutor(Executor):
    """One actor per worker (1 CPU each), made on its first task; tasks wait here until an actor is free. An
    actor that dies (or cannot be reached) is replaced by a new one of the same rank (its CARLA server), and its
    task goes back to the head of the queue, for the next free actor, at most MAX_ATTEMPTS times. Ray restarts
    no actor and retries no task itself: a restarting actor fails every call made meanwhile, and a retry Ray
    made would be one more that this queue cannot see."""

    def __init__(self, workers: int, factory: WorkerFactory, address: str | None = None,
                 on_report: Report | None = None) -> None:
        super().__init__(workers, on_report)
        self._raym = _ray()
        self._owns_ray = init_ray(address, workers)
        self._actor = self._raym.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(_RayWorker)
        self._factory = factory
        self._actors: list[Any] = [None] * workers  # made on their first task: a resume with nothing to do starts none
        self._free: deque[int] = deque(range(workers))
        self._queue: deque[tuple[Hashable, Any, int]] = deque()  # (key, task, attempts so far)
        self._running: dict[Any, tuple[int, Hashable, Any, int]] = {}  # ObjectRef -> (rank, key, task, attempts)

    def _actor_of(self, rank: int) -> Any:
        if self._actors[rank] is None:
            self._actors[rank] = self._actor.remote(self._factory, rank)
        return self._actors[rank]

    def pids(self) -> list[int]:
        """The actors' process ids (tests kill one)."""
        return [int(pid) for pid in self._raym.get([self._actor_of(r).pid.remote() for r in range(self.workers)])]

    def submit(self, key: Hashable, task: Any) -> None:
        self._queue.append((key, task, 0))
        self._dispatch()

    def _dispatch(self) -> None:
        while self._free and self._queue:
            rank = self._free.popleft()
            key, task, attempts = self._queue.popleft()
            self._running[self._actor_of(rank).run.remote(task)] = (rank, key, task, attempts)

    def results(self, timeout: float | None = None) -> list[tuple[Hashable, Any]]:
        ray = self._raym
        self._dispatch()
        if not self._running:
            return []
        ready, _ = ray.wait(list(self._running), num_returns=1, timeout=timeout)
        if ready:  # and every other one finished by now
            ready, _ = ray.wait(list(self._running), num_returns=len(self._running), timeout=0)
        out: list[tuple[Hashable, Any]] = []
        for ref in ready:
            rank, key, task, attempts = self._running.pop(ref)
            self._free.append(rank)
            try:
                out.append((key, ray.get(ref)))
            except ray.exceptions.RayActorError as err:  # the worker process died: its result never came back
                ray.kill(self._actors[rank], no_restart=True)
                self._actors[rank] = None  # a new actor of this rank on its next task
                if attempts + 1 >= MAX_ATTEMPTS:
                    raise RuntimeError(f"{key!r}: its worker died {MAX_ATTEMPTS} times running it; "
                                       f"last: {str(err).splitlines()[0]}") from err
                print(f"executor: the ray worker running {key!r} died; it runs again on the next free worker",
                      file=sys.stderr)
                self._queue.appendleft((key, task, attempts + 1))
            except ray.exceptions.RayTaskError as err:  # the task's own exception, raised as the local pool does
                if isinstance(err.cause, BaseException):
                    raise err.cause from err
                raise
        self._dispatch()
        return out

    def __len__(self) -> int:
        return len(self._queue) + len(self._running)

    def close(self) -> None:
        ray = self._raym
        try:
            ray.get([a.close.remote() for a in self._actors if a is not None], timeout=60)
        except (ray.exceptions.RayError, TimeoutError) as err:  # a world that cannot close cleanly ends with its actor
            print(f"executor: closing the ray workers: {str(err).splitlines()[0]}", file=sys.stderr)
        self.terminate()

    def terminate(self) -> None:
        for actor in self._actors:
            if actor is not None:
                self._raym.kill(actor, no_restart=True)
        self._queue.clear()
        self._running.clear()
        if self._owns_ray:
            self._raym.shutdown()
