"""Where independent pieces of work run: processes on this machine, or a Ray cluster.

One parallel path for the whole project: `LocalEngine` is what ``aimbench study --engine local``
and ``aimbench sweep --jobs N`` (`scenarios.runner.ParallelSimRunner`) run on; `RayEngine` is the
same contract on Ray, through Ray's own task API (``ray.remote`` tasks, ``ray.wait``, Ray's retries
of tasks whose worker died). Either engine takes tasks ``(key, args)`` and a module-level function
``fn(*args)``, runs each once, and hands every result back to the caller's process, in the order
they finish, through ``on_result(key, result)``. The caller alone writes the store, so a result is
committed once, whatever the engine.

A task may report as it goes (`emit`: the sweep's scans, one by one): on the local engine the
messages arrive while the task runs, on Ray with its result; on both every message of a task is
delivered before its result. A task may look at `stopping()` to stop early (Ctrl-C).

A worker lost mid-task (SIGKILL, a node gone) costs that task only: the local engine rebuilds its
pool and runs the task again (after ``retry(key, args)``, which may shorten it to what is still
missing, or drop it), Ray retries it itself (``max_retries``). A result that never arrived was
never committed, so nothing is lost, and nothing is doubled.

Why `concurrent.futures.ProcessPoolExecutor` for the local engine: it reports a dead worker as
`BrokenProcessPool` on every task in flight, where `multiprocessing.Pool` waits for ever on the
task a killed worker held. Why Ray tasks rather than `ray.util.multiprocessing.Pool`: a task is
retried by Ray when its worker dies, and `ray.wait` hands results back as they finish.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import Any

from twin.core.errors import AimbenchError

Task = tuple[Hashable, tuple]
OnResult = Callable[[Hashable, Any], None]
OnMessage = Callable[[Hashable, Any], None]
Retry = Callable[[Hashable, tuple], tuple | None]

#: Times a task is run again after its worker died, before the study or sweep fails.
MAX_RETRIES = 3
#: Environment every worker gets: one BLAS/OpenMP thread per process (the engines give each
#: task one CPU; more threads per process only fight over the cores).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: The project's import packages, shipped to a Ray cluster's workers (`RayEngine`).
PROJECT_PACKAGES = ("aimbench", "align", "bench_fw", "models", "scenarios", "twin")
#: What a missing Ray says.
NO_RAY = ("--engine ray needs Ray, which is not installed: pip install 'aimbench[ray]' (or use "
          "--engine local)")


class EngineError(AimbenchError):
    """A study or sweep could not be run on the engine (Ray missing, a task that kept dying)."""


class WorkerLost(EngineError):
    """A task whose worker died more often than `MAX_RETRIES`."""


# -- inside a worker ---------------------------------------------------------------------------

_messages: Any = None  # the local engine's queue, or a Ray task's list
_stop: Any = None  # the local engine's stop event
_task_key: Hashable = None


def emit(message: Any) -> None:
    """Send `message` to the caller's ``on_message`` (from inside a task)."""
    if isinstance(_messages, list):
        _messages.append(message)
    elif _messages is not None:
        _messages.put((_task_key, message))


def stopping() -> bool:
    """Whether the caller asked the tasks to stop (Ctrl-C): a task may end early."""
    return _stop is not None and _stop.is_set()


Warm = tuple[Callable, tuple]


#: How often a worker looks whether its parent is still there, s.
PARENT_WATCH_S = 0.5


