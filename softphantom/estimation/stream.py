"""Run an estimator over a sensor source and write the estimate CSV (docs/architecture.md).

Live sources (the serial board): a reader thread drains the source into a bounded queue, so
acquisition never waits for the estimator. Every sample is estimated, in order, even when the
reader hands several at once (a loaded machine delivers frames in bursts); only a sample older
than ``MAX_LAG_S`` behind the newest is dropped, and counted (``Estimate.skipped``: the estimator
fell behind). Offline sources (a replay, a simulation) are estimated sample by sample.

Outages are part of the data: every link event of the source (silent, disconnected, reconnected,
restart, resumed, retared: :class:`~softphantom.sensing.sources.SourceEvent`) becomes a marker row
at its time (numbers empty, ``status`` = ``event:<kind>: <detail>``), in the CSV and in whatever
else consumes the estimates (:func:`marker_estimate`).
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from softphantom.records.estimate import Estimate, estimate_row, is_marker, marker_estimate
from softphantom.records.channels import ChannelLayout
from softphantom.records.names import EVENT_PREFIX, estimate_columns
from softphantom.records.session import OverSessionWriter, SessionWriter

__all__ = ["EVENT_PREFIX", "EstimateWriter", "EventMarkers", "StepStats", "estimate_columns", "estimate_row",
           "estimate_stream", "is_marker", "iter_samples", "marker_estimate", "write_estimates"]

MAX_LAG_S = 0.25
"""A live sample this far behind the newest one is dropped (and counted): the estimator is behind."""


class StepStats:
    """Step-time percentiles in constant memory: a histogram of 1 % wide bins from 1 µs to 100 s
    (the per-estimate list it replaces grew by 8 bytes per estimate: 2.2 MB an hour at 77 Hz).

    >>> s = StepStats()
    >>> for k in range(1, 101):
    ...     s.add(k * 1e-3)
    >>> s.n, round(s.percentile(50) * 1e3, 1), round(s.max * 1e3, 1)   # p50 of 1..100 ms: ≤ 1 % high
    (100, 50.4, 100.0)
    """

    LO, HI, PER_DECADE = 1e-6, 100.0, 232   # 10^(1/232) ≈ 1.0100: bins 1 % wide

    def __init__(self) -> None:
        self._n_bins = int(math.log10(self.HI / self.LO) * self.PER_DECADE) + 2
        self._h = np.zeros(self._n_bins, np.int64)
        self.n = 0
        self.max = math.nan

    def _bin(self, x: float) -> int:
        if not x > self.LO:
            return 0
        return min(self._n_bins - 1, 1 + int(math.log10(x / self.LO) * self.PER_DECADE))

    def add(self, x: float) -> None:
        self._h[self._bin(x)] += 1
        self.n += 1
        self.max = x if not self.max >= x else self.max

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (upper edge of its bin, so ≤ 1 % high; exact for the max)."""
        if self.n == 0:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self._h), math.ceil(q / 100.0 * self.n)))
        return min(self.LO * 10 ** (k / self.PER_DECADE), self.max)


class EstimateWriter(OverSessionWriter):
    """Write estimates to the estimate file (a session file, :mod:`softphantom.records.session`):
    the metadata line (with the phantom's ``layout`` under ``channels``), the header (its volume
    and pressure columns), one row per estimate, each handed to the OS as it is written."""

    def __init__(self, path, target_names: Iterable[str], metadata: dict | None, layout: ChannelLayout) -> None:
        self.target_names = list(target_names)
        self.layout = layout
        self._w = SessionWriter(path, estimate_columns(self.target_names, layout),
                                {**(metadata or {}), **layout.to_meta()})
        self.path = self._w.path

    @property
    def rows(self) -> int:
        return self._w.rows

    def write(self, e: Estimate) -> None:
        if (e.layout.sensing, e.layout.actuated) != (self.layout.sensing, self.layout.actuated):
            raise ValueError(f"an estimate of channels {list(e.layout.channels)} in a file of "
                             f"{list(self.layout.channels)}")
        self._w.write_row(estimate_row(e, self.target_names))


def write_estimates(path, estimates: Iterable[Estimate], target_names: Iterable[str],
                    metadata: dict | None, layout: ChannelLayout) -> Path:
    """Write a sequence of estimates of a phantom of ``layout`` to ``path`` (see :class:`EstimateWriter`)."""
    with EstimateWriter(path, target_names, metadata, layout) as w:
        for e in estimates:
            w.write(e)
    return w.path


class _SampleQueue:
    """Reader thread: drains a source into a queue; ``take`` gives samples in order. A sample more
    than ``max_lag_s`` older than the newest is dropped and counted (the consumer is behind)."""

    def __init__(self, source, read_timeout_s: float = 0.05, max_lag_s: float | None = None) -> None:
        self._src = source
        self._timeout = read_timeout_s
        self._max_lag = MAX_LAG_S if max_lag_s is None else max_lag_s
        self._cond = threading.Condition()
        self._q: collections.deque = collections.deque()
        self._dropped = 0  # samples dropped since the last take
        self.received = 0
        self.ended = False
        self.error: BaseException | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="softphantom-acquire", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop:
                batch = self._src.read(self._timeout)
                if batch is None:
                    break
                if batch:
                    with self._cond:
                        q = self._q
                        q.extend(batch)
                        self.received += len(batch)
                        newest = batch[-1].t
                        while len(q) > 1 and q[0].t < newest - self._max_lag:
                            q.popleft()
                            self._dropped += 1
                        self._cond.notify()
        except BaseException as exc:  # surfaced to the consumer
            self.error = exc
        finally:
            with self._cond:
                self.ended = True
                self._cond.notify()

    def take(self, timeout_s: float = 0.5):
        """(oldest queued sample, samples dropped before it) or (None, 0) on timeout / end."""
        with self._cond:
            if not self._q and not self.ended:
                self._cond.wait(timeout_s)
            if not self._q:
                return None, 0
            m, skipped = self._q.popleft(), self._dropped
            self._dropped = 0
            return m, skipped

    def stop(self) -> None:
        self._stop = True
        self._thread.join(timeout=2.0)


