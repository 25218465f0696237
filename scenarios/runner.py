"""Run a plan on a bench into a store: move, scan, estimate, commit, one scan at a time.

The loop commits the scans' results in scan order, a few per transaction (what arrived in the
last `_OrderedCommits.FLUSH_S`: every commit is fsynced), and all of them before it stops, so:

- a crash (SIGKILL, power cut) loses at most the scans of that last fraction of a second, which
  the store never had, and ``--resume`` continues from the store: references already done are
  skipped, a reference half done takes only its missing scans (numbered after the stored ones,
  which are always 0 .. m - 1), and ``UNIQUE(reference, scan)`` in the store makes a duplicate
  impossible; on the simulated bench the scans taken again are the very same (seeded);
- Ctrl-C (SIGINT) or SIGTERM sets a flag checked between scans: the run stops cleanly with every
  finished scan committed, is marked ``interrupted``, and the bench is closed. A second Ctrl-C
  stops at once (still safe: a transaction is atomic).

Failures a user can fix (a port that does not open, a silent LiDAR, a board not in view, a
reference beyond travel) mark the run ``failed`` in the store with where it failed (reference,
scan) and why, and raise `RunFailed` with one clear line.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import logging
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np

import align
from align import PoseEstimate, Status
from align.calibration import LaserCalibration
from scenarios import calibrate
from scenarios.bench import Bench, BenchError, TravelError
from scenarios.config import MAX_CONSECUTIVE_FAILURES
from scenarios.interrupt import StopFlag
from scenarios.plans import Plan, Reference, references_beyond
from scenarios.progress import Bar, is_terminal
from scenarios.store import ScanResult, Store, StoreError
from scenarios.truth import scan_truth
from twin.core.errors import AimbenchError
from twin.core.pose import StagePose
from twin.core.scan import Scan


class RunFailed(AimbenchError):
    """The run stopped on a failure; the store says where (reference, scan) and why."""


def _record_failure(store: Store, plan: Plan, where: dict[str, int | None],
                    exc: AimbenchError) -> RunFailed:
    """Mark the run (and the reference it failed at, if any) failed in the store, and return
    the `RunFailed` to raise, its message saying where: ``where`` holds reference and scan."""
    i, k = where["reference"], where["scan"]
    message = str(exc)
    if i is not None:
        store.finish_reference(i, "failed", message)
        message = (f"at reference {i} ({plan.references[i].describe()})"
                   + (f", scan {k}" if k is not None else "") + f": {message}")
    store.set_status("failed", message, i, k)
    return RunFailed(message)


@dataclass
class PipelineCPU:
    """CPU time (s) a run spent inside its scans' emulation (or acquisition) and their
    estimates, in whichever process took them: what is not here is the runner's and the
    store's overhead (benchmarks/bench_sweep.py)."""

    scans: int = 0
    acquire_s: float = 0.0
    estimate_s: float = 0.0
    #: Worker processes' CPU up to the end of their warm-up (`_sim_warm`: the interpreter,
    #: imports, the twin, the kernels' first calls): a run's fixed cost, not a scan's.
    startup_s: float = 0.0

    def add(self, acquire_s: float, estimate_s: float) -> None:
        self.scans += 1
        self.acquire_s += acquire_s
        self.estimate_s += estimate_s

    def merge(self, other: PipelineCPU) -> None:
        self.scans += other.scans
        self.acquire_s += other.acquire_s
        self.estimate_s += other.estimate_s
        self.startup_s += other.startup_s


#: The runner's estimate of one scan: align's own answer (`align.PoseEstimate`), stored as is.
Estimator = Callable[[Scan], PoseEstimate]


