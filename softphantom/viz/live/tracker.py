"""The tracker beside the estimate: a NatNet stream (Motive, or ``virtual serve --natnet``) read in
a thread and attached to any estimate source as its ``poll_tracker()``.

Each ``/tracker`` message carries the raw pose (``position_m``, ``quat_xyzw`` in the tracker's
frame, ``frame``, ``latency_ms``, ``t_s`` on Motive's clock) and, once the first half second of
valid samples has given the rest pose, the pose relative to rest in the model frame
(``x_mm … roll_deg``), which the page draws dashed beside the estimate.
"""

from __future__ import annotations

import threading
from typing import Any

from softphantom.pose import Pose6
from softphantom.tracking.client import NatNetClient, NatNetConfig
from softphantom.tracking.record import RestRegistrar


class NatNetTrackerFeed:
    """Connects in :meth:`start` (a ``UserError`` when nobody answers), then reads in a thread."""

    def __init__(self, config: NatNetConfig, body: str | None = None, rest_window_s: float = 0.5):
        self.client = NatNetClient(config)
        self.body = body
        self.rest_window_s = rest_window_s
        self.body_id: int | None = None
        self.name = ""
        self._out: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "NatNetTrackerFeed":
        info = self.client.connect()
        self.body_id, self.name = self.client.choose_body(self.body)
        self._clock_hz = info.clock_hz
        self._thread = threading.Thread(target=self._run, name="natnet-tracker", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        reg = RestRegistrar(self.name, self.rest_window_s)
        for _, f in self.client.frames(stop=self._stop.is_set):
            rb = f.body(self.body_id)
            ok = rb is not None and rb.tracking_valid
            nan3, nan4 = (float("nan"),) * 3, (float("nan"),) * 4
            msg: dict[str, Any] = {"t_s": f.timestamp_s, "valid": ok, "name": self.name, "frame": f.frame_number,
                                   "position_m": list(rb.position if ok else nan3),
                                   "quat_xyzw": list(rb.quat_xyzw if ok else nan4)}
            lat = f.system_latency_s(self._clock_hz)
            if lat is not None:
                msg["latency_ms"] = lat * 1e3
            reg.add(f.timestamp_s, rb.position if ok else nan3, rb.quat_xyzw if ok else nan4, ok)
            cols = reg.take()
            if ok and cols is not None and len(cols["t_s"]):
                msg.update({k: float(cols[k][-1]) for k in Pose6.COLUMNS})
            with self._lock:
                self._out.append(msg)
                del self._out[:-10000]  # bounded if nobody polls

    def poll(self) -> list[dict[str, Any]]:
        """The messages since the last call (in order)."""
        with self._lock:
            out, self._out = self._out, []
        return out

    def stats(self) -> dict[str, Any]:
        st = self.client.stats
        return {"frames": st.frames, "lost": st.lost, "duplicates": st.duplicates, "reconnects": st.reconnects}

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        self.client.close()


class TrackedSource:
    """An estimate source with a tracker feed: iterates, draws and closes as the source does, and
    adds ``poll_tracker()``."""

    def __init__(self, source: Any, feed: NatNetTrackerFeed):
        self._source = source
        self.feed = feed

    def __getattr__(self, name: str) -> Any:
        return getattr(self._source, name)

    def __iter__(self):
        return iter(self._source)

    def poll_tracker(self) -> list[dict[str, Any]]:
        return self.feed.poll()

    def close(self) -> None:
        self.feed.close()
        close = getattr(self._source, "close", None)
        if callable(close):
            close()
