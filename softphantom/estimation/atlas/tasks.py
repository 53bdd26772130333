"""An atlas build as a small graph of tasks on Dask, every finished task kept on disk.

A build is a few dozen tasks (a plane of the grid, or the lines of a displacement axis between two
of its planes), each minutes long on a fine model: :func:`run_graph` submits every task whose
inputs are done, highest ``priority`` first, and keeps each result in a :class:`TaskStore` as it
arrives. A build that is stopped (Ctrl-C, ``kill -9``, a reboot) and started again with the same
settings loads the kept results and runs only the rest: at most the tasks in flight are lost. A
build started with other settings while an interrupted one waits is refused, naming the setting
(:func:`check_partials`), unless the user discards it.

The estimated time left (:class:`Eta`) is the wall time of the tasks left scheduled on this run's
workers (:func:`schedule_s`: each free worker takes the ready task of highest priority, as Dask
does): each task's time is its predicted cost (``Task.cost``, the cost model of
:func:`~softphantom.estimation.atlas.build.estimated_build`) times the wall seconds per unit of
predicted cost measured on the finished tasks of its kind (before the first of a kind finishes,
on all finished tasks). So a loaded machine or a larger cluster shows in the estimate at once,
and so does the graph's tail: the last tasks of a fine graph run on fewer workers than there are.
The priorities are each task's bottom level (:func:`bottom_levels`: the longest chain of
predicted costs from it to the end), so the long chains start first.
"""

from __future__ import annotations

import heapq
import json
import logging
import os
import pickle
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from softphantom.errors import UserError
from softphantom.progress import report

log = logging.getLogger(__name__)

PARTIAL = "partial"  # MODEL/atlas/partial/<key>/: an unfinished build's kept tasks
MAGIC = b"softphantom-atlas-task-1\n"


_PLAIN = (int, float, complex, str, bytes, bool, type(None), tuple, list, dict, set, frozenset)


@dataclass(frozen=True)
class Task:
    """One task of a build: ``fn(*args(results))`` on a worker, where ``results`` maps the names in
    ``deps`` to their values; ``points`` the grid points it solves, ``cost`` its predicted CPU-s and
    ``kind`` its cost class (the ETA), ``priority`` Dask's (higher first)."""

    name: str
    fn: Callable[..., Any]
    args: Callable[[dict[str, Any]], tuple]
    deps: tuple[str, ...] = ()
    points: int = 1
    kind: str = "plane"
    priority: int = 0
    cost: float = 0.0  # predicted CPU-s (0: unknown, ``points`` stands in)

    @property
    def weight(self) -> float:
        """The predicted cost, in CPU-s where the cost model gave one (``cost``), else the points."""
        return float(self.cost) if self.cost > 0 else float(self.points)


