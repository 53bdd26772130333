"""What the live session's threads share: its options (:class:`LiveConfig`) and the bounded state
between the estimate pump and the page's server (:class:`LiveState`). Both
:mod:`~softphantom.viz.live.server` (the session, which fills it) and
:mod:`~softphantom.viz.live.web` (the page's server, which reads it) build on this module; the
server imports the web module, never the other way round.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from itertools import takewhile
from pathlib import Path
from typing import Any

import numpy as np

from softphantom.errors import UserError
from softphantom.records.names import EVENT_PREFIX
from softphantom.stream.schema import encode
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