def make_estimator(method: str | None = None, board: Any = None,
                   calibration: LaserCalibration | None = None,
                   station: Any = None) -> Estimator:
    """align's estimate of one scan the way a run makes it: its method (None: align's default),
    its board (None: the paper's), and its sensor calibration, applied to every scan before
    estimating (the run's configuration keeps it, so a resume or a replay uses the same), with
    the hints of its ``station`` (`scenarios.station.Station.estimate_hints`: a new unit's
    range offset estimated unless the calibration measured it; None: the paper's station, as a
    run's configuration has it without a station file, so that a replay estimates alike). An
    unknown method is refused here, before any move.

    An exception inside the estimator becomes a failed estimate (`Status.ESTIMATOR_ERROR`, the
    message as its diagnostic) rather than a crashed run: one bad scan must not lose a sweep.
    """
    if method is not None and method not in align.METHODS:
        raise AimbenchError(f"unknown estimation method {method!r}; use one of "
                            f"{', '.join(align.METHODS)}")
    if method == "icp":  # a resumed run, a plan file: the command line checks its own --method
        from scenarios.extras import require

        require("open3d", "the method icp")
    name = method if method is not None else align.DEFAULT_METHOD
    board = board if board is not None else align.BoardSpec()
    if station is None:
        from scenarios.station import Station

        station = Station()
    hints = station.estimate_hints(calibrated=calibration is not None)

    def estimate(scan: Scan) -> PoseEstimate:
        try:
            if calibration is not None:
                scan = calibrate.apply(scan, calibration)  # another model's: one line
            return align.estimate([scan], board=board, method=name, hints=hints)
        except AimbenchError:
            raise
        except Exception as exc:  # an estimator bug on one scan: record it, keep the run
            return PoseEstimate.failed(Status.ESTIMATOR_ERROR, name,
                                       error=f"{type(exc).__name__}: {exc}")

    return estimate


