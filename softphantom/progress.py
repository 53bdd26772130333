"""Progress that shows wherever the output goes.

rich draws its progress bars, spinners and live lines only on a terminal: with stdout piped to a
file (a CI log, ``make demo > log``) a long step printed nothing until it ended. The helpers here
give rich's display on a terminal and plain lines elsewhere:

- :func:`progress_bar`: a ``rich.progress.Progress`` on a terminal, else a :class:`LineProgress`
  (same ``add_task`` / ``update`` / ``advance`` calls) that prints one line per task each time it
  passes another ``step_pct`` (10 %) or, while it moves, every ``every_s`` (10 s), and when it ends;
- :func:`status`: ``console.status`` (a spinner) on a terminal, else a line when the step starts,
  one every ``every_s`` while it runs, and one when it ends, with its time;
- :func:`live_line`: ``rich.live.Live`` for a one-line live display, else the line printed at
  most every ``every_s``.

Library code reports the progress of long work through :mod:`logging`: :func:`report` logs a
record carrying a :class:`Step` (task, done, total, what). It never configures logging; the CLI
installs :class:`ProgressHandler` (the steps as :func:`progress_bar` tasks) and
:func:`message_handler` (the other records: rich's ``RichHandler`` on a terminal, plain lines
elsewhere). :func:`forward_progress` hands a Dask task's steps to the client.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

EVERY_S = 10.0
STEP_PCT = 10.0


def _console(console):
    if console is not None:
        return console
    from rich import get_console

    return get_console()


def _draws(console) -> bool:
    """Does rich draw live displays on ``console`` (a terminal, not TERM=dumb)?"""
    return console.is_terminal and not console.is_dumb_terminal


def _clock_text(seconds: float) -> str:
    s = int(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


@dataclass
class _Task:
    description: str
    total: float | None
    completed: float
    fields: dict
    started: float
    last_line: float = -1.0
    last_step: int = -1
    last_text: str = ""
    done: bool = False


class LineProgress:
    """The calls of ``rich.progress.Progress`` that this project makes, printed as plain lines (one
    per task per ``step_pct`` of its total, at most one per ``every_s`` in between, and one at its
    end); for output that is not a terminal. ``clock`` for tests."""

    def __init__(self, console=None, *, every_s: float = EVERY_S, step_pct: float = STEP_PCT,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.console = _console(console)
        self.every_s, self.step_pct, self.clock = every_s, step_pct, clock
        self._tasks: dict[int, _Task] = {}
        self._lock = threading.Lock()

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> None:
        pass

    def stop(self) -> None:
        """Say where every unfinished task stopped (unless that is what its last line said)."""
        for tid in list(self._tasks):
            self._emit(tid, final=True)

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields: Any) -> int:
        fields.pop("start", None)
        fields.pop("visible", None)
        with self._lock:
            tid = len(self._tasks)
            self._tasks[tid] = _Task(description, total, completed, fields, self.clock())
        self._emit(tid)
        return tid

    def advance(self, task_id: int, advance: float = 1) -> None:
        self.update(task_id, advance=advance)

    def update(self, task_id: int, *, total: float | None = None, completed: float | None = None,
               advance: float | None = None, description: str | None = None, **fields: Any) -> None:
        fields.pop("refresh", None)
        fields.pop("visible", None)
        t = self._tasks[task_id]
        with self._lock:
            if total is not None:
                t.total = total
            if completed is not None:
                t.completed = completed
            if advance is not None:
                t.completed += advance
            if description is not None:
                t.description = description
            t.fields.update(fields)
        self._emit(task_id)

    @staticmethod
    def _state(t: _Task) -> str:
        what = " ".join(str(v) for v in t.fields.values() if v not in (None, ""))
        head = (f"{t.description}: {t.completed:g}/{t.total:g} ({100.0 * t.completed / t.total:.0f} %)"
                if t.total else f"{t.description}:")
        return f"{head} {what}" if what else head

    def _emit(self, task_id: int, final: bool = False) -> None:
        t = self._tasks[task_id]
        now = self.clock()
        with self._lock:
            if t.done:
                return
            finished = bool(t.total) and t.completed >= t.total
            step = int(100.0 * t.completed / t.total // self.step_pct) if t.total else -1
            state = self._state(t)
            if final:
                due = state != t.last_text
            else:
                due = (t.last_line < 0 or finished or step > t.last_step
                       or (state != t.last_text and now - t.last_line >= self.every_s))
            if not due:
                return
            t.last_line, t.last_step, t.last_text, t.done = now, step, state, finished or final
        self.console.print(f"{state} {_clock_text(now - t.started)}", highlight=False, markup=False, soft_wrap=True)


def progress_bar(*columns: Any, console=None, transient: bool = False, every_s: float = EVERY_S,
                 **kwargs: Any):
    """A ``rich.progress.Progress(*columns, console=…, transient=…, **kwargs)`` on a terminal; a
    :class:`LineProgress` otherwise."""
    console = _console(console)
    if _draws(console):
        from rich.progress import Progress

        return Progress(*columns, console=console, transient=transient, **kwargs)
    return LineProgress(console, every_s=every_s)


@contextlib.contextmanager
def status(text: str, console=None, every_s: float = EVERY_S) -> Iterator[None]:
    """A spinner with ``text`` on a terminal; otherwise ``text …`` when the step starts, ``text …
    0:00:10`` every ``every_s`` while it runs and ``text: done in 12.3 s`` (or ``stopped after``)
    when it ends."""
    console = _console(console)
    if _draws(console):
        with console.status(f"{text} …"):
            yield
        return
    t0 = time.monotonic()
    console.print(f"{text} …", highlight=False, markup=False, soft_wrap=True)
    stop = threading.Event()

    def tick() -> None:
        while not stop.wait(every_s):
            console.print(f"{text} … {_clock_text(time.monotonic() - t0)}", highlight=False, markup=False,
                          soft_wrap=True)

    ticker = threading.Thread(target=tick, name="status-ticker", daemon=True)
    ticker.start()
    ok = False
    try:
        yield
        ok = True
    finally:
        stop.set()
        ticker.join()
        how = "done in" if ok else "stopped after"
        console.print(f"{text}: {how} {time.monotonic() - t0:.1f} s", highlight=False, markup=False, soft_wrap=True)


class _LineLive:
    """``rich.live.Live``'s ``update(text)`` as a line printed at most every ``every_s`` (the last
    one again when it closes, if it was not printed)."""

    def __init__(self, console, every_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.console, self.every_s, self.clock = console, every_s, clock
        self._last = -float("inf")
        self._pending: str | None = None

    def __enter__(self) -> _LineLive:
        return self

    def __exit__(self, *exc) -> None:
        if self._pending is not None:
            self._print(self._pending)

    def _print(self, text: str) -> None:
        self.console.print(text, highlight=False, markup=False, soft_wrap=True)
        self._pending = None

    def update(self, renderable: Any, **_: Any) -> None:
        now = self.clock()
        if now - self._last >= self.every_s:
            self._last = now
            self._print(str(renderable))
        else:
            self._pending = str(renderable)


def live_line(console=None, every_s: float = EVERY_S, **kwargs: Any):
    """``rich.live.Live(console=…, **kwargs)`` on a terminal; elsewhere an object whose
    ``update(text)`` prints the text at most every ``every_s``."""
    console = _console(console)
    if _draws(console):
        from rich.live import Live

        return Live(console=console, **kwargs)
    return _LineLive(console, every_s)


#: The attribute of a progress record that holds its :class:`Step` (``extra={"progress": step}``).
PROGRESS = "progress"


@dataclass(frozen=True)
class Step:
    """One report of a long task: ``done`` of ``total`` (None: not known yet) and what it does now.

    >>> str(Step("atlas: 12 forward solves", 3, 12)), str(Step("push: truth", 0, None, "queued"))
    ('atlas: 12 forward solves: 3/12', 'push: truth: 0 queued')
    """

    task: str
    done: float
    total: float | None = None
    what: str = ""

    def __str__(self) -> str:
        head = f"{self.task}: {self.done:g}/{self.total:g}" if self.total else f"{self.task}: {self.done:g}"
        return f"{head} {self.what}" if self.what else head


def report(logger: logging.Logger, task: str, done: float, total: float | None = None, what: str = "",
           level: int = logging.INFO) -> None:
    """Log the progress of ``task`` on ``logger``: a record whose message is the :class:`Step` as text
    and whose ``progress`` attribute is the step (drawn as a bar by :class:`ProgressHandler`); inside
    :func:`forward_progress` the step goes to its sink too. A ``total`` below ``done`` is raised to it."""
    step = Step(task, done, None if total is None else max(total, done), what)
    sink = getattr(_forward, "sink", None)
    if sink is not None:
        sink(step)
    if logger.isEnabledFor(level):
        logger.log(level, "%s", step, extra={PROGRESS: step})


def is_progress(record: logging.LogRecord) -> bool:
    """Is ``record`` a progress report (:func:`report`)?"""
    return isinstance(getattr(record, PROGRESS, None), Step)


def _not_progress(record: logging.LogRecord) -> bool:
    return not is_progress(record)


class ProgressHandler(logging.Handler):
    """The progress records (:func:`report`) as tasks of one :func:`progress_bar` on ``console``:
    rich bars on a terminal, plain lines elsewhere; other records pass it by. A task whose ``done``
    goes back (run again under the same name) gets a new bar. The display stops when every task it
    shows has reached its total (the next record starts a new one), or on :meth:`close`."""

    def __init__(self, console=None, level: int = logging.NOTSET, every_s: float = EVERY_S) -> None:
        super().__init__(level)
        self.addFilter(is_progress)
        self.console, self.every_s = console, every_s
        self._bar: Any = None
        self._tasks: dict[str, tuple[int, Step]] = {}  # task -> (its bar's id, its last step)

    def emit(self, record: logging.LogRecord) -> None:
        step: Step = getattr(record, PROGRESS)
        if self._bar is None:
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

            self._bar = progress_bar(TextColumn("{task.description}", markup=False), BarColumn(),
                                     MofNCompleteColumn(), TimeElapsedColumn(),
                                     TextColumn("{task.fields[what]}", markup=False),
                                     console=self.console, every_s=self.every_s)
            self._bar.start()
        seen = self._tasks.get(step.task)
        if seen is None or step.done < seen[1].done:
            tid = self._bar.add_task(step.task, total=step.total, completed=step.done, what=step.what)
        else:
            tid = seen[0]
            self._bar.update(tid, completed=step.done, total=step.total, what=step.what)
        self._tasks[step.task] = (tid, step)
        if all(s.total is not None and s.done >= s.total for _, s in self._tasks.values()):
            self._stop()

    def _stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()
        self._bar = None
        self._tasks.clear()

    def close(self) -> None:
        with self.lock:
            self._stop()
        super().close()


class _PlainFormatter(logging.Formatter):
    """The message as it is at INFO; ``warning: …`` (the level's name) at other levels."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return text if record.levelno == logging.INFO else f"{record.levelname.lower()}: {text}"


class _ConsoleHandler(logging.Handler):
    """Each record as one plain line on a rich console (no markup, no highlighting)."""

    def __init__(self, console) -> None:
        super().__init__()
        self.console = console
        self.setFormatter(_PlainFormatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.console.print(self.format(record), highlight=False, markup=False, soft_wrap=True)
        except Exception:  # noqa: BLE001 - logging's own policy: report, never raise
            self.handleError(record)


def message_handler(console=None) -> logging.Handler:
    """The handler of the log messages (not the progress records) on ``console``: rich's
    ``RichHandler`` (level, message; no time or path) on a terminal, else plain lines
    (:class:`_PlainFormatter`)."""
    console = _console(console)
    if _draws(console):
        from rich.highlighter import NullHighlighter
        from rich.logging import RichHandler

        handler: logging.Handler = RichHandler(console=console, show_time=False, show_path=False,
                                               highlighter=NullHighlighter(), keywords=[])
    else:
        handler = _ConsoleHandler(console)
    handler.addFilter(_not_progress)
    return handler


_forward = threading.local()  # .sink: where forward_progress sends this thread's steps


@contextlib.contextmanager
def forward_progress(sink: Callable[[Step], None]) -> Iterator[None]:
    """Hand every :class:`Step` that this thread reports (:func:`report`) to ``sink`` too while the
    block runs, whatever the loggers' levels: from a Dask task to its client (``sink`` puts the step
    on a Dask event topic, the client reports it again; a worker process has no logging set up)."""
    outer = getattr(_forward, "sink", None)
    _forward.sink = sink
    try:
        yield
    finally:
        _forward.sink = outer
