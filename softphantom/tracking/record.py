"""Where a live tracker session goes: a session recording (MCAP, raw poses on ``/tracker``) or the
truth CSV (registered by its rest window as it is written). Both are written as the frames arrive
and flushed every second, so a session that is killed keeps all but its last second.

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
from softphantom.pose import Pose6
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

    def take(self, finish: bool = False) -> dict[str, np.ndarray] | None:
        """The registered rows so far (None before the rest pose is known); ``finish``: a session
        shorter than the rest window takes all of it as rest."""
        if self.rest is None and finish and any(p[3] for p in self._pending):
            self._set_rest(min(p[0] for p in self._pending if p[3]), math.inf)
        if self.rest is None or not self._pending:
            return None
        cols = pose_columns(register_track(self._track(), rest=self.rest))
        self._pending.clear()
        return cols


class TrackerSink:
    """Write tracker samples to ``path`` (``.mcap`` or ``.csv``), see the module docstring."""

    def __init__(self, path, *, body: str, meta: dict | None = None, rest_window_s: float = DEFAULT_REST_WINDOW_S):
        self.path = Path(path)
        self.body = body
        self.meta = dict(meta or {})
        self.kind = self.path.suffix.lower()
        if self.kind not in (".mcap", ".csv"):
            raise UserError(f"--out must name a .mcap (session recording) or .csv (truth CSV) file, got {self.path}")
        self.rest_window_s = rest_window_s
        self.samples = 0
        self._rec = None
        self._fh = None
        self._reg = RestRegistrar(body, rest_window_s)
        self._header = False
        self._last_flush = time.monotonic()
        if self.kind == ".mcap":
            from softphantom.stream.recording import SessionRecorder

            self._rec = SessionRecorder(self.path, metadata={k: str(v) for k, v in self.meta.items()})
        else:
            try:
                self._fh = open(self.path, "w", newline="")
            except OSError as exc:
                raise UserError(f"cannot write {self.path}: {exc.strerror}") from None

    def add(self, t: float, position, quat_xyzw, valid: bool, *, frame: int | None = None,
            latency_ms: float | None = None) -> None:
        """One sample: ``t`` s (the tracker's clock), position m and quaternion in the tracker frame."""
        self.samples += 1
        if self._rec is not None:
            msg = {"t_s": float(t), "valid": bool(valid), "name": self.body,
                   "position_m": [float(x) for x in position], "quat_xyzw": [float(x) for x in quat_xyzw]}
            if frame is not None:
                msg["frame"] = int(frame)
            if latency_ms is not None:
                msg["latency_ms"] = float(latency_ms)
            self._rec.write_tracker(msg)
            return
        self._reg.add(t, position, quat_xyzw, valid)
        if self._reg.rest is not None and time.monotonic() - self._last_flush >= FLUSH_S:
            self.flush()

    def _write_header(self) -> None:
        from softphantom import __version__

        r = self._reg
        meta = {"softphantom": __version__, **self.meta, "body": self.body, "registration": "rest window",
                "rest_window_s": [r.t0, r.t0 + self.rest_window_s], "rest_spread_m": float(r.rest.rms_residual)}
        self._fh.write("# " + json.dumps(meta, default=str) + "\n" + ",".join(("t_s",) + Pose6.COLUMNS) + "\n")
        self._header = True

    def flush(self, finish: bool = False) -> None:
        if self._rec is not None:
            self._rec.flush()
            return
        cols = self._reg.take(finish)
        if cols is None:
            return
        if not self._header:
            self._write_header()
        names = ("t_s",) + Pose6.COLUMNS
        for row in zip(*(cols[k] for k in names)):
            self._fh.write(",".join(repr(float(x)) for x in row) + "\n")
        self._fh.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if self._rec is not None:
            self._rec.close()
            self._rec = None
        if self._fh is not None:
            self.flush(finish=True)
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "TrackerSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