class TaskStore:
    """The finished tasks of one build (one atlas key) in ``directory``, with the settings they
    were made with (``settings.json``). Each result is written to a temporary name and renamed, so a
    kill never leaves half a file; a file that cannot be read is run again (with a warning)."""

    def __init__(self, directory: Path, settings: dict) -> None:
        self.dir = Path(directory)
        self.settings = settings
        self.dir.mkdir(parents=True, exist_ok=True)
        meta = self.dir / "settings.json"
        if not meta.is_file():
            tmp = meta.with_name("settings.json.tmp")
            tmp.write_text(json.dumps(settings, sort_keys=True, indent=1))
            tmp.replace(meta)

    def _path(self, name: str) -> Path:
        return self.dir / f"{name}.task"

    def names(self) -> list[str]:
        return sorted(p.stem for p in self.dir.glob("*.task"))

    def load(self, name: str) -> tuple[Any, float, float] | None:
        """(value, CPU-s, wall-s) of a kept task, or None."""
        path = self._path(name)
        if not path.is_file():
            return None
        try:
            data = path.read_bytes()
            if not data.startswith(MAGIC):
                raise ValueError("not a task file")
            rec = pickle.loads(data[len(MAGIC):])
            if rec["name"] != name:
                raise ValueError(f"holds task {rec['name']!r}")
            return rec["value"], float(rec["cpu_s"]), float(rec["wall_s"])
        except Exception as exc:  # noqa: BLE001 - a damaged file is run again, not fatal
            log.warning(f"atlas: {path}: unreadable ({type(exc).__name__}: {exc}); running that task again")
            return None

    def save(self, name: str, value: Any, cpu_s: float, wall_s: float) -> None:
        path = self._path(name)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(MAGIC)
            pickle.dump({"name": name, "value": value, "cpu_s": cpu_s, "wall_s": wall_s}, f, protocol=5)
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(path)

    def discard(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def partial_dir(cache_dir, key: str) -> Path:
    """Where the kept tasks of the build of atlas ``key`` live next to a model directory."""
    return Path(cache_dir) / "atlas" / PARTIAL / key[:32]


def discard_tasks(cache_dir, key: str) -> None:
    """Delete the kept tasks of the build of atlas ``key`` (and the partial directory once empty)."""
    d = partial_dir(cache_dir, key)
    shutil.rmtree(d, ignore_errors=True)
    try:
        d.parent.rmdir()
    except OSError:
        pass  # other builds' tasks are still there


def _first_difference(a: dict, b: dict, prefix: str = "") -> str | None:
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            d = _first_difference(va, vb, f"{prefix}{k}.")
            if d:
                return d
        elif va != vb:
            return f"{prefix}{k} {json.dumps(va)} there, {json.dumps(vb)} here"
    return None


def check_partials(cache_dir, build: dict, discard: bool = False) -> None:
    """Refuse to start a build of settings ``build`` next to an interrupted build of other settings
    in ``cache_dir`` (one line naming the first differing setting), or with ``discard`` delete the
    interrupted one's kept tasks. Kept tasks of the same settings are left to be resumed.

    ``build`` is what identifies the whole command (all pieces of a split atlas), so resuming
    finds the same settings in every piece's store."""
    root = Path(cache_dir) / "atlas" / PARTIAL
    if not root.is_dir():
        return
    build = json.loads(json.dumps(build))  # as settings.json holds it (tuples as lists)
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        try:
            theirs = json.loads((d / "settings.json").read_text())["build"]
        except Exception:  # noqa: BLE001 - no readable settings: nothing to resume from
            shutil.rmtree(d, ignore_errors=True)
            continue
        if theirs == build:
            continue
        n = len(list(d.glob("*.task")))
        if discard:
            log.warning(f"atlas: discarding an interrupted build with other settings ({n} finished tasks): {d}")
            shutil.rmtree(d, ignore_errors=True)
            continue
        raise UserError(f"{d}: an interrupted atlas build with other settings ({_first_difference(theirs, build)}; "
                        f"{n} finished tasks): run it again with its settings to resume it, or add "
                        f"--discard-partial to drop it")


def _clock(seconds: float) -> str:
    s = max(0, int(round(seconds)))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def bottom_levels(tasks: list[Task], seconds: dict[str, float]) -> dict[str, float]:
    """Each task's bottom level: the longest chain of ``seconds`` from it (included) to the end of
    the graph — the priority that starts the long chains first.

    >>> t = [Task("a", None, None), Task("b", None, None, deps=("a",)), Task("c", None, None)]
    >>> bottom_levels(t, {"a": 1.0, "b": 5.0, "c": 2.0})
    {'a': 6.0, 'b': 5.0, 'c': 2.0}
    """
    after: dict[str, list[str]] = {t.name: [] for t in tasks}
    for t in tasks:
        for d in t.deps:
            after[d].append(t.name)
    memo: dict[str, float] = {}

    def level(n: str) -> float:
        if n not in memo:
            memo[n] = seconds.get(n, 0.0) + max((level(c) for c in after[n]), default=0.0)
        return memo[n]

    return {t.name: level(t.name) for t in tasks}


def schedule_s(tasks: list[Task], seconds: dict[str, float], workers: int, done=(),
               running: dict[str, float] | None = None, queued: dict[str, float] | None = None) -> float:
    """The wall time to run the tasks not in ``done`` on ``workers`` workers, task n taking
    ``seconds[n]``: whenever a worker is free it takes the ready task of highest priority (as
    :func:`run_graph` submits them and Dask runs them); ``running`` (name → seconds still to go)
    occupy a worker each from the start; among tasks of equal priority the one ready first goes
    first (``queued``: name → when it was submitted, ≤ 0, for those already waiting).

    >>> t = [Task("a", None, None, priority=2), Task("b", None, None, priority=1),
    ...      Task("c", None, None, deps=("a",))]
    >>> schedule_s(t, {"a": 2.0, "b": 3.0, "c": 2.0}, 2), schedule_s(t, {"a": 2.0, "b": 3.0, "c": 2.0}, 1)
    (4.0, 7.0)
    >>> schedule_s(t, {"a": 2.0, "b": 3.0, "c": 2.0}, 2, done={"a"}, running={"b": 1.0})
    2.0
    """
    running = dict(running or {})
    finished = set(done)
    index = {t.name: i for i, t in enumerate(tasks)}
    since = dict(queued or {})  # when each ready task became ready
    left = {t.name: t for t in tasks if t.name not in finished and t.name not in running}
    events = [(float(s), n) for n, s in running.items()]
    heapq.heapify(events)
    free = max(1, int(workers)) - len(events)
    now = 0.0
    while True:
        ready = [n for n, t in left.items() if all(d in finished for d in t.deps)]
        for n in ready:
            since.setdefault(n, now)
        ready.sort(key=lambda n: (-left[n].priority, since[n], index[n]))
        for n in ready[:max(free, 0)]:
            heapq.heappush(events, (now + float(seconds.get(n, 0.0)), n))
            del left[n]
            free -= 1
        if not events:
            return now
        now, n = heapq.heappop(events)
        finished.add(n)
        free += 1


@dataclass
class Eta:
    """The time left of a build: the tasks left scheduled on ``workers`` (:func:`schedule_s`), each
    task's wall time its predicted cost times the wall seconds per unit of cost measured on the
    finished tasks of its kind (before one of its kind finished: of its kind of point in another
    piece, then of all kinds).

    >>> t = [Task("a", None, None, points=10, kind="plane"), Task("b", None, None, points=10, kind="plane"),
    ...      Task("c", None, None, points=20, kind="lines", deps=("a", "b"))]
    >>> e = Eta(t, workers=1)
    >>> e.start(0.0)
    >>> e.started("a", 0.0)
    >>> e.finished("a", cpu_s=90.0, wall_s=100.0, now=100.0)  # 10 wall-s a point
    >>> e.started("b", 100.0)
    >>> round(e.seconds_left(100.0))  # b: 100 s, then c: 20 points at the same rate
    300
    >>> round(e.seconds_left(150.0))  # b half done
    250
    """

    task_list: list[Task]
    workers: int = 1
    done: dict[str, float] = field(default_factory=dict)  # name -> wall-s
    begun: dict[str, float] = field(default_factory=dict)  # name -> when it started running (a worker's)
    queued: dict[str, float] = field(default_factory=dict)  # name -> when it was submitted (waiting for a worker)
    run_cpu_s: float = 0.0
    t0: float | None = None

    def __post_init__(self) -> None:
        self.by = {t.name: t for t in self.task_list}

    def start(self, now: float) -> None:
        self.t0 = now

    def kept(self, name: str, wall_s: float) -> None:
        """A task loaded from an interrupted run: its wall time counts for the rates."""
        self.done[name] = wall_s

    def started(self, name: str, now: float) -> None:
        """Task ``name`` submitted at ``now``: it runs from then if a worker is free, else from when
        one frees (the queued task of highest priority first, as Dask runs them)."""
        self.queued[name] = now
        self._fill(now)

    def finished(self, name: str, cpu_s: float, wall_s: float, now: float) -> None:
        self.done[name] = wall_s
        self.begun.pop(name, None)
        self.queued.pop(name, None)
        self.run_cpu_s += cpu_s
        self._fill(now)

    def _fill(self, now: float) -> None:
        for n in sorted(self.queued, key=lambda n: (-self.by[n].priority, self.queued[n])):
            if len(self.begun) >= max(1, self.workers):
                break
            self.begun[n] = now
            del self.queued[n]

    def _rate(self, kind: str) -> float | None:
        """Wall seconds per unit of predicted cost of the tasks of ``kind``; before one ended, of the
        tasks of its last word (the same kind of point in another piece), then of all."""
        mine = [n for n in self.done if self.by[n].kind == kind]
        word = [n for n in self.done if self.by[n].kind.split()[-1:] == kind.split()[-1:]]
        for names in (mine, word, list(self.done)):
            w = sum(self.by[n].weight for n in names)
            if w > 0:
                return sum(self.done[n] for n in names) / w
        return None

    def seconds_left(self, now: float) -> float | None:
        if self.t0 is None or not self.done:
            return None
        seconds = {}
        for n, t in self.by.items():
            if n not in self.done:
                r = self._rate(t.kind)
                if r is None:
                    return None
                seconds[n] = t.weight * r
        # a running task's time still to go; one past its prediction: a twentieth of it more
        running = {n: seconds[n] - (now - t) if seconds[n] > now - t else 0.05 * seconds[n]
                   for n, t in self.begun.items()}
        return schedule_s(self.task_list, seconds, self.workers, set(self.done), running,
                          {n: t - now for n, t in self.queued.items()})

    def text(self, now: float) -> str:
        s = self.seconds_left(now)
        return "" if s is None else f"ETA {_clock(s)}"


def _timed(fn, *args):
    """Run a task on a worker: (its value, CPU-s, wall-s)."""
    t0, c0 = time.perf_counter(), time.process_time()
    value = fn(*args)
    return value, time.process_time() - c0, time.perf_counter() - t0


def critical_path_s(tasks: list[Task], wall_s: dict[str, float]) -> float:
    """The longest chain of task wall times through the graph: the build's wall time on a cluster
    with a worker for every task that can run.

    >>> t = [Task("a", None, None), Task("b", None, None), Task("c", None, None, deps=("a", "b"))]
    >>> critical_path_s(t, {"a": 3.0, "b": 5.0, "c": 2.0})
    7.0
    """
    by = {t.name: t for t in tasks}
    memo: dict[str, float] = {}

    def end(n: str) -> float:
        if n not in memo:
            memo[n] = wall_s.get(n, 0.0) + max((end(d) for d in by[n].deps), default=0.0)
        return memo[n]

    return max((end(t.name) for t in tasks), default=0.0)


@dataclass
class GraphRun:
    """What :func:`run_graph` gives back: every task's value, CPU-s and wall-s (kept ones included),
    and which were loaded from an interrupted run."""

    values: dict[str, Any]
    cpu_s: dict[str, float]
    wall_s: dict[str, float]
    kept: tuple[str, ...]


def run_graph(client, tasks: list[Task], store_of: Callable[[str], TaskStore | None], label: str,
              on_error: Callable[[Task, str], Exception]) -> GraphRun:
    """Run ``tasks`` on ``client``: load the ones kept in their store (``store_of(name)``), submit each
    other as soon as its deps are done, keep each result in its store as it arrives, and report the
    progress with the ETA (:func:`softphantom.progress.report`, task ``label``). A task that raises
    stops the build: ``on_error(task, message)`` is raised (the kept tasks stay)."""
    from distributed import as_completed

    by = {t.name: t for t in tasks}
    values: dict[str, Any] = {}
    cpu: dict[str, float] = {}
    wall: dict[str, float] = {}
    kept = []
    eta = Eta(tasks, workers=max(1, sum(client.nthreads().values())))
    for t in tasks:
        store = store_of(t.name)
        rec = store.load(t.name) if store is not None else None
        if rec is not None:
            values[t.name], cpu[t.name], wall[t.name] = rec
            eta.kept(t.name, wall[t.name])
            kept.append(t.name)
    if kept:
        log.info(f"{label}: resuming, {len(kept)} of {len(tasks)} tasks kept from an interrupted build")
    total = len(tasks)
    eta.start(time.perf_counter())
    report(log, label, len(values), total)
    pending: dict[Any, str] = {}
    ac = as_completed()
    shipped: dict[int, tuple[Any, Any]] = {}

    def ship(a: Any) -> Any:
        # the model every task shares (tens of MB pickled) goes to the workers once, not in each task
        if isinstance(a, (*_PLAIN, np.ndarray, np.generic)):
            return a
        if id(a) not in shipped:
            shipped[id(a)] = (a, client.scatter(a, hash=False))
        return shipped[id(a)][1]

    def submit_ready() -> None:
        waiting = {n for n in pending.values()}
        for t in sorted(tasks, key=lambda t: -t.priority):
            if t.name in values or t.name in waiting or not all(d in values for d in t.deps):
                continue
            fut = client.submit(_timed, t.fn, *map(ship, t.args(values)), pure=False, priority=t.priority)
            pending[fut] = t.name
            eta.started(t.name, time.perf_counter())
            ac.add(fut)

    submit_ready()
    for fut in ac:
        name = pending.pop(fut)
        try:
            value, c, w = fut.result()
        except Exception as exc:  # noqa: BLE001 - one line, then the build stops
            for f in pending:
                f.cancel()
            raise on_error(by[name], f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
        store = store_of(name)
        if store is not None:
            store.save(name, value, c, w)
        values[name], cpu[name], wall[name] = value, c, w
        now = time.perf_counter()
        eta.finished(name, c, w, now)
        report(log, label, len(values), total, eta.text(now))
        submit_ready()
    return GraphRun(values, cpu, wall, tuple(kept))