def _watch_parent(parent: int) -> None:
    """End this worker when `parent` is gone. After a kill -9 of `study` (or of a sweep), its
    workers went on with their tasks and kept multiprocessing's resource tracker alive with
    them (issue 37): nothing was left to take their results. A thread that polls the parent
    id rather than prctl's PR_SET_PDEATHSIG, which fires when the *thread* that spawned the
    worker ends, not the process, and exists on Linux only."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_WATCH_S)
        os._exit(1)  # the parent is gone: its results have nowhere to go

    threading.Thread(target=watch, name="aimbench-parent-watch", daemon=True).start()


def _init_local(messages: Any, stop: Any, warm: Warm | None = None,
                parent: int | None = None) -> None:
    global _messages, _stop
    if parent is not None:
        _watch_parent(parent)
    # The caller decides when to stop (its own SIGINT handler sets `stop`).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ.update(WORKER_ENV)
    _messages, _stop = messages, stop
    if warm is not None:
        fn, args = warm
        # Only a head start: what fails here fails again in the worker's first task, which
        # reports it as that task's error (an initializer's exception would break the pool).
        with contextlib.suppress(Exception):
            fn(*args)


def _started() -> int:
    """The task that makes the pool spawn a worker (`LocalEngine.start`)."""
    return os.getpid()


_END = "__aimbench_task_end__"


def _run_local(key: Hashable, fn: Callable, args: tuple) -> Any:
    global _task_key
    _task_key = key
    try:
        return fn(*args)
    finally:
        # Every message of the task is in the queue before this marker: the caller waits for it
        # before it takes the result, so messages always come first.
        _messages.put((key, _END))


def _run_ray(fn: Callable, args: tuple) -> tuple[list, Any]:
    global _messages
    os.environ.update(WORKER_ENV)
    _messages = []
    try:
        return _messages, fn(*args)
    finally:
        _messages = None


# -- the engines -------------------------------------------------------------------------------

class LocalEngine:
    """Tasks on `jobs` worker processes of this machine (spawned, never forked: MuJoCo and
    threads), at most `jobs` in flight, dealt in the order given.

    warm: ``(fn, args)`` every worker runs as it starts, before its first task (a module-level
    function: e.g. build its twin and load its compiled kernels); `start` spawns the workers
    ahead of `run`, so that this start-up overlaps what the caller does meanwhile.
    """

    name = "local"

    def __init__(self, jobs: int = 1, warm: Warm | None = None) -> None:
        self.jobs = max(1, int(jobs))
        self.warm = warm
        self.retries = 0  # tasks run again after a lost worker (for the caller's log)
        self.workers: list[int] = []
        #: `start`'s context, queue, stop event and pool, until `run` takes them.
        self._early: tuple[Any, Any, Any, cf.ProcessPoolExecutor] | None = None

    def describe(self) -> str:
        return f"{self.jobs} local worker process{'es' if self.jobs > 1 else ''}"

    def start(self) -> LocalEngine:
        """Spawn the workers now (each runs `warm`), for the next `run` to use."""
        if self._early is None:
            ctx = mp.get_context("spawn")
            messages, stop = ctx.Queue(), ctx.Event()
            pool = self._pool(ctx, messages, stop)
            with _sigint_ignored():  # workers are spawned here: they inherit SIG_IGN
                # One task per worker: the pool spawns a process per task while none is idle.
                for _ in range(self.jobs):
                    pool.submit(_started)
            self.workers = [p.pid for p in (pool._processes or {}).values()]
            self._early = (ctx, messages, stop, pool)
        return self

    def close(self) -> None:
        """Stop the workers `start` spawned if no `run` took them."""
        if self._early is not None:
            self._early[2].set()
            self._early[3].shutdown(wait=True, cancel_futures=True)
            self._early = None

    def _pool(self, ctx: Any, messages: Any, stop: Any) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(self.jobs, mp_context=ctx, initializer=_init_local,
                                      initargs=(messages, stop, self.warm, os.getpid()))

    def run(self, fn: Callable, tasks: Sequence[Task], on_result: OnResult,
            on_message: OnMessage | None = None, should_stop: Callable[[], bool] = lambda: False,
            retry: Retry | None = None, on_lost: Callable[[Hashable], None] | None = None
            ) -> bool:
        """Run every task; True if stopped by `should_stop` before all were done."""
        if self._early is not None:
            ctx, messages, stop, pool = self._early
            self._early = None
        else:
            ctx = mp.get_context("spawn")
            messages, stop = ctx.Queue(), ctx.Event()
            pool = None
        todo = list(tasks)
        tries: dict[Hashable, int] = {}
        while True:
            lost, rest = self._run_pool(ctx, messages, stop, fn, todo, on_result, on_message,
                                        should_stop, pool)
            pool = None  # a pool that lost a worker is gone: the next attempt makes its own
            if not lost or stop.is_set():
                return stop.is_set()
            todo = []
            for key, args in lost:
                tries[key] = tries.get(key, 0) + 1
                if tries[key] > MAX_RETRIES:
                    raise WorkerLost(f"task {key} lost its worker {tries[key]} times; giving up "
                                     "(is the machine out of memory?)")
                if on_lost is not None:
                    on_lost(key)
                args = retry(key, args) if retry is not None else args
                if args is not None:
                    todo.append((key, args))
                    self.retries += 1
            todo += rest

    def _run_pool(self, ctx: Any, messages: Any, stop: Any, fn: Callable, todo: list[Task],
                  on_result: OnResult, on_message: OnMessage | None,
                  should_stop: Callable[[], bool], pool: cf.ProcessPoolExecutor | None = None
                  ) -> tuple[list[Task], list[Task]]:
        """Run `todo` on one pool (`pool`, or a new one); the tasks it lost to a dead worker
        (the pool is then gone) and those it had not started."""
        pending = list(reversed(todo))
        running: dict[cf.Future, Task] = {}
        finished: dict[Hashable, Any] = {}  # results waiting for their end marker
        ended: set[Hashable] = set()
        lost: list[Task] = []
        pool = pool if pool is not None else self._pool(ctx, messages, stop)

        def deliver(block: bool) -> None:
            self._drain(messages, on_message, ended, block)
            for key in [k for k in finished if k in ended]:
                ended.discard(key)
                on_result(key, finished.pop(key))

        try:
            while pending or running or finished:
                if should_stop() and not stop.is_set():
                    stop.set()
                    pending.clear()
                while pending and len(running) < self.jobs and not lost:
                    key, args = pending.pop()
                    with _sigint_ignored():  # workers are spawned here: they inherit SIG_IGN
                        running[pool.submit(_run_local, key, fn, args)] = (key, args)
                    self.workers = [p.pid for p in (pool._processes or {}).values()]
                done, _ = cf.wait(running, timeout=0.05, return_when=cf.FIRST_COMPLETED)
                for fut in done:
                    key, args = running.pop(fut)
                    try:
                        finished[key] = fut.result()
                    except cf.process.BrokenProcessPool:
                        lost.append((key, args))
                deliver(block=not done and bool(finished))
                if lost and not running:
                    # A dead worker breaks the whole pool: the tasks in flight with it come
                    # back lost too; those that had finished still deliver (their end marker
                    # is in the queue), the rest run again on a new pool.
                    deadline = time.monotonic() + 10.0
                    while finished and time.monotonic() < deadline:
                        deliver(block=True)
                    return lost, list(reversed(pending))
        except BaseException:
            stop.set()  # the caller is going away: the workers stop between their steps
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return lost, []

    @staticmethod
    def _drain(messages: Any, on_message: OnMessage | None, ended: set, block: bool) -> None:
        """Hand the queued messages to `on_message`; note the tasks whose end marker came."""
        try:
            item = messages.get(timeout=0.2) if block else messages.get_nowait()
            while True:
                key, msg = item
                if isinstance(msg, str) and msg == _END:
                    ended.add(key)
                elif on_message is not None:
                    on_message(key, msg)
                item = messages.get_nowait()
        except queue.Empty:
            return


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored while workers are spawned (a Ctrl-C at the terminal reaches the whole
    process group; the workers hear of it only through the stop event)."""
    main = threading.current_thread() is threading.main_thread()
    saved = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGINT, saved)


