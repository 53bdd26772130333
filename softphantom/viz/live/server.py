"""The live session: pump estimates from a source to the network stream, the recording and the
local web page (:mod:`softphantom.viz.live.web`: Starlette on uvicorn, Server-Sent Events).

Threads: one *pump* runs the source and, per estimate, publishes (non-blocking), records and
appends to :class:`LiveState`; the web server's thread builds one frame per view tick from the
shared state for every browser. Nothing a browser or subscriber does can block the pump: the state
is a bounded ring under a lock held for microseconds.

Security (docs/stream.md; :mod:`softphantom.viz.live.security`): loopback unless a token is given,
the ``Host`` header checked (DNS rebinding), the token (query once, then a cookie) beyond loopback,
at most ``max_clients`` requests at once (503 beyond), a silent or stalled client dropped after
``client_timeout_s``.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from itertools import takewhile
from pathlib import Path
from typing import Any

import numpy as np

from softphantom.errors import SoftphantomError, UserError
from softphantom.stream.schema import encode, estimate_to_message
from softphantom.records.names import EVENT_PREFIX
from softphantom.records.names import POSE_COLUMNS as _TRACKER_KEYS
from softphantom.viz.live.security import is_loopback

OUTAGE_EVENTS = ("silent", "disconnected", "reconnected")
"""Link events after which no sample arrives until ``resumed`` (docs/sensing.md §9)."""


@dataclass(frozen=True)
class LiveConfig:
    """Options of a live session. Ports 0 pick a free port; ``stream_port=None`` disables the
    network stream. ``listen_host`` is loopback unless set explicitly (both page and stream);
    beyond loopback a ``token`` is required (:func:`~softphantom.viz.live.security.is_loopback`).
    ``allowed_hosts``: extra names accepted in the ``Host`` header; ``max_clients``: requests served
    at once (an open page holds one). ``foxglove_port``: serve Foxglove's WebSocket protocol there
    too, on ``listen_host`` (:mod:`softphantom.stream.foxglove`; None: not)."""

    listen_host: str = "127.0.0.1"
    http_port: int = 8765
    stream_port: int | None = 5556
    view_rate_Hz: float = 30.0
    history: int = 20000
    record: Path | None = None
    record_surface_Hz: float = 10.0
    duration_s: float | None = None
    token: str | None = None
    allowed_hosts: tuple[str, ...] = ()
    max_clients: int = 16
    client_timeout_s: float = 10.0
    foxglove_port: int | None = None

    def __post_init__(self) -> None:
        if not is_loopback(self.listen_host) and not self.token:
            raise UserError(f"listen host {self.listen_host!r} is beyond loopback: a token is required")
        if self.max_clients < 1:
            raise UserError(f"max_clients must be >= 1, got {self.max_clients}")




class LiveState:
    """Shared, bounded state between the pump and the page (thread-safe)."""

    def __init__(self, history: int = 20000):
        self._lock = threading.Condition()
        self._hist: deque[tuple[dict[str, Any], bytes]] = deque(maxlen=history)  # (message, its JSON)
        self.latest: dict[str, Any] | None = None
        self.seq = -1
        self.surface_b64: str | None = None
        self.surface_version = 0
        self.surface_max_mm = 0.0
        self.skipped_total = 0
        self.view_dropped = 0
        self.stream: dict[str, Any] = {"enabled": False}
        self.recording: dict[str, Any] = {"enabled": False}
        self.finished = False
        self.error: str | None = None
        self.outage: str | None = None  # the link event the link is down since, if it is
        self.last_event: str | None = None
        self.in_envelope: bool | None = None
        self._arrivals: deque[float] = deque(maxlen=4096)
        self._steps: deque[float] = deque(maxlen=1000)
        self.frames_served = 0

    def push(self, msg: dict[str, Any], data: bytes | None = None) -> None:
        """Append an estimate message (``data``: its JSON, if already encoded)."""
        status = str(msg.get("status") or "ok")
        data = encode(msg) if data is None else data
        with self._lock:
            self._hist.append((msg, data))
            self.latest = msg
            self.seq = msg["seq"]
            self.skipped_total += int(msg.get("skipped") or 0)
            self._arrivals.append(time.monotonic())
            if status.startswith(EVENT_PREFIX):  # a link event's marker: no numbers, no step
                self.last_event = status[len(EVENT_PREFIX):]
                kind = self.last_event.split(":", 1)[0]
                if kind in OUTAGE_EVENTS:
                    self.outage = self.last_event
                elif kind == "resumed":
                    self.outage = None
            else:
                self.outage = None
                self.in_envelope = bool(msg.get("in_envelope", 1))
                if msg.get("step_ms") is not None:
                    self._steps.append(msg["step_ms"])
            self._lock.notify_all()

    def set_surface(self, b64: str, max_mm: float) -> None:
        with self._lock:
            self.surface_b64, self.surface_max_mm = b64, max_mm
            self.surface_version += 1

    def finish(self, error: str | None = None) -> None:
        with self._lock:
            self.finished, self.error = True, error
            self._lock.notify_all()

    def add_view_dropped(self, n: int) -> None:
        with self._lock:
            self.view_dropped += n

    def changed_since(self, seq: int, surface_version: int) -> bool:
        return self.seq != seq or self.surface_version != surface_version

    def status(self) -> dict[str, Any]:
        """Rate (Hz, over the last 2 s), step latency (ms, last and p99), counters, health, link."""
        with self._lock:
            now = time.monotonic()
            recent = [a for a in self._arrivals if now - a <= 2.0]
            rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 2 and recent[-1] > recent[0] else 0.0
            steps = list(self._steps)
            latest = self.latest
            age = now - self._arrivals[-1] if self._arrivals else None
            health, link, detail = "waiting", "waiting", ""
            if latest is not None:
                health = str(latest.get("status", "ok"))
                link = "ok"
                if self.outage is not None:
                    link, detail = "outage", self.outage
                elif not self.finished and age is not None and age > 1.0:
                    health = f"stalled ({age:.1f} s without estimate)"
                    link, detail = "stalled", f"{age:.1f} s without estimate"
            if self.finished:
                link = "ended"
            if self.error:
                health = f"error: {self.error}"
                link, detail = "error", self.error
            return {
                "rate_Hz": round(rate, 2),
                "step_ms": latest.get("step_ms") if latest else None,
                "step_p99_ms": float(np.percentile(steps, 99)) if steps else None,
                "estimates": self.seq + 1,
                "skipped_total": self.skipped_total,
                "view_dropped": self.view_dropped,
                "last_estimate_age_s": None if age is None else round(age, 3),
                "sensor_health": health,
                "link": link,
                "link_detail": detail,
                "last_event": self.last_event,
                "in_envelope": self.in_envelope,
                "qp_status": latest.get("qp_status") if latest else None,
                "cond_W": latest.get("cond_W") if latest else None,
                "surface_max_mm": round(self.surface_max_mm, 3),
                "stream": dict(self.stream),
                "recording": dict(self.recording),
                "finished": self.finished,
            }

    def _since(self, seq: int, surface_version: int, max_samples: int) -> tuple[list, str | None, int, int]:
        """(the (message, JSON) pairs after ``seq``, the surface if newer than ``surface_version``,
        the seq and surface version to pass next time)."""
        with self._lock:
            new = list(takewhile(lambda m: m[0]["seq"] > seq, reversed(self._hist)))[:max_samples]
            new.reverse()
            if new and seq >= 0 and new[0][0]["seq"] > seq + 1:
                self.view_dropped += new[0][0]["seq"] - seq - 1
            changed = self.surface_version != surface_version
            self.frames_served += 1
            return new, self.surface_b64 if changed else None, self.seq, self.surface_version

    def frame_since(self, seq: int, surface_version: int, max_samples: int = 2000) -> tuple[dict[str, Any], int, int]:
        """The next frame for a client that has seen up to ``seq`` and ``surface_version``:
        ``(frame, seq, surface_version)`` to pass next time."""
        new, surface, last, sv = self._since(seq, surface_version, max_samples)
        frame: dict[str, Any] = {"samples": [m for m, _ in new]}
        if surface is not None:
            frame["surface_mm_f32_b64"] = surface
        frame["status"] = self.status()
        return frame, last, sv

    def frame_json_since(self, seq: int, surface_version: int, max_samples: int = 2000) -> tuple[bytes, int, int, int]:
        """:meth:`frame_since` as JSON bytes, joined from the messages' JSON (each estimate is
        encoded once, by the pump): ``(json, number of samples, seq, surface_version)``."""
        new, surface, last, sv = self._since(seq, surface_version, max_samples)
        parts = [b'{"samples":[', b",".join(d for _, d in new), b"]"]
        if surface is not None:
            parts += [b',"surface_mm_f32_b64":"', surface.encode(), b'"']
        parts += [b',"status":', encode(self.status()), b"}"]
        return b"".join(parts), len(new), last, sv


class LiveSession:
    """Run a source live: page on ``url``, stream on ``stream_endpoint``, optional recording.

    >>> from softphantom.viz.live.source import SyntheticSource
    >>> src = SyntheticSource(rate_Hz=200, duration_s=0.2, subdivisions=1)
    >>> with LiveSession(src, LiveConfig(http_port=0, stream_port=0)) as s:
    ...     ended = s.wait(timeout_s=120.0)
    ...     st = s.state.status()
    >>> ended, st["finished"], st["estimates"] + st["skipped_total"]  # each tick shown or counted skipped
    (True, True, 40)
    """

    def __init__(self, source: Any, config: LiveConfig = LiveConfig()):
        self.source, self.config = source, config
        self.state = LiveState(config.history)
        self._stop = threading.Event()
        self._pump: threading.Thread | None = None
        self._web = None
        self.publisher = None
        self.recorder = None
        self.foxglove = None  # Foxglove's messages, to the recording and/or its live server
        self.error: BaseException | None = None
        geo = getattr(source, "geometry", None)
        self.geometry_json = None if geo is None else geo.to_json()

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> "LiveSession":
        from softphantom.viz.live.web import WebServer

        cfg = self.config
        fox_server = None
        if cfg.foxglove_port is not None:  # first: a port in use stops the session before anything started
            from softphantom.stream.foxglove import FoxgloveServer

            fox_server = FoxgloveServer(cfg.listen_host, cfg.foxglove_port)
        try:
            self._web = WebServer(self)
        except BaseException:
            if fox_server is not None:
                fox_server.close()
            raise
        if cfg.stream_port is not None:
            from softphantom.stream.publisher import EstimatePublisher

            self.publisher = EstimatePublisher(port=cfg.stream_port, host=cfg.listen_host)
            self.state.stream = {"enabled": True, "endpoint": self.publisher.endpoint, "sent": 0, "subscribers": 0}
        if cfg.record is not None:
            from softphantom.stream.recording import TOPIC_GEOMETRY, SessionRecorder

            self.recorder = SessionRecorder(cfg.record, metadata={"source": type(self.source).__name__})
            if self.geometry_json is not None:
                self.recorder.write(TOPIC_GEOMETRY, self.geometry_json)
            self.state.recording = {"enabled": True, "path": str(cfg.record), "messages": 0}
        if fox_server is not None or self.recorder is not None:
            from softphantom.stream.foxglove import FoxgloveBridge, FoxgloveScene

            geo = getattr(self.source, "geometry", None)
            self.foxglove = FoxgloveBridge(FoxgloveScene(self.geometry_json), self.recorder, fox_server,
                                           node_index=None if geo is None else geo.node_index)
        self._pump = threading.Thread(target=self._run_pump, name="live-pump", daemon=True)
        self._pump.start()
        return self

    @property
    def url(self) -> str:
        """The page's address (with ``?token=`` when one is required)."""
        assert self._web is not None
        host, port = self._web.address
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{port}/" + (f"?token={self.config.token}" if self.config.token else "")

    @property
    def foxglove_url(self) -> str | None:
        """``ws://host:port`` of the Foxglove server, if one runs."""
        fg = self.foxglove
        return None if fg is None or fg.server is None else fg.server.url

    @property
    def stream_endpoint(self) -> str | None:
        return None if self.publisher is None else self.publisher.endpoint

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the source to end (or ``timeout_s``); re-raise a source error. True if ended."""
        assert self._pump is not None
        self._pump.join(timeout_s)
        if self.error is not None:
            raise self.error
        return not self._pump.is_alive()

    def stop(self) -> None:
        """Stop the pump, the page server, the stream and finish the recording. Idempotent."""
        self._stop.set()
        if self._pump is not None:
            self._pump.join(5.0)
        self.state.finish(self.state.error)
        if self._web is not None:
            self._web.stop()
            self._web = None
        if self.publisher is not None:
            self.publisher.close()
            self.publisher = None
        if self.foxglove is not None:
            self.foxglove.close()
            self.foxglove = None
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        close = getattr(self.source, "close", None)
        if callable(close):
            close()

    def __enter__(self) -> "LiveSession":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the pump ---------------------------------------------------------------------------
    def _run_pump(self) -> None:
        from softphantom.stream.recording import TOPIC_SURFACE, measurement_to_message

        src, cfg, st = self.source, self.config, self.state
        geo = getattr(src, "geometry", None)
        view_dt = 1.0 / cfg.view_rate_Hz
        rec_dt = 1.0 / cfg.record_surface_Hz if cfg.record_surface_Hz > 0 else None
        last_view = last_rec = -1e9
        t_end = None if cfg.duration_s is None else time.monotonic() + cfg.duration_s
        last_meas = getattr(src, "last_measurement", None)
        poll_tracker = getattr(src, "poll_tracker", None)
        tracker = None  # the latest tracker pose relative to rest, drawn beside the estimate
        seq = -1
        try:
            for est in src:
                if self._stop.is_set():
                    break
                seq += 1
                msg = estimate_to_message(est, seq, time.time())
                data = encode(msg)
                if self.publisher is not None:
                    self.publisher.publish(data)
                if self.recorder is not None:
                    self.recorder.write_estimate(data)
                    if callable(last_meas) and (m := last_meas()) is not None:
                        self.recorder.write_sensors(measurement_to_message(m))
                if self.foxglove is not None:
                    self.foxglove.estimate(msg, data)
                for tm in (poll_tracker() or ()) if callable(poll_tracker) else ():
                    if self.recorder is not None:
                        self.recorder.write_tracker(tm)
                    if self.foxglove is not None:
                        self.foxglove.tracker(tm)
                    if all(isinstance(tm.get(k), (int, float)) and math.isfinite(tm[k]) for k in _TRACKER_KEYS):
                        tracker = {k: tm[k] for k in _TRACKER_KEYS}  # a lost frame keeps the last pose
                if tracker is None:
                    st.push(msg, data)
                else:
                    st.push({**msg, "tracker": tracker})  # the page only
                now = time.monotonic()
                want_rec = self.recorder is not None and rec_dt is not None and now - last_rec >= rec_dt
                if geo is not None and (now - last_view >= view_dt or want_rec):
                    pos = src.node_positions()
                    if pos is not None:
                        b64 = _set_surface(st, geo, pos)
                        last_view = now
                        if self.foxglove is not None:
                            self.foxglove.surface(pos)
                        if want_rec:
                            self.recorder.write(TOPIC_SURFACE, {"t_s": msg["t_s"], "seq": seq,
                                                                "positions_mm_f32_b64": b64})
                            last_rec = now
                if self.publisher is not None and seq % 16 == 0:
                    ps = self.publisher.stats()
                    st.stream.update(sent=ps.sent, subscribers=ps.subscribers, max_publish_ms=round(ps.max_publish_ms, 3))
                if self.recorder is not None and seq % 16 == 0:
                    st.recording["messages"] = self.recorder.messages_written
                if t_end is not None and now >= t_end:
                    break
        except SoftphantomError as exc:
            self.error = exc
            st.finish(str(exc))
            return
        except Exception as exc:  # a bug in a source: keep the page up, say so, re-raise in wait()
            self.error = exc
            st.finish(f"{type(exc).__name__}: {exc}")
            return
        if geo is not None and seq >= 0 and (pos := src.node_positions()) is not None:  # show the final state
            _set_surface(st, geo, pos)
        if self.publisher is not None:
            ps = self.publisher.stats()
            st.stream.update(sent=ps.sent, subscribers=ps.subscribers, max_publish_ms=round(ps.max_publish_ms, 3))
        if self.recorder is not None:
            st.recording["messages"] = self.recorder.messages_written
        st.finish()

    # -- for the web server ----------------------------------------------------------------
    def state_json(self) -> dict[str, Any]:
        return {"status": self.state.status(), "latest": self.state.latest,
                "has_geometry": self.geometry_json is not None,
                "view_rate_Hz": self.config.view_rate_Hz,
                "surface_mm_f32_b64": self.state.surface_b64}


def _set_surface(st: LiveState, geo: Any, pos: np.ndarray) -> str:
    """Pick the surface out of all model nodes (or take it as is), publish it to the page."""
    from softphantom.viz.live.source import encode_positions_mm

    pos = np.asarray(pos)
    surf = pos[geo.node_index] if len(pos) != len(geo.nodes) else pos
    b64 = encode_positions_mm(surf)
    st.set_surface(b64, float(np.max(np.linalg.norm(surf - geo.nodes, axis=1))) * 1e3)
    return b64