class Progress:
    """The sweep's progress on stderr with the estimate so far at the current reference.

    On a terminal a `scenarios.progress.Bar` (tqdm) over all the plan's scans, with the current
    reference and its running estimate after it; otherwise one whole line per finished
    reference, so logs stay short. Keeps the running estimate per reference, so parallel
    workers interleaving references each show their own.
    """

    def __init__(self, plan: Plan, stream: TextIO | None = None, enabled: bool = True,
                 tty: bool | None = None) -> None:
        self.plan = plan
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.total = plan.total_scans
        self.done = 0
        self.started = time.monotonic()
        self.session_scans = 0
        self._ref = 0
        self._acc: dict[int, dict] = {}
        self._tty = tty
        self._bar: Bar | None = None

    @property
    def tty(self) -> bool:
        return self.enabled and (is_terminal(self.stream) if self._tty is None else self._tty)

    def _ensure_bar(self) -> Bar:
        # Made at the first reference, once `skip` has counted what a resumed run holds.
        if self._bar is None:
            self._bar = Bar(self.total, self.plan.name, "scans", stream=self.stream,
                            enabled=self.enabled, every=None, initial=self.done, tty=self.tty)
        return self._bar

    def start_reference(self, index: int, already: int) -> None:
        self._ref = index
        self._acc[index] = {"done": already, "yaw": [], "x": [], "fail": 0}
        self._ensure_bar().set_status(self.status(index))

    def skip(self, n: int) -> None:
        self.done += n

    def scan(self, est: PoseEstimate, reference: int | None = None) -> None:
        if reference is not None:
            self._ref = reference
        acc = self._acc.setdefault(self._ref, {"done": 0, "yaw": [], "x": [], "fail": 0})
        self.done += 1
        self.session_scans += 1
        acc["done"] += 1
        if est.success:
            acc["yaw"].append(est.pose.yaw)
            acc["x"].append(est.pose.x)
        else:
            acc["fail"] += 1
        self._ensure_bar().update(1, self.status() if self.tty else None)

    def status(self, reference: int | None = None) -> str:
        """The reference, its scan count and its estimate so far (what follows the bar)."""
        i = self._ref if reference is None else reference
        ref = self.plan.references[i]
        acc = self._acc.get(i, {"done": 0, "yaw": [], "x": [], "fail": 0})
        text = (f"ref {i + 1}/{len(self.plan)} ({ref.describe()}) "
                f"scan {acc['done']}/{self.plan.scans}")
        if acc["yaw"]:
            yaw = np.degrees(acc["yaw"])
            x = np.array(acc["x"]) * 1e3
            text += (f" | estimate (board frame): yaw {yaw.mean():+.3f}±{yaw.std():.3f} deg"
                     f" x {x.mean():+.1f}±{x.std():.1f} mm")
        if acc["fail"]:
            text += f" | {acc['fail']} without pose"
        return text

    def line(self, reference: int | None = None) -> str:
        """The whole line a log gets per finished reference: share done, status, rate, ETA."""
        frac = self.done / self.total if self.total else 1.0
        elapsed = time.monotonic() - self.started
        rate = self.session_scans / elapsed if elapsed > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else math.nan
        text = f"{100 * frac:5.1f}% {self.status(reference)} | {rate:.1f} scans/s"
        if math.isfinite(eta):
            text += f" ETA {int(eta // 60)}m{int(eta % 60):02d}s"
        return text

    def end_reference(self, reference: int | None = None) -> None:
        if not self.enabled:
            return
        if not self.tty:
            self._ensure_bar().write(self.line(reference))
        self._acc.pop(self._ref if reference is None else reference, None)

    def finish(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def message(self, text: str) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.write(text)
        else:
            self.stream.write(text + "\n")
            self.stream.flush()


class Runner:
    """Runs `plan` on `bench` into `store` with `estimator`.

    max_consecutive_failures: scans in a row without a pose, with none at this reference, after
        which the board is declared not in view and the run fails.
    move_timeout_s: longest wait for the stages to arrive at a reference.
    check_scans: called once with the run's first few raw scans (before any calibration is
        applied), e.g. to check that they fit the calibration; it reports what it finds.
    """

    #: Scans `check_scans` gets.
    CHECK_SCANS = 3

    def __init__(self, plan: Plan, bench: Bench, store: Store, estimator: Estimator,
                 progress: Progress | None = None,
                 max_consecutive_failures: int = MAX_CONSECUTIVE_FAILURES,
                 move_timeout_s: float = 120.0,
                 check_scans: Callable[[list[Scan]], None] | None = None) -> None:
        self.plan = plan
        self._check_scans = check_scans
        self._first_scans: list[Scan] = []
        self.bench = bench
        self.store = store
        self.estimator = estimator
        self.progress = progress or Progress(plan, enabled=False)
        self.max_consecutive_failures = max_consecutive_failures
        self.move_timeout_s = move_timeout_s
        self.stop = False
        #: CPU of this run's scans and estimates (in the workers, for a parallel run).
        self.cpu = PipelineCPU()

    def request_stop(self) -> None:
        """Stop after the scan in flight (what Ctrl-C does); safe from another thread."""
        self.stop = True

    #: What Ctrl-C says while the run winds down.
    stop_message = ("stopping after this scan (results so far are saved; --resume continues; "
                    "Ctrl-C again to stop at once)")

    def run(self) -> str:
        """Run (or resume) the plan; returns the final status (``completed``/``interrupted``).

        Raises `RunFailed` after marking the run failed.
        """
        store, plan = self.store, self.plan
        resumed = store.scan_count() > 0 or store.status not in ("created",)
        with StopFlag(lambda: self.progress.message(self.stop_message)) as flag:
            store.set_status("running", ("resumed" if resumed else "started") + self._how())
            where: dict[str, int | None] = {"reference": None, "scan": None}
            try:
                self._check_travel(where)
                if self._execute(self._pending(), flag, where):
                    return self._interrupted(flag)
                store.set_status("completed")
                self.progress.finish()
                return "completed"
            except KeyboardInterrupt:
                return self._interrupted(flag)
            except AimbenchError as exc:
                self.progress.finish()
                raise _record_failure(store, plan, where, exc) from exc
            finally:
                self._release()

    def _how(self) -> str:
        """What the run's start event adds after "started"/"resumed"."""
        return ""

    def _pending(self) -> list[tuple[int, int, int]]:
        """(reference, first scan, scans to take) of every reference not yet done, in order;
        references already complete are counted as done (and marked so if they are not)."""
        todo = []
        for i in range(len(self.plan)):
            done = self.store.done_scans(i)
            self.progress.skip(len(done))
            if len(done) >= self.plan.scans:
                if self.store.references()[i]["status"] != "done":
                    self.store.finish_reference(i, "done")
            else:
                todo.append((i, (max(done) + 1) if done else 0, self.plan.scans - len(done)))
        return todo

    def _execute(self, todo: list[tuple[int, int, int]], flag: StopFlag, where: dict) -> bool:
        """Take the scans of `todo` on this process's bench; True if stopped by a signal."""
        self.bench.home()
        for i, first, n in todo:
            where.update(reference=i, scan=None)
            if self._stopping(flag):
                return True
            ref = self.plan.references[i]
            stage = self._go_to(ref)
            self.store.start_reference(i, stage)
            self.progress.start_reference(i, self.plan.scans - n)
            self.bench.prepare(i, first)
            if self._take_scans(i, ref, first, n, flag, where):
                return True
            self.store.finish_reference(i, "done")
            self.progress.end_reference()
        return False

    def _release(self) -> None:
        self.bench.close()

    # -- steps -----------------------------------------------------------------------------

    def _stopping(self, flag: StopFlag) -> bool:
        return self.stop or flag.stop

    def _interrupted(self, flag: StopFlag) -> str:
        self.progress.finish()
        self.store.set_status("interrupted", f"stopped by {flag.signal or 'request'}; "
                                             f"{self.store.scan_count()} scans saved")
        return "interrupted"

    def _check_travel(self, where: dict) -> None:
        """Refuse the plan before any move if a reference is beyond the stages' travel (the
        run fails at the first such reference)."""
        mounted = [i for i, r in enumerate(self.plan.references) if r.mount]
        if mounted and not self.bench.can_set_mount:
            where["reference"] = mounted[0]
            raise BenchError(f"the plan changes the LiDAR's mount ({len(mounted)} references), "
                             f"which the {self.bench.kind} bench cannot do; run it with --bench "
                             "sim; nothing was moved")
        yaw_lim, x_lim = self.bench.travel()
        beyond = list(references_beyond(self.plan, yaw_lim, x_lim))
        if beyond:
            i, ref = beyond[0]
            where["reference"] = i
            try:
                self.bench.check_reachable(ref.stage, "the reference")
                if ref.via:
                    self.bench.check_reachable(ref.via,
                                               f"its approach point ({ref.via.describe()})")
            except TravelError as exc:
                more = f" ({len(beyond) - 1} more beyond travel)" if len(beyond) > 1 else ""
                raise TravelError(f"{exc}{more}; nothing was moved") from None

    def _go_to(self, ref: Reference) -> StagePose:
        return visit(self.bench, ref, self.move_timeout_s)

    def _take_scans(self, i: int, ref: Reference, first: int, n: int, flag: StopFlag,
                    where: dict) -> bool:
        """Take and store `n` scans numbered from `first`; True if stopped by a signal."""
        watch = _FailureWatch(self.max_consecutive_failures)
        # A few scans per transaction (`_OrderedCommits`): all committed before this returns,
        # stopped, failed or done.
        commits = _OrderedCommits(self.store, [(i, first, n)], lambda r: None)
        k = first
        where["scan"] = k
        scans = self.bench.scans(n)
        try:
            t0, c0 = time.monotonic(), time.process_time()
            for scan in scans:
                t_scan = time.monotonic() - t0
                c_scan = time.process_time() - c0
                self._checking(scan)
                t1, c1 = time.monotonic(), time.process_time()
                est = self.estimator(scan)
                t_est = time.monotonic() - t1
                self.cpu.add(c_scan, time.process_time() - c1)
                try:
                    stage = self.bench.position()
                except BenchError:
                    stage = None
                commits.add(scan_result(i, k, scan, est, stage, t_scan, t_est))
                self.progress.scan(est)
                watch.add(est)
                k += 1
                where["scan"] = k
                if self._stopping(flag):
                    return True
                t0, c0 = time.monotonic(), time.process_time()
        finally:
            close = getattr(scans, "close", None)
            if close is not None:
                close()
            commits.flush()
        return False


    def _checking(self, scan: Scan) -> None:
        """Hand the run's first `CHECK_SCANS` scans to ``check_scans``, once."""
        if self._check_scans is None:
            return
        self._first_scans.append(scan)
        if len(self._first_scans) >= self.CHECK_SCANS:
            check, self._check_scans = self._check_scans, None
            check(self._first_scans)
            self._first_scans = []


def visit(bench: Bench, ref: Reference, timeout_s: float = 120.0) -> StagePose:
    """Bring `bench` to `ref` the way every run does: its mount, its approach point if it has
    one, then the reference itself; returns where the stages say they arrived."""
    bench.set_mount(ref.mount)
    if ref.via is not None:
        bench.move_to(x_m=ref.via.x_m, yaw_rad=ref.via.yaw_rad)
        bench.wait_until_there(timeout_s)
    bench.move_to(x_m=ref.x_m, yaw_rad=ref.yaw_rad)
    return bench.wait_until_there(timeout_s)


def scan_result(reference: int, k: int, scan: Scan, est: PoseEstimate,
                stage: StagePose | None, scan_s: float, estimate_s: float) -> ScanResult:
    """What the store keeps of scan `k` at `reference` and its estimate: the estimate without
    its ``used`` indices (the store keeps none; a parallel run's workers would send them to the
    writing process for nothing)."""
    return ScanResult(
        reference=reference, scan=k, estimate=dataclasses.replace(est, used={}),
        truth=scan_truth(scan), stage=stage, points=int(np.count_nonzero(scan.valid)),
        complete=bool(scan.complete), missing_packets=int(scan.missing_packets),
        acquired_at=time.time(), scan_s=scan_s, estimate_s=estimate_s)


class _FailureWatch:
    """Counts a reference's scans without a pose; raises when `limit` came in a row and none at
    this reference gave one: the board is not in view, and more scans will not bring it back."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.consecutive = 0
        self.successes = 0

    def add(self, est: PoseEstimate) -> None:
        self.successes += est.success
        self.consecutive = 0 if est.success else self.consecutive + 1
        if self.successes == 0 and self.consecutive >= self.limit:
            raise _no_board(self.consecutive, str(est.status), est.diagnostics)


def _no_board(consecutive: int, status: str, diagnostics: dict) -> BenchError:
    """The error of a reference where no scan gave a pose."""
    hint = next((f": {diagnostics[k]}" for k in ("reason", "message", "error")
                 if k in (diagnostics or {})), "")
    return BenchError(f"no pose in {consecutive} scans in a row (last status {status!r}{hint}): "
                      "the board is not in view or not found; check the board, the LiDAR's aim "
                      "and the estimator's hints")


# -- parallel runs on the simulated bench -------------------------------------------------------

#: A worker process's bench, estimator and plan, kept between its references (key: the run's
#: setup as JSON): building the twin once per process, not once per reference.
_worker_bench: dict[str, tuple[Any, Estimator, Plan]] = {}
#: A worker process's twin (key: `_twin_key`), built by its warm-up (`_sim_warm`) or its first
#: task, whichever comes first.
_worker_twin: dict[str, Any] = {}
#: This worker's CPU at the end of its warm-up, s, until its first task reports it.
_worker_started: dict[str, float] = {}
#: The `SimBench.prepare` reference of a worker's warm-up scan: no plan's (the warm-up changes
#: no scan of a run: each is drawn from (seed, reference, scan) alone).
WARM_UP_REFERENCE = 2_000_000
#: Whether this worker process has registered `_exit_at_once`.
_worker_exit = {"registered": False}


def _exit_at_once() -> None:
    """A sweep worker's end (an `atexit` handler, the last registered, so the first run):
    its streams flushed, then `os._exit` without the interpreter's teardown.

    Why: that teardown (freeing MuJoCo's model, numba's and LLVM's code, every module) takes
    0.6 s of a worker that has scanned, and the pool waits for its workers to exit before the
    sweep's report can begin. Nothing of the worker's needs it: its results are all sent
    (multiprocessing flushed its queue before the interpreter began to exit), it has no file
    open and made no temporary file; the handlers it skips set numba's and llvmlite's
    at-shutdown flags and flush `logging` (done here). A pool worker that gets this far ends
    with status 0 in any case (a crash or a kill never runs `atexit`)."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(0)


def _twin_key(setup: dict) -> str:
    """What a worker's twin depends on (a run's setup, or a warm-up's): its seed, whether it is
    ideal, and its station."""
    import json

    return json.dumps({k: setup.get(k) for k in ("seed", "ideal", "station")}, sort_keys=True,
                      default=str)


def _worker_twin_for(setup: dict) -> Any:
    """This worker's SimBench for `setup` (built and homed once per process)."""
    import multiprocessing
    import warnings

    from scenarios import station as stations
    from scenarios.bench import SimBench

    key = _twin_key(setup)
    if key not in _worker_twin:
        if not _worker_exit["registered"] and multiprocessing.parent_process() is not None:
            # a worker process of the pool (never the process that runs the sweep), once
            atexit.register(_exit_at_once)
            _worker_exit["registered"] = True
        warnings.simplefilter("ignore", RuntimeWarning)  # the twin's NaN masks
        _worker_twin.clear()
        station = setup["station"]
        st = stations.from_dict(station, "the run's station") if station else None
        bench = SimBench(seed=setup["seed"], ideal=setup["ideal"], station=st)
        bench.home()
        _worker_twin[key] = bench
    return _worker_twin[key]


def _worker_setup(setup: dict) -> tuple[Any, Estimator, Plan]:
    import json

    cal = setup["calibration"]  # a `LaserCalibration`: keyed by its content
    key = json.dumps({**setup, "calibration": cal.to_dict() if cal is not None else None},
                     sort_keys=True, default=str)
    if key not in _worker_bench:
        bench = _worker_twin_for(setup)
        _worker_bench.clear()
        st = bench.station
        estimator = make_estimator(setup["method"], st.board_spec() if st else None,
                                   setup["calibration"], st)
        _worker_bench[key] = (bench, estimator, Plan.from_dict(setup["plan"]))
    return _worker_bench[key]


def _sim_warm(twin: dict, method: str | None) -> None:
    """A sweep worker's head start, as it starts (`LocalEngine`'s warm-up): its twin built and
    homed, and the numba kernels of the emulation and of `method`'s estimate loaded from their
    cache (the first call of each in a process: about a second), by one scan of a reference
    outside every plan, estimated without calibration. It runs while the sweep's own process
    is still busy (the demo's calibration, the store, its own twin for the plan's travel)."""
    bench = _worker_twin_for(twin)
    st = bench.station
    bench.prepare(WARM_UP_REFERENCE, 0)
    scan = next(bench.scans(1))
    make_estimator(method, st.board_spec() if st else None)(scan)
    _worker_started["cpu_s"] = time.process_time()


def sim_twin(seed: int, ideal: bool, station: Any) -> dict:
    """The part of a parallel sweep's worker setup its twin depends on (`_twin_key`)."""
    return {"seed": seed, "ideal": ideal,
            "station": station.to_dict() if station is not None else None}


def sim_engine(jobs: int, seed: int = 0, ideal: bool = False, station: Any = None,
               method: str | None = None) -> Any:
    """A `LocalEngine` for `ParallelSimRunner` whose workers are started now, each warming up
    its twin and its kernels (`_sim_warm`) while the caller goes on: give it to the runner
    (``engine=``) of the run with the same seed, ideal, station and method, or `close` it."""
    from scenarios.study.engines import LocalEngine

    return LocalEngine(jobs, warm=(_sim_warm, (sim_twin(seed, ideal, station), method))).start()


def _sim_reference(setup: dict, i: int, first: int, n: int) -> Any:
    """A task of the parallel path (`scenarios.study.engines`): scans `first` .. `first` + `n` - 1
    of reference `i` on this worker's SimBench (of the run's station, sent as its stored dict),
    each result emitted as it is made; returns "done", "stopped" (the caller asked to stop,
    between scans) or ("error", reference, scan, message)."""
    from scenarios.study.engines import emit, stopping

    k = None
    cpu = PipelineCPU()
    try:
        bench, estimator, plan = _worker_setup(setup)
        emit(("start", i, visit(bench, plan.references[i]), first))
        bench.prepare(i, first)
        k = first
        t0, c0 = time.monotonic(), time.process_time()
        for scan in bench.scans(n):
            t_scan = time.monotonic() - t0
            t1, c1 = time.monotonic(), time.process_time()
            est = estimator(scan)
            t_est = time.monotonic() - t1
            cpu.add(c1 - c0, time.process_time() - c1)
            emit(("scan", scan_result(i, k, scan, est, bench.position(), t_scan, t_est)))
            k += 1
            if stopping():
                return "stopped"
            t0, c0 = time.monotonic(), time.process_time()
        return "done"
    except AimbenchError as exc:
        return ("error", i, k, str(exc))
    except Exception as exc:  # a bug in a worker must reach the user, not hang the run
        return ("error", i, k, f"{type(exc).__name__}: {exc}")
    finally:
        cpu.startup_s = _worker_started.pop("cpu_s", 0.0)
        emit(("cpu", cpu))


class _OrderedCommits:
    """The workers' results, committed in scan order per reference, several per transaction.

    In order: a reference's stored scans are always 0 .. m - 1 with no hole, whatever the
    workers' timing, even when one reference's scans are taken by two workers at once
    (`_deal`); so an interrupted run stores a prefix of every reference and a resume takes
    the rest (`Runner._pending`). A result that arrives before its predecessors waits for
    them in memory; stopped before they come, it is dropped, never committed, and the resume
    takes it again: the same result, every scan being drawn from (seed, reference, scan).

    Several per transaction: every commit is fsynced (`scenarios.store`), milliseconds of a
    busy disk each, while two workers deliver a scan every few milliseconds. A result waits at
    most `FLUSH_S` (or `BATCH` results) for its commit; a kill meanwhile loses only results
    the store never had, which the resume takes again.
    """

    #: Longest a committable result waits for its transaction, s.
    FLUSH_S = 0.2
    #: Most results waiting for one transaction.
    BATCH = 64

    def __init__(self, store: Store, todo: list[tuple[int, int, int]],
                 on_commit: Callable[[ScanResult], None]) -> None:
        self.store = store
        self.on_commit = on_commit
        #: Per reference: the next scan to commit, the end of its pending range, and the
        #: results that came before their predecessors.
        self.next = {i: first for i, first, _ in todo}
        self.end = {i: first + n for i, first, n in todo}
        self.waiting: dict[int, dict[int, ScanResult]] = {i: {} for i, _, _ in todo}
        self.ready: list[ScanResult] = []
        self.last = time.monotonic()

    def add(self, r: ScanResult) -> None:
        i, k = r.reference, r.scan
        if i not in self.next or not self.next[i] <= k < self.end[i] or k in self.waiting[i]:
            raise StoreError(f"scan {k} of reference {i} arrived twice or was never asked for")
        waiting = self.waiting[i]
        waiting[k] = r
        while self.next[i] in waiting:
            self.ready.append(waiting.pop(self.next[i]))
            self.next[i] += 1
        if len(self.ready) >= self.BATCH or time.monotonic() - self.last >= self.FLUSH_S:
            self.flush()

    def flush(self, check: bool = True) -> None:
        """Commit the results that are next in their reference's order (one transaction);
        then hand each to ``on_commit`` (``check``: may raise, e.g. the board not in view)."""
        if self.ready:
            self.store.add_scans(self.ready)
            batch, self.ready = self.ready, []
            if check:
                for r in batch:
                    self.on_commit(r)
        self.last = time.monotonic()

    def received(self, i: int, first: int, n: int) -> int:
        """How many of scans `first` .. `first` + `n` - 1 of reference `i` arrived (a task's
        scans arrive in order: these are its first ones)."""
        return sum(1 for k in range(first, first + n)
                   if k < self.next[i] or k in self.waiting[i])


#: `_deal`: the chunks a reference of the run's last references is cut into.
TAIL_CHUNKS = 4


def _deal(todo: list[tuple[int, int, int]], jobs: int) -> list[tuple[int, int, int]]:
    """The tasks (reference, first scan, scans) of `todo` for `jobs` workers, in the order they
    are dealt: whole references, but the last `jobs` references in `TAIL_CHUNKS` chunks each.

    Why: the workers take the next task as they come free, so they end together within the
    last task they took; with whole references that is up to a reference's scans on one core
    while the other idles (21 references on 2 workers: 11 against 10), with chunks a quarter of
    one. Only the tail is cut: each task costs a visit of its reference (a move, a first scan
    without the pose's caches). Which worker takes a scan changes nothing in it (`SimBench`)."""
    if jobs <= 1 or not todo:
        return list(todo)
    head, tail = todo[:-jobs], todo[-jobs:]
    tasks = list(head)
    for i, first, n in tail:
        size = -(-n // TAIL_CHUNKS)
        tasks += [(i, a, min(size, first + n - a)) for a in range(first, first + n, size)]
    return tasks


class ParallelSimRunner(Runner):
    """`Runner` on `jobs` SimBench worker processes (the simulated bench only), through the
    project's one parallel path, `scenarios.study.engines.LocalEngine` (as ``aimbench study``).

    Each reference is a task (the last `jobs` references are cut into chunks so that the
    workers end together: `_deal`), dealt in reference order to the next free worker; every
    scan is drawn from (seed, reference, scan) alone (`SimBench`), so a run is the same
    whatever `jobs`. The store is written by this process only, in scan order per reference,
    a few scans per transaction (`_OrderedCommits`); Ctrl-C stops every worker between scans
    and everything committable is committed. A worker that dies (SIGKILL, out of memory)
    costs nothing but time: its task runs again on a new worker, from the first of its scans
    that did not arrive.
    """

    def __init__(self, plan: Plan, bench: Bench, store: Store, *, seed: int = 0,
                 ideal: bool = False, method: str | None = None,
                 calibration: LaserCalibration | None = None, jobs: int = 2,
                 progress: Progress | None = None,
                 max_consecutive_failures: int = MAX_CONSECUTIVE_FAILURES,
                 station: Any = None, engine: Any = None) -> None:
        super().__init__(plan, bench, store, estimator=lambda scan: None,  # type: ignore[arg-type]
                         progress=progress, max_consecutive_failures=max_consecutive_failures)
        self.seed, self.ideal, self.method, self.jobs = seed, ideal, method, max(1, int(jobs))
        self.calibration = calibration
        #: The run's `scenarios.station.Station` (None: the paper's), for the workers' twins.
        self.station = station
        #: The engine of the last `run` (its ``retries``: tasks run again after a lost
        #: worker; ``workers``: its processes' ids); given (`sim_engine`), its workers may
        #: already be started.
        self.engine: Any = engine

    stop_message = ("stopping after the scans in flight (results so far are saved; --resume "
                    "continues; Ctrl-C again to stop at once)")

    def _how(self) -> str:
        return f" on {self.jobs} worker processes"

    def _release(self) -> None:
        super()._release()
        if self.engine is not None:  # workers started ahead that no run took (a failure)
            self.engine.close()

    def _execute(self, todo: list[tuple[int, int, int]], flag: StopFlag, where: dict) -> bool:
        """Deal `todo` to the workers and store what they send; True if stopped by a signal."""
        from scenarios.study.engines import LocalEngine

        self.bench.close()  # travel and info only: the workers have their own twins
        setup = {"plan": self.plan.to_dict(), "method": self.method,
                 "calibration": self.calibration,
                 **sim_twin(self.seed, self.ideal, self.station)}
        tasks = _deal(todo, self.jobs)
        left = {i: 0 for i, _, _ in todo}  # tasks not yet done per reference
        for i, _, _ in tasks:
            left[i] += 1
        stored = {i: self.plan.scans - n for i, _, n in todo}  # before this session
        started: set[int] = set()
        watches: dict[int, _FailureWatch] = {}

        def on_commit(r: ScanResult) -> None:
            where.update(reference=r.reference, scan=r.scan)
            self.progress.scan(r.estimate, r.reference)
            watches.setdefault(r.reference, _FailureWatch(self.max_consecutive_failures)
                               ).add(r.estimate)

        commits = _OrderedCommits(self.store, todo, on_commit)

        def on_message(_key: tuple[int, int], msg: tuple) -> None:
            kind = msg[0]
            if kind == "start":
                _, i, stage, _first = msg
                if i not in started:  # a reference's first task to begin
                    started.add(i)
                    self.store.start_reference(i, stage)
                    self.progress.start_reference(i, stored[i])
            elif kind == "scan":
                commits.add(msg[1])
            elif kind == "cpu":
                self.cpu.merge(msg[1])

        def on_result(key: tuple[int, int], result: Any) -> None:
            i = key[0]
            if result == "done":
                left[i] -= 1
                commits.flush()
                if left[i] == 0:
                    self.store.finish_reference(i, "done")
                    self.progress.end_reference(i)
            elif isinstance(result, tuple) and result[0] == "error":
                commits.flush()  # every scan before the failure is kept
                where.update(reference=result[1], scan=result[2])
                raise BenchError(result[3])

        def retry(key: tuple[int, int], args: tuple) -> tuple | None:
            """A lost worker's task: only those of its scans that did not arrive."""
            _, i, first, n = args
            got = commits.received(i, first, n)
            if got >= n:
                left[i] -= 1
                commits.flush()
                if left[i] == 0:
                    self.store.finish_reference(i, "done")
                return None
            return (setup, i, first + got, n - got)

        def on_lost(key: tuple[int, int]) -> None:
            self.store.log(f"a worker process died at reference {key[0]}; it runs again",
                           "warning", reference=key[0])

        if self.engine is None:
            self.engine = LocalEngine(self.jobs)
        try:
            stopped = self.engine.run(
                _sim_reference, [((i, first), (setup, i, first, n)) for i, first, n in tasks],
                on_result, on_message, should_stop=lambda: self._stopping(flag), retry=retry,
                on_lost=on_lost)
        except BaseException:
            # What arrived in order before the failure or the second Ctrl-C is kept.
            with contextlib.suppress(Exception):
                commits.flush(check=False)
            raise
        commits.flush()
        return stopped