def import_ray() -> Any:
    """The `ray` module, or an `EngineError` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise EngineError(NO_RAY) from None
    return ray


def project_root() -> Path:
    """The folder that holds the project's import packages (this file is scenarios/study/)."""
    return Path(__file__).resolve().parents[2]


def runtime_env(kind: str) -> dict[str, Any] | None:
    """The Ray runtime environment that puts the project on a cluster's workers.

    ``modules``: the project's own packages uploaded with the job (Ray's ``py_modules``), its
    third-party dependencies taken as the cluster has them; ``pip``: the same, and the
    project's dependencies installed on the workers by Ray (its ``pip`` field: the workers
    need a package index); ``none``: nothing shipped (the workers import the project as the
    driver's machine has it installed: a Ray started on this machine).
    """
    if kind == "none":
        return {"env_vars": dict(WORKER_ENV)}
    if kind not in ("modules", "pip"):
        raise EngineError(f"unknown Ray runtime environment {kind!r}; use modules, pip or none")
    root = project_root()
    env: dict[str, Any] = {
        "py_modules": [str(root / p) for p in PROJECT_PACKAGES if (root / p).is_dir()],
        "env_vars": dict(WORKER_ENV),
        # Ray's default leaves out what .gitignore does; the firmware's build folder too.
        "excludes": ["build/", "__pycache__/", "*.nbi", "*.nbc"],
    }
    if kind == "pip":
        env["pip"] = project_dependencies()
    return env


