"""Run a study into its store on an engine: create (or resume), deal the tasks, commit results.

The tasks are every (design point, block of poses) not yet in the store, in design order (the
first points finish first, so a report of an interrupted study has whole points). Results are
committed by this process only, one task per transaction (`StudyStore.add_task`). Ctrl-C
(SIGINT) or SIGTERM stops dealing and asks the tasks in flight to stop between poses; what was
committed stays, and ``--resume`` runs the rest.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from scenarios import station as stations
from scenarios.interrupt import StopFlag
from scenarios.progress import Bar
from scenarios.study.evaluate import NO_BOUND, STOPPED, bound_available, evaluate_task
from scenarios.study.spec import StudySpec, apply, design
from scenarios.study.store import StudyStore
from twin.core.errors import AimbenchError


def base_station(spec: StudySpec, folder: Path) -> stations.Station:
    """The study's station: a file relative to the study file's folder, or a shipped name."""
    path = folder / spec.station
    return stations.load(path if path.suffix and path.is_file() else spec.station)


def check(spec: StudySpec, folder: Path) -> tuple[stations.Station, list[dict[str, Any]]]:
    """The study's station and design points, every point checked (a `StudyError` naming the
    first bad one)."""
    base = base_station(spec, folder)
    points = design(spec)
    for values in points:
        apply(base, spec, values, spec.name)
    return base, points


def create(spec: StudySpec, folder: Path, out: Path, config: dict[str, Any]) -> StudyStore:
    """A new study store in `out`, every design point checked first (nothing is made for a
    study that cannot run)."""
    from scenarios.versions import versions

    base, points = check(spec, folder)
    tasks = math.ceil(spec.protocol.poses / spec.protocol.poses_per_task)
    return StudyStore.create(out, points, tasks, {
        "spec": spec.model_dump(mode="json"), "station": base.to_dict(), "config": config,
        "versions": versions()})


class Progress:
    """Progress over design points on stderr, through the project's one progress library
    (`scenarios.progress.Bar`, tqdm): a bar redrawn in place on a terminal, a line per finished
    design point elsewhere (with the tasks done, the rate and the time left, so a log says how
    long a study took). Notes (a lost worker, a missing bound) are said even without the bar."""

    def __init__(self, points: int, tasks_per_point: int, done: set[tuple[int, int]],
                 stream: TextIO | None = None, enabled: bool = True) -> None:
        self.points, self.per = points, tasks_per_point
        self.stream = stream if stream is not None else sys.stderr
        self.tasks: dict[int, int] = {}
        for i, _ in done:
            self.tasks[i] = self.tasks.get(i, 0) + 1
        self.started = time.monotonic()
        self.session_points = 0.0
        self.bar = Bar(points, "aimbench study", unit="design points", stream=self.stream,
                       enabled=enabled, every=None, initial=self.done_points)

    @property
    def done_points(self) -> int:
        return sum(1 for n in self.tasks.values() if n >= self.per)

    def task(self, point: int) -> None:
        self.tasks[point] = self.tasks.get(point, 0) + 1
        self.session_points += 1.0 / self.per
        finished = self.tasks[point] == self.per
        if self.bar.tty:
            # tqdm shows the rate and the time left itself; the status says the tasks
            self.bar.update(int(finished), status=self._tasks())
        elif finished:
            self.bar.update(1)
            self.bar.write(self.line())

    def _tasks(self) -> str:
        done = sum(min(n, self.per) for n in self.tasks.values())
        return f"{done}/{self.points * self.per} tasks"

    def line(self) -> str:
        """``aimbench study: 3/12 design points | 18/72 tasks | 0.64 points/min | ETA 12m30s``
        (the rate of this session: a resumed study's earlier points are not in it)."""
        elapsed = time.monotonic() - self.started
        rate = 60.0 * self.session_points / elapsed if elapsed > 0 else 0.0
        left = self.points - sum(min(n, self.per) for n in self.tasks.values()) / self.per
        text = (f"aimbench study: {self.done_points}/{self.points} design points | "
                f"{self._tasks()} | {rate:.2f} points/min")
        if rate > 0:
            eta = 60.0 * left / rate
            text += f" | ETA {int(eta // 60)}m{int(eta % 60):02d}s"
        return text

    def message(self, text: str) -> None:
        """A note: above the bar on a terminal, a line elsewhere, said even with no bar."""
        if self.bar.enabled:
            self.bar.write(text)
        else:
            self.stream.write(text + "\n")
            self.stream.flush()

    def finish(self) -> None:
        self.bar.close()


def execute(store: StudyStore, engine: Any, progress: bool = True,
            stream: TextIO | None = None) -> str:
    """Run the study's missing tasks on `engine`; the final status (completed, interrupted).
    A failure marks the study failed and raises."""
    stream = stream if stream is not None else sys.stderr
    spec = StudySpec.model_validate(store.get("spec"))
    station = store.get("station")
    points = store.points()
    per = math.ceil(spec.protocol.poses / spec.protocol.poses_per_task)
    ppt = spec.protocol.poses_per_task
    done = store.done_tasks()
    spec_dict = spec.model_dump(mode="json")
    tasks = [((i, b), (spec_dict, station, values, b * ppt,
                       min(ppt, spec.protocol.poses - b * ppt)))
             for i, values in enumerate(points) for b in range(per) if (i, b) not in done]
    bar = Progress(len(points), per, done, stream, progress)
    resumed = bool(done) or store.status != "created"
    store.set_status("running", f"{'resumed' if resumed else 'started'} on "
                                f"{engine.describe()}, {len(tasks)} tasks to run")
    if not bound_available():
        bar.message(f"aimbench study: note: {NO_BOUND}")
    kept = {"n": 0}

    def on_result(key: tuple[int, int], result: Any) -> None:
        if result == STOPPED:
            return
        if store.add_task(key[0], key[1], result, engine.name):
            kept["n"] += 1
            bar.task(key[0])

    def on_lost(key: tuple[int, int]) -> None:
        store.log(f"a worker died; task {key} (point {key[0]}, poses block {key[1]}) runs "
                  "again", "warning")
        bar.message(f"aimbench study: a worker died; its task {key} runs again")

    message = ("stopping after the tasks in flight (results so far are saved; --resume "
               "continues; Ctrl-C again to stop at once)")
    with StopFlag(lambda: bar.message(message)) as flag:
        try:
            stopped = engine.run(evaluate_task, tasks, on_result,
                                 should_stop=lambda: flag.stop, on_lost=on_lost)
        except KeyboardInterrupt:
            stopped = True
        except AimbenchError as exc:
            bar.finish()
            store.set_status("failed", str(exc))
            raise
        except Exception as exc:  # a bug in a task: say it, keep what was committed
            bar.finish()
            store.set_status("failed", f"{type(exc).__name__}: {exc}")
            raise AimbenchError(f"a task failed: {type(exc).__name__}: {exc} (the results so "
                                "far are kept; --resume retries the rest)") from exc
    bar.finish()
    if stopped and len(store.done_tasks()) < len(points) * per:
        store.set_status("interrupted", f"stopped by {flag.signal or 'request'}; "
                                        f"{len(store.done_tasks())} of {len(points) * per} tasks "
                                        "saved")
        return "interrupted"
    store.set_status("completed", f"{kept['n']} tasks in this session")
    return "completed"
