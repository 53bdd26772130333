"""Run an estimator over a sensor source and write the estimate CSV (docs/architecture.md).

Live sources (the serial board): a reader thread drains the source into a latest-sample slot, so
acquisition never waits for the estimator; when estimation falls behind it takes the newest
sample and counts the ones it skipped (``Estimate.skipped``). Offline sources (a replay, a
simulation) are estimated sample by sample, nothing skipped.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.types import ARM_NAMES, Estimate

POSE_COLUMNS = ("x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg")
FLUSH_EVERY_S = 0.2


def estimate_columns(target_names: Iterable[str]) -> list[str]:
    """Header of the estimate CSV, in order (docs/architecture.md).

    >>> estimate_columns(["apex"])[:5], estimate_columns([])[-4:]
    (['t_s', 'force_x_N', 'force_y_N', 'force_z_N', 'p_urethra_kPa'], ['cond_W', 'qp_status', 'step_ms', 'skipped'])
    """
    cols = ["t_s", "force_x_N", "force_y_N", "force_z_N", "p_urethra_kPa", *POSE_COLUMNS]
    for n in target_names:
        cols += [f"{n}_dx_mm", f"{n}_dy_mm", f"{n}_dz_mm"]
    cols += [f"dVpred_{a}_mm3" for a in ARM_NAMES] + [f"dVmeas_{a}_mm3" for a in ARM_NAMES]
    return cols + ["cond_W", "qp_status", "step_ms", "skipped"]


def _cell(v: float) -> str:
    v = float(v)
    return repr(v) if math.isfinite(v) else "nan"


def estimate_row(e: Estimate, target_names: Iterable[str]) -> list[str]:
    """One CSV row (units of the header) for an estimate."""
    cells = [_cell(e.t), *(_cell(f) for f in e.force), _cell(e.p_urethra * 1e-3)]
    cells += [_cell(v) for v in np.concatenate([np.asarray(e.pose.xyz) * 1e3, np.degrees(e.pose.ypr)])]
    for n in target_names:
        cells += [_cell(v * 1e3) for v in e.target_shift[n]]
    cells += [_cell(v * 1e9) for v in e.volume_pred] + [_cell(v * 1e9) for v in e.volume_meas]
    cells += [_cell(e.cond_W), str(e.qp_status).replace(",", ";"), _cell(e.step_time * 1e3), str(int(e.skipped))]
    return cells


class EstimateWriter:
    """Write estimates to a CSV: a ``# {json}`` metadata line, the header, one row per estimate,
    flushed to the OS at least every ``flush_every_s`` (and on :meth:`close`)."""

    def __init__(self, path, target_names: Iterable[str], metadata: dict | None = None,
                 flush_every_s: float = FLUSH_EVERY_S) -> None:
        self.path = Path(path)
        self.target_names = list(target_names)
        try:
            self._f = open(self.path, "w", encoding="utf-8", newline="")
        except OSError as exc:
            raise UserError(f"--out {self.path}: cannot create ({exc.strerror})") from None
        self._every = flush_every_s
        self._last = time.monotonic()
        self.rows = 0
        self._f.write("# " + json.dumps(metadata or {}, separators=(",", ":"), default=str) + "\n")
        self._f.write(",".join(estimate_columns(self.target_names)) + "\n")
        self._f.flush()

    def write(self, e: Estimate) -> None:
        self._f.write(",".join(estimate_row(e, self.target_names)) + "\n")
        self.rows += 1
        now = time.monotonic()
        if now - self._last >= self._every:
            self._f.flush()
            self._last = now

    def close(self) -> None:
        if not self._f.closed:
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_estimates(path, estimates: Iterable[Estimate], target_names: Iterable[str],
                    metadata: dict | None = None) -> Path:
    """Write a sequence of estimates to ``path`` (see :class:`EstimateWriter`)."""
    with EstimateWriter(path, target_names, metadata) as w:
        for e in estimates:
            w.write(e)
    return w.path


class _LatestSlot:
    """Reader thread: drains a source into a slot holding only the newest sample."""

    def __init__(self, source, read_timeout_s: float = 0.05) -> None:
        self._src = source
        self._timeout = read_timeout_s
        self._cond = threading.Condition()
        self._latest = None
        self._pending = 0  # samples arrived since the last take
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
                        self._latest = batch[-1]
                        self._pending += len(batch)
                        self.received += len(batch)
                        self._cond.notify()
        except BaseException as exc:  # surfaced to the consumer
            self.error = exc
        finally:
            with self._cond:
                self.ended = True
                self._cond.notify()

    def take(self, timeout_s: float = 0.5):
        """(newest sample, samples skipped) or (None, 0) on timeout / end."""
        with self._cond:
            if self._pending == 0 and not self.ended:
                self._cond.wait(timeout_s)
            if self._pending == 0:
                return None, 0
            m, skipped = self._latest, self._pending - 1
            self._pending = 0
            return m, skipped

    def stop(self) -> None:
        self._stop = True
        self._thread.join(timeout=2.0)


def iter_samples(source, live: bool, stop: threading.Event | None = None):
    """(measurement, skipped) from a sensor source. ``live``: a reader thread keeps only the newest
    sample, so acquisition never waits for the consumer, and ``skipped`` counts what it overtook;
    otherwise every sample, ``skipped`` 0. Ends with the source or when ``stop`` is set; a reader
    error is re-raised. The caller closes the source."""
    if not live:
        for m in source:
            yield m, 0
            if stop is not None and stop.is_set():
                return
        return
    slot = _LatestSlot(source)
    try:
        while not (stop is not None and stop.is_set()):
            m, skipped = slot.take()
            if m is None:
                if slot.ended:
                    break
                continue
            yield m, skipped
    finally:
        slot.stop()
    if slot.error is not None:
        raise slot.error


def _is_live(source) -> bool:
    from softphantom.sensing.sources import SerialSource

    return isinstance(source, SerialSource) or bool(getattr(source, "live", False))


def estimate_stream(source, estimator, out_path, progress: Callable[[Estimate, int], None] | None = None,
                    *, live: bool | None = None, metadata: dict | None = None,
                    max_samples: int | None = None, stop: threading.Event | None = None) -> dict:
    """Estimate every sample of ``source`` (a :class:`~softphantom.sensing.sources.SensorSource`)
    with ``estimator`` (``.step(measurement, skipped=)``) and write the estimate CSV to
    ``out_path``. ``live`` (default: a serial source, or one with ``live = True``) uses the
    latest-sample slot; ``progress(estimate, n)`` is called after each estimate; ``stop`` ends a
    live run. Returns a summary dict (counts, rate, step-time percentiles)."""
    live = _is_live(source) if live is None else live
    targets = list(getattr(estimator, "target_names", ()))
    meta = {"softphantom": _version(), "kind": "softphantom-estimate", "live": live, **(metadata or {})}
    steps: list[float] = []
    n = rejected = skipped_total = 0
    t0 = time.perf_counter()

    def handle(m, skipped: int) -> None:
        nonlocal n, rejected, skipped_total
        e = estimator.step(m, skipped=skipped)
        writer.write(e)
        n += 1
        skipped_total += skipped
        steps.append(e.step_time)
        if e.status != "ok":
            rejected += 1
        if progress is not None:
            progress(e, n)

    with EstimateWriter(out_path, targets, meta) as writer:
        try:
            for m, skipped in iter_samples(source, live, stop):
                handle(m, skipped)
                if max_samples is not None and n >= max_samples:
                    break
        finally:
            source.close()
    wall = time.perf_counter() - t0
    st = np.asarray(steps) * 1e3 if steps else np.full(1, np.nan)
    return {
        "out": str(out_path), "estimates": n, "rejected": rejected, "skipped": skipped_total,
        "wall_s": wall, "rate_Hz": n / wall if wall > 0 else math.nan,
        "step_ms_p50": float(np.percentile(st, 50)), "step_ms_p99": float(np.percentile(st, 99)),
        "step_ms_max": float(np.max(st)),
    }


def _version() -> str:
    try:
        from softphantom import __version__

        return __version__
    except ImportError:  # pragma: no cover
        return "unknown"
