"""An atlas build as a small graph of tasks on Dask, every finished task kept on disk.

A build is a few dozen tasks (a plane of the grid, or the lines of a displacement axis between two
of its planes), each minutes long on a fine model: :func:`run_graph` submits every task whose
inputs are done, highest ``priority`` first, and keeps each result in a :class:`TaskStore` as it
arrives. A build that is stopped (Ctrl-C, ``kill -9``, a reboot) and started again with the same
settings loads the kept results and runs only the rest: at most the tasks in flight are lost. A
build started with other settings while an interrupted one waits is refused, naming the setting
(:func:`check_partials`), unless the user discards it.

The estimated time left (:class:`Eta`) is the predicted CPU time of the tasks left over the CPU
this run gets through per second of wall time: each task's cost is its grid points times the CPU
per point of its kind (measured on the finished tasks of that kind; before the first of a kind
finishes, the measured rate scaled by :data:`PRIOR_COST`), so a loaded machine or a larger cluster
shows in the estimate at once.
"""

from __future__ import annotations

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
# CPU per grid point of each kind of task (its last word) relative to a plane of force-controlled
# solves, before one of that kind has finished: on the quadratic BIP model (28 329 nodes) a line
# point (one mixed-control solve from its neighbour on the line) took 3.6 CPU-s where a face plane's
# point took 7.1-9.4
PRIOR_COST = {"plane": 1.0, "lines": 0.5}


_PLAIN = (int, float, complex, str, bytes, bool, type(None), tuple, list, dict, set, frozenset)


@dataclass(frozen=True)
class Task:
    """One task of a build: ``fn(*args(results))`` on a worker, where ``results`` maps the names in
    ``deps`` to their values; ``points`` the grid points it solves and ``kind`` its cost class (the
    ETA), ``priority`` Dask's (higher first)."""

    name: str
    fn: Callable[..., Any]
    args: Callable[[dict[str, Any]], tuple]
    deps: tuple[str, ...] = ()
    points: int = 1
    kind: str = "plane"
    priority: int = 0


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


@dataclass
class Eta:
    """The time left of a build: predicted CPU of the tasks left over this run's CPU per wall second.

    >>> e = Eta({"a": (10, "piece 0 plane"), "b": (10, "piece 0 plane"), "c": (20, "piece 0 lines")},
    ...         prior={"plane": 1.0, "lines": 2.0})
    >>> e.start(0.0)
    >>> e.finished("a", cpu_s=100.0, now=50.0)  # 10 points at 10 CPU-s each, 2 CPU-s per wall second
    >>> round(e.seconds_left(50.0))  # b: 100 CPU-s, c: 20 points at twice the rate: 400 CPU-s
    250
    """

    tasks: dict[str, tuple[int, str]]  # name -> (points, kind)
    prior: dict[str, float] = field(default_factory=lambda: dict(PRIOR_COST))
    done: dict[str, float] = field(default_factory=dict)  # name -> CPU-s
    run_cpu_s: float = 0.0
    t0: float | None = None

    def start(self, now: float) -> None:
        self.t0 = now

    def kept(self, name: str, cpu_s: float) -> None:
        """A task loaded from an interrupted run: its cost counts for the rates, not for this run's speed."""
        self.done[name] = cpu_s

    def finished(self, name: str, cpu_s: float, now: float) -> None:
        self.done[name] = cpu_s
        self.run_cpu_s += cpu_s

    def _rate(self, kind: str) -> float | None:
        pts = sum(self.tasks[n][0] for n in self.done if self.tasks[n][1] == kind)
        if pts:
            return sum(c for n, c in self.done.items() if self.tasks[n][1] == kind) / pts
        weighted = sum(self.tasks[n][0] * self._prior(self.tasks[n][1]) for n in self.done)
        if not weighted:
            return None
        return sum(self.done.values()) / weighted * self._prior(kind)

    def _prior(self, kind: str) -> float:
        return self.prior.get(kind, self.prior.get(kind.split()[-1] if kind else kind, 1.0))

    def cpu_left(self) -> float | None:
        left = 0.0
        for n, (pts, kind) in self.tasks.items():
            if n not in self.done:
                r = self._rate(kind)
                if r is None:
                    return None
                left += pts * r
        return left

    def seconds_left(self, now: float) -> float | None:
        cpu = self.cpu_left()
        if cpu is None or self.t0 is None or self.run_cpu_s <= 0 or now <= self.t0:
            return None
        return cpu / (self.run_cpu_s / (now - self.t0))

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
    eta = Eta({t.name: (t.points, t.kind) for t in tasks})
    for t in tasks:
        store = store_of(t.name)
        rec = store.load(t.name) if store is not None else None
        if rec is not None:
            values[t.name], cpu[t.name], wall[t.name] = rec
            eta.kept(t.name, cpu[t.name])
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
        eta.finished(name, c, now)
        report(log, label, len(values), total, eta.text(now))
        submit_ready()
    return GraphRun(values, cpu, wall, tuple(kept))