def project_dependencies() -> list[str]:
    """The project's runtime dependencies as pyproject.toml lists them (for Ray's ``pip``)."""
    from importlib import metadata

    try:
        reqs = metadata.requires("aimbench") or []
    except metadata.PackageNotFoundError:
        raise EngineError("aimbench is not installed here (pip install -e .), so its "
                          "dependencies are unknown; use --ray-env modules") from None
    return [r for r in reqs if "extra ==" not in r]


class RayEngine:
    """Tasks on a Ray cluster (``address``: ``ray://HOST:PORT``, ``HOST:PORT`` or ``auto``), or on
    a Ray started here with `num_cpus` CPUs (``address`` None). One CPU per task; at most twice
    the cluster's CPUs in flight, so a Ctrl-C has little to cancel. ``env``: `runtime_env`'s
    kind (default: ``modules`` on a cluster, ``none`` on a Ray started here)."""

    name = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None,
                 env: str | None = None) -> None:
        self.ray = import_ray()
        self.address = address
        self.retries = 0
        self.workers: list[int] = []
        self._started = False
        # ray.init makes SIGTERM exit this process (its driver's handler) and shutdown leaves
        # it so: the handler found here is put back by `close`
        self._sigterm = signal.getsignal(signal.SIGTERM)
        if not self.ray.is_initialized():
            kind = env or ("none" if address is None else "modules")
            try:
                self.ray.init(address=address, num_cpus=num_cpus if address is None else None,
                              runtime_env=runtime_env(kind), include_dashboard=False,
                              log_to_driver=False, configure_logging=False)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise EngineError(f"cannot reach the Ray cluster at {address}: {exc}; start one "
                                  "(ray start --head) or check --address") from None
            self._started = True
        self.env = env
        self.cpus = max(1, int(self.ray.cluster_resources().get("CPU", 1)))
        self._remote = self.ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_run_ray)

    def describe(self) -> str:
        where = self.address or "a Ray started here"
        return f"Ray ({where}, {self.cpus} CPUs)"

    def close(self) -> None:
        if self._started:
            self.ray.shutdown()
            self._started = False
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGTERM, self._sigterm)

    def run(self, fn: Callable, tasks: Sequence[Task], on_result: OnResult,
            on_message: OnMessage | None = None, should_stop: Callable[[], bool] = lambda: False,
            retry: Retry | None = None, on_lost: Callable[[Hashable], None] | None = None
            ) -> bool:
        """Run every task; True if stopped by `should_stop` before all were done. Ray itself
        retries a task whose worker died (`MAX_RETRIES` times)."""
        ray = self.ray
        pending = list(reversed(tasks))
        running: dict[Any, Hashable] = {}
        window = 2 * self.cpus
        while pending or running:
            if should_stop():
                for ref in running:
                    ray.cancel(ref, force=True)
                return True
            while pending and len(running) < window:
                key, args = pending.pop()
                running[self._remote.remote(fn, args)] = key
            done, _ = ray.wait(list(running), num_returns=1, timeout=0.5)
            for ref in done:
                key = running.pop(ref)
                try:
                    messages, result = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    raise WorkerLost(f"task {key} failed on Ray: {type(exc).__name__}: "
                                     f"{str(exc).splitlines()[0] if str(exc) else ''}") from None
                if on_message is not None:
                    for msg in messages:
                        on_message(key, msg)
                on_result(key, result)
        return False


def make_engine(name: str, jobs: int = 1, address: str | None = None,
                ray_cpus: int | None = None, ray_env: str | None = None) -> Any:
    """The engine a command line names (``local`` or ``ray``)."""
    if name == "local":
        return LocalEngine(jobs)
    if name == "ray":
        return RayEngine(address, num_cpus=ray_cpus if ray_cpus else jobs if jobs > 1 else None,
                         env=ray_env)
    raise EngineError(f"unknown engine {name!r}; use local or ray")


def wall_and_cpu() -> tuple[float, float]:
    """(wall s, CPU s of this process and its finished children), for the benchmarks."""
    t = os.times()
    return time.perf_counter(), t.user + t.system + t.children_user + t.children_system
