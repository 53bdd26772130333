"""Where a live tracker session goes: a session recording (MCAP, raw poses on ``/tracker``) or the
truth CSV (registered by its rest window as it is written). Both are written as the frames arrive
and flushed every second, so a session that is killed keeps all but its last second. A frame with
the body lost is an explicit gap, never NaN; the file says whether it is complete (:class:`TrackerSink`).

>>> import tempfile, os
>>> p = os.path.join(tempfile.mkdtemp(), "t.csv")
>>> with TrackerSink(p, body="bip", meta={"source": "doctest"}) as sink:
...     for i in range(120):
...         sink.add(i / 100, (0.1 + 0.001 * max(i - 60, 0), 0.0, 0.0), (0, 0, 0, 1), True, frame=i)
>>> from softphantom.evaluation import read_truth
>>> tru = read_truth(p)
>>> len(tru.t), round(float(tru.mm_deg()[-1, 0]), 6)
(120, 59.0)
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.records.names import POSE_COLUMNS
from softphantom.records.session import SessionWriter
from softphantom.tracking.registration import DEFAULT_REST_WINDOW_S, pose_columns, register_track, rest_pose
from softphantom.tracking.track import PoseTrack, make_track

FLUSH_S = 1.0


class RestRegistrar:
    """Register samples as they come: the first ``rest_window_s`` of valid samples give the rest
    pose, then every sample's pose relative to rest in the model frame (as :func:`register_track`).
    :meth:`add` returns the registered rows that became known (``t_s`` and the 6 DoF in mm, deg;
    lost samples left out)."""

    def __init__(self, name: str, rest_window_s: float = DEFAULT_REST_WINDOW_S):
        self.name = name
        self.rest_window_s = rest_window_s
        self.rest = None
        self.t0: float | None = None
        self._pending: list[tuple] = []

    def add(self, t: float, position, quat_xyzw, valid: bool) -> None:
        self._pending.append((float(t), tuple(position), tuple(quat_xyzw), bool(valid)))
        if self.rest is None:
            valid_t = [p[0] for p in self._pending if p[3]]
            if not valid_t or t < valid_t[0] + self.rest_window_s:
                return None
            self._set_rest(valid_t[0], valid_t[0] + self.rest_window_s)

    def _set_rest(self, t0: float, t1: float) -> None:
        self.t0 = t0
        self.rest = rest_pose(self._track(), (t0, t1))

    def _track(self) -> PoseTrack:
        t, p, q, v = zip(*self._pending)
        p = np.where(np.asarray(v)[:, None], np.asarray(p, float), np.nan)
        return make_track(np.asarray(t), p, np.asarray(q, float), clock="tracker", source="live", name=self.name)

    def take(self, finish: bool = False, gaps: bool = False) -> dict[str, np.ndarray] | None:
        """The registered rows so far (None before the rest pose is known); ``finish``: a session
        shorter than the rest window takes all of it as rest; ``gaps``: lost samples kept (NaN),
        and at ``finish`` a body never seen gives all its samples as gaps."""
        if self.rest is None and finish and any(p[3] for p in self._pending):
            self._set_rest(min(p[0] for p in self._pending if p[3]), math.inf)
        if not self._pending or (self.rest is None and not (finish and gaps)):
            return None
        if self.rest is None:
            t = np.array([p[0] for p in self._pending])
            cols = {"t_s": t, **{k: np.full(len(t), np.nan) for k in POSE_COLUMNS}}
        else:
            cols = pose_columns(register_track(self._track(), rest=self.rest), keep_lost=gaps)
        self._pending.clear()
        return cols


class TrackerSink:
    """Write tracker samples to ``path`` (``.mcap`` or ``.csv``), see the module docstring.

    A lost frame (``valid`` False) is an explicit gap: ``null`` pose on ``/tracker``, a row with the
    time and empty pose cells in the CSV; never NaN. The file's metadata says ``complete`` false
    from the start; closing after the last frame (leaving the ``with`` without an exception, no
    write cut short) sets it true and adds the counts (``frames``, ``frames_body_lost`` and
    :attr:`end_meta`, e.g. the client's lost frames). A session that fails stays incomplete (an
    MCAP without its summary, as a killed one; the CSV's header keeps ``complete`` false).
    """

    def __init__(self, path, *, body: str, meta: dict | None = None, rest_window_s: float = DEFAULT_REST_WINDOW_S):
        self.path = Path(path)
        self.body = body
        self.meta = dict(meta or {})
        self.kind = self.path.suffix.lower()
        if self.kind not in (".mcap", ".csv"):
            raise UserError(f"--out must name a .mcap (session recording) or .csv (truth CSV) file, got {self.path}")
        self.rest_window_s = rest_window_s
        self.samples = 0
        self.body_lost = 0
        #: what the caller adds to the file's metadata at a clean close (client counters, how it stopped)
        self.end_meta: dict = {}
        self._rec = None
        self._fh: SessionWriter | None = None
        self._reg = RestRegistrar(body, rest_window_s)
        self._header: dict | None = None
        self._writing = False  # True while a write is under way: an exception then cuts it short
        #: after :meth:`close`: whether the file was marked complete
        self.complete: bool | None = None
        self._last_flush = time.monotonic()
        if self.kind == ".mcap":
            from softphantom.stream.recording import SessionRecorder

            self._rec = SessionRecorder(self.path, layout=None, metadata=_strings(self._start_meta()))
        else:  # the metadata line waits for the rest window
            self._fh = SessionWriter(self.path, ("t_s",) + POSE_COLUMNS)

    def _start_meta(self) -> dict:
        return {**self.meta, "body": self.body, "complete": False}

    def add(self, t: float, position, quat_xyzw, valid: bool, *, frame: int | None = None,
            latency_ms: float | None = None) -> None:
        """One sample: ``t`` s (the tracker's clock), position m and quaternion in the tracker frame."""
        self._writing = True
        self.samples += 1
        self.body_lost += not valid
        if self._rec is not None:
            self._rec.write_tracker(tracker_raw_message(t, position, quat_xyzw, valid, self.body, frame, latency_ms))
        else:
            self._reg.add(t, position, quat_xyzw, valid)
            if self._reg.rest is not None and time.monotonic() - self._last_flush >= FLUSH_S:
                self.flush()
        self._writing = False

    def _write_header(self) -> None:
        from softphantom import __version__

        r = self._reg
        rest = r.rest is not None
        self._header = {"softphantom": __version__, **self._start_meta(), "registration": "rest window",
                        "rest_window_s": [r.t0, r.t0 + self.rest_window_s] if rest else None,
                        "rest_spread_m": float(r.rest.rms_residual) if rest else None}
        self._fh.start(self._header)

    def flush(self, finish: bool = False) -> None:
        if self._rec is not None:
            self._rec.flush()
            return
        cols = self._reg.take(finish, gaps=True)
        if cols is None:
            return
        if self._header is None:
            self._write_header()
        self._fh.write_rows(zip(*(cols[k] for k in self._fh.columns)))
        self._last_flush = time.monotonic()

    def close(self, complete: bool = True) -> None:
        """Close the file; ``complete`` False (or a write cut short) leaves it marked incomplete."""
        self.complete = complete = complete and not self._writing
        end = {"complete": complete, "frames": self.samples, "frames_body_lost": self.body_lost, **self.end_meta}
        if self._rec is not None:
            rec, self._rec = self._rec, None
            if complete:
                rec.close(metadata=_strings(end))
            else:
                rec.abort()
        if self._fh is not None:
            fh, final = self._fh, None
            try:
                self.flush(finish=True)
                if self._header is None:  # not one sample
                    self._write_header()
                final = {**self._header, **end} if complete else None  # the final counts
            except Exception:
                if complete:
                    raise
                # the session failed already: keep what was written, and its error
            finally:
                self._fh = None
                fh.close(final)

    def __enter__(self) -> "TrackerSink":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(complete=exc_type is None)


def _strings(meta: dict) -> dict[str, str]:
    """MCAP metadata values (strings; JSON's spelling of booleans and None)."""
    return {k: json.dumps(v) if isinstance(v, (bool, type(None))) else str(v) for k, v in meta.items()}


def tracker_raw_message(t: float, position, quat_xyzw, valid: bool, name: str, frame: int | None = None,
                        latency_ms: float | None = None) -> dict:
    """The ``/tracker`` message of a raw tracker pose (tracker frame, m); a lost body's pose is ``None``."""
    msg = {"t_s": float(t), "valid": bool(valid), "name": name,
           "position_m": [float(x) for x in position] if valid else None,
           "quat_xyzw": [float(x) for x in quat_xyzw] if valid else None}
    if frame is not None:
        msg["frame"] = int(frame)
    if latency_ms is not None:
        msg["latency_ms"] = float(latency_ms)
    return msg