def iter_samples(source, live: bool, stop: threading.Event | None = None, idle: bool = False):
    """(measurement, skipped) from a sensor source. ``live``: a reader thread queues the samples,
    so acquisition never waits for the consumer; every sample comes out in order and ``skipped``
    counts those dropped for lagging more than ``MAX_LAG_S`` behind; otherwise every sample,
    ``skipped`` 0. ``idle``: also yield ``(None, 0)`` when a live source gave nothing for 0.5 s
    (so the consumer can show an outage while it lasts). Ends with the source or when ``stop``
    is set; a reader error is re-raised. The caller closes the source."""
    if not live:
        for m in source:
            yield m, 0
            if stop is not None and stop.is_set():
                return
        return
    q = _SampleQueue(source)
    try:
        while not (stop is not None and stop.is_set()):
            m, skipped = q.take()
            if m is None:
                if q.ended:
                    break
                if idle:
                    yield None, 0
                continue
            yield m, skipped
    finally:
        q.stop()
    if q.error is not None:
        raise q.error


class EventMarkers:
    """Turns a source's link events into marker estimates in time order: ``due(t)`` gives the
    markers of the events at or before ``t`` (all of them for ``t`` None)."""

    def __init__(self, source, target_names: Iterable[str], layout: ChannelLayout) -> None:
        self._src = source
        self._targets = list(target_names)
        self._layout = layout
        self._pending: list = []
        self.counts: dict[str, int] = {}

    def due(self, t: float | None = None) -> list[Estimate]:
        self._pending += self._src.events()
        now = [e for e in self._pending if t is None or e.t <= t]
        self._pending = [e for e in self._pending if not (t is None or e.t <= t)]
        for e in now:
            self.counts[e.kind] = self.counts.get(e.kind, 0) + 1
        return [marker_estimate(e, self._targets, self._layout) for e in now]


def _is_live(source) -> bool:
    from softphantom.sensing.sources import SerialSource

    return isinstance(source, SerialSource) or bool(getattr(source, "live", False))


def estimate_stream(source, estimator, out_path, on_estimate: Callable[[Estimate, int], None] | None = None,
                    *, live: bool | None = None, metadata: dict | None = None,
                    max_samples: int | None = None, stop: threading.Event | None = None,
                    on_event: Callable[[Estimate], None] | None = None) -> dict:
    """Estimate every sample of ``source`` (a :class:`~softphantom.sensing.sources.SensorSource`)
    with ``estimator`` (``.step(measurement, skipped=)``) and write the estimate CSV to
    ``out_path``, with a marker row for every link event of the source (``on_event(marker)`` is
    called for each, as it happens). ``live`` (default: a serial source, or one with
    ``live = True``) uses the reader thread's queue; ``on_estimate(estimate, n)`` is called after
    each estimate (the n-th); ``stop`` ends a live run. Memory stays flat (step times go into a histogram).
    Returns a summary dict (counts, rate, step-time percentiles, events by kind; ``outside`` the
    estimates clamped at the estimator's envelope, ``in_envelope`` False). An error of the
    source (e.g. a new board under the ``stop`` policy) is raised after its marker is written."""
    live = _is_live(source) if live is None else live
    targets = list(getattr(estimator, "target_names", ()))
    layout = estimator.layout
    meta = {"softphantom": _version(), "kind": "softphantom-estimate", "live": live, **(metadata or {})}
    steps = StepStats()
    n = rejected = skipped_total = outside = 0
    markers = EventMarkers(source, targets, layout)
    t0 = time.perf_counter()

    def mark(t: float | None) -> None:
        for e in markers.due(t):
            writer.write(e)
            if on_event is not None:
                on_event(e)

    with EstimateWriter(out_path, targets, meta, layout) as writer:
        try:
            for m, skipped in iter_samples(source, live, stop, idle=True):
                if m is None:
                    mark(None)
                    continue
                mark(m.t)
                e = estimator.step(m, skipped=skipped)
                writer.write(e)
                n += 1
                skipped_total += skipped
                steps.add(e.step_time)
                if e.status != "ok":
                    rejected += 1
                elif not e.in_envelope:
                    outside += 1
                if on_estimate is not None:
                    on_estimate(e, n)
                if max_samples is not None and n >= max_samples:
                    break
        finally:
            source.close()
            mark(None)
    wall = time.perf_counter() - t0
    return {
        "out": str(out_path), "estimates": n, "rejected": rejected, "skipped": skipped_total, "outside": outside,
        "wall_s": wall, "rate_Hz": n / wall if wall > 0 else math.nan,
        "step_ms_p50": steps.percentile(50) * 1e3, "step_ms_p99": steps.percentile(99) * 1e3,
        "step_ms_max": steps.max * 1e3, "events": dict(markers.counts),
    }


def _version() -> str:
    try:
        from softphantom import __version__

        return __version__
    except ImportError:  # pragma: no cover
        return "unknown"
