"""The live session: pump estimates from a source to the network stream, the recording and a
local web page (stdlib HTTP server, Server-Sent Events).

Threads: one *pump* runs the source and, per estimate, publishes (non-blocking), records and
appends to :class:`LiveState`; the HTTP server serves the page and one SSE stream per browser,
each reading the shared state at the view rate. Nothing a browser or subscriber does can block
the pump: the state is a bounded ring under a lock held for microseconds, and a browser that
falls behind by more than the ring skips samples (counted as ``view_dropped``).

Security (docs/stream.md): every request's ``Host`` header must name this server (loopback names,
IP literals, the machine's own names or ``allowed_hosts``), so a page on another site that rebinds
its DNS name to 127.0.0.1 is refused; with a ``token`` (required beyond loopback) every request
must carry it (``?token=`` once, then the cookie the page gets); at most ``max_clients``
connections are served at once (503 beyond), and a client idle for ``client_timeout_s`` is dropped.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np

from softphantom.errors import SoftphantomError, UserError
from softphantom.stream.schema import encode, estimate_to_message

STATIC_DIR = Path(__file__).with_name("static")
_STATIC = {"/": ("index.html", "text/html; charset=utf-8"),
           "/static/live.js": ("live.js", "text/javascript; charset=utf-8"),
           "/static/live.css": ("live.css", "text/css; charset=utf-8")}


@dataclass(frozen=True)
class LiveConfig:
    """Options of a live session. Ports 0 pick a free port; ``stream_port=None`` disables the
    network stream. ``listen_host`` is loopback unless set explicitly (both page and stream);
    beyond loopback a ``token`` is required (:func:`is_loopback`). ``allowed_hosts``: extra names
    accepted in the ``Host`` header; ``max_clients``: connections served at once."""

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

    def __post_init__(self) -> None:
        if not is_loopback(self.listen_host) and not self.token:
            raise UserError(f"listen host {self.listen_host!r} is beyond loopback: a token is required")
        if self.max_clients < 1:
            raise UserError(f"max_clients must be >= 1, got {self.max_clients}")


def is_loopback(host: str) -> bool:
    """True for an address or name that only this machine can reach ("" and 0.0.0.0 are every interface).

    >>> [is_loopback(h) for h in ("127.0.0.1", "::1", "localhost", "", "0.0.0.0", "192.168.1.5")]
    [True, True, True, False, False, False]
    """
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _host_names(cfg: LiveConfig) -> set[str]:
    """Names a client may put in the ``Host`` header (lower case, without the port)."""
    names = {"localhost", *(h.lower() for h in cfg.allowed_hosts)}
    if not is_loopback(cfg.listen_host):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        if cfg.listen_host:
            names.add(cfg.listen_host.lower())
    return names


def host_allowed(header: str | None, names: set[str], loopback_only: bool) -> bool:
    """Whether a ``Host`` header names this server: a listed name, or an IP literal (loopback
    only when serving on loopback). DNS rebinding gives the attacker's name: refused.

    >>> host_allowed("127.0.0.1:8765", {"localhost"}, True), host_allowed("evil.example:8765", {"localhost"}, True)
    (True, False)
    """
    if not header:
        return False
    host = header.strip().lower()
    if host.startswith("["):
        host = host[1:].split("]", 1)[0]
    elif host.count(":") == 1:
        host = host.split(":", 1)[0]
    if host in names:
        return True
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return False
    return ip.is_loopback or not loopback_only

_TRACKER_KEYS = ("x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg")


class LiveState:
    """Shared, bounded state between the pump and the page (thread-safe)."""

    def __init__(self, history: int = 20000):
        self._lock = threading.Condition()
        self._hist: deque[dict[str, Any]] = deque(maxlen=history)
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
        self._arrivals: deque[float] = deque(maxlen=4096)
        self._steps: deque[float] = deque(maxlen=1000)
        self.frames_served = 0

    def push(self, msg: dict[str, Any]) -> None:
        with self._lock:
            self._hist.append(msg)
            self.latest = msg
            self.seq = msg["seq"]
            self.skipped_total += int(msg.get("skipped") or 0)
            self._arrivals.append(time.monotonic())
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

    def wait_newer(self, seq: int, timeout_s: float) -> None:
        with self._lock:
            self._lock.wait_for(lambda: self.seq > seq or self.finished, timeout=timeout_s)

    def status(self) -> dict[str, Any]:
        """Rate (Hz, over the last 2 s), step latency (ms, last and p99), counters, health."""
        with self._lock:
            now = time.monotonic()
            recent = [a for a in self._arrivals if now - a <= 2.0]
            rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 2 and recent[-1] > recent[0] else 0.0
            steps = list(self._steps)
            latest = self.latest
            age = now - self._arrivals[-1] if self._arrivals else None
            health = "waiting"
            if latest is not None:
                health = str(latest.get("status", "ok"))
                if not self.finished and age is not None and age > 1.0:
                    health = f"stalled ({age:.1f} s without estimate)"
            if self.error:
                health = f"error: {self.error}"
            return {
                "rate_Hz": round(rate, 2),
                "step_ms": latest.get("step_ms") if latest else None,
                "step_p99_ms": float(np.percentile(steps, 99)) if steps else None,
                "estimates": self.seq + 1,
                "skipped_total": self.skipped_total,
                "view_dropped": self.view_dropped,
                "last_estimate_age_s": None if age is None else round(age, 3),
                "sensor_health": health,
                "qp_status": latest.get("qp_status") if latest else None,
                "cond_W": latest.get("cond_W") if latest else None,
                "surface_max_mm": round(self.surface_max_mm, 3),
                "stream": dict(self.stream),
                "recording": dict(self.recording),
                "finished": self.finished,
            }

    def frame_since(self, seq: int, surface_version: int, max_samples: int = 2000) -> tuple[dict[str, Any], int, int]:
        """The next SSE frame for a client that has seen up to ``seq`` and ``surface_version``."""
        with self._lock:
            new = [m for m in reversed(self._hist) if m["seq"] > seq][:max_samples] if self.seq > seq else []
            new.reverse()
            if new and seq >= 0 and new[0]["seq"] > seq + 1:
                self.view_dropped += new[0]["seq"] - seq - 1
            frame: dict[str, Any] = {"samples": new}
            if self.surface_version != surface_version and self.surface_b64 is not None:
                frame["surface_mm_f32_b64"] = self.surface_b64
            sv = self.surface_version
            last = self.seq
            self.frames_served += 1
        frame["status"] = self.status()
        return frame, last, sv


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
        self._httpd: ThreadingHTTPServer | None = None
        self.publisher = None
        self.recorder = None
        self.error: BaseException | None = None
        geo = getattr(source, "geometry", None)
        self._geometry_json = None if geo is None else geo.to_json()

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> "LiveSession":
        cfg = self.config
        try:
            self._httpd = _make_server(self, cfg)
        except OSError as exc:
            raise UserError(f"cannot serve the live page on {cfg.listen_host}:{cfg.http_port}: {exc.strerror}") from None
        threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.1},
                         name="live-http", daemon=True).start()
        if cfg.stream_port is not None:
            from softphantom.stream.publisher import EstimatePublisher

            self.publisher = EstimatePublisher(port=cfg.stream_port, host=cfg.listen_host)
            self.state.stream = {"enabled": True, "endpoint": self.publisher.endpoint, "sent": 0, "subscribers": 0}
        if cfg.record is not None:
            from softphantom.stream.recording import TOPIC_GEOMETRY, SessionRecorder

            self.recorder = SessionRecorder(cfg.record, metadata={"source": type(self.source).__name__})
            if self._geometry_json is not None:
                self.recorder.write(TOPIC_GEOMETRY, self._geometry_json)
            self.state.recording = {"enabled": True, "path": str(cfg.record), "messages": 0}
        self._pump = threading.Thread(target=self._run_pump, name="live-pump", daemon=True)
        self._pump.start()
        return self

    @property
    def url(self) -> str:
        """The page's address (with ``?token=`` when one is required)."""
        assert self._httpd is not None
        host, port = self._httpd.server_address[:2]
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{port}/" + (f"?token={self.config.token}" if self.config.token else "")

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
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
            self._httpd = None
        if self.publisher is not None:
            self.publisher.close()
            self.publisher = None
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
                for tm in (poll_tracker() or ()) if callable(poll_tracker) else ():
                    if self.recorder is not None:
                        self.recorder.write_tracker(tm)
                    if "x_mm" in tm:
                        tracker = {k: tm[k] for k in _TRACKER_KEYS}
                st.push(msg if tracker is None else {**msg, "tracker": tracker})  # the page only
                now = time.monotonic()
                want_rec = self.recorder is not None and rec_dt is not None and now - last_rec >= rec_dt
                if geo is not None and (now - last_view >= view_dt or want_rec):
                    pos = src.node_positions()
                    if pos is not None:
                        b64 = _set_surface(st, geo, pos)
                        last_view = now
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

    # -- for the HTTP handler ----------------------------------------------------------------
    def state_json(self) -> dict[str, Any]:
        return {"status": self.state.status(), "latest": self.state.latest,
                "has_geometry": self._geometry_json is not None,
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


_COOKIE = "softphantom_live_token"


def _make_server(session: LiveSession, cfg: LiveConfig) -> ThreadingHTTPServer:
    from http.cookies import SimpleCookie
    from urllib.parse import parse_qs

    names = _host_names(cfg)
    loopback_only = is_loopback(cfg.listen_host)

    class Handler(BaseHTTPRequestHandler):
        server_version = "softphantom-live"
        timeout = cfg.client_timeout_s  # a silent or stalled client is dropped, its slot freed

        def log_message(self, *args: Any) -> None:  # quiet
            pass

        def _refuse(self, code: int, why: str) -> None:
            self._send(f"{why}\n".encode(), "text/plain; charset=utf-8", code)

        def _token_ok(self) -> tuple[bool, bool]:
            """(authorised, came in the query: set the cookie)."""
            if not cfg.token:
                return True, False
            given = parse_qs(self.path.partition("?")[2]).get("token", [""])[0]
            if given and hmac.compare_digest(given.encode(), cfg.token.encode()):
                return True, True
            morsel = SimpleCookie(self.headers.get("Cookie", "")).get(_COOKIE)
            ok = morsel is not None and hmac.compare_digest(morsel.value.encode(), cfg.token.encode())
            return ok, False

        def _send(self, body: bytes, ctype: str, code: int = 200, cookie: bool = False) -> None:
            self.send_response(code)
            if cookie:
                self.send_header("Set-Cookie", f"{_COOKIE}={cfg.token}; HttpOnly; SameSite=Strict; Path=/")
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:  # noqa: N802
            path = self.path.split("?", 1)[0]
            try:
                if not host_allowed(self.headers.get("Host"), names, loopback_only):
                    self._refuse(HTTPStatus.FORBIDDEN, "Host not served here (use the printed address)")
                    return
                ok, from_query = self._token_ok()
                if not ok:
                    self._refuse(HTTPStatus.UNAUTHORIZED, "token required (open the printed address)")
                    return
                if path in _STATIC:
                    name, ctype = _STATIC[path]
                    self._send((STATIC_DIR / name).read_bytes(), ctype, cookie=from_query)
                elif path == "/api/state":
                    self._send(json.dumps(session.state_json(), allow_nan=False).encode(), "application/json")
                elif path == "/api/geometry":
                    geo = session._geometry_json
                    self._send(json.dumps(geo).encode(), "application/json", 200 if geo else 404)
                elif path == "/api/events":
                    self._events()
                else:
                    self._send(b"not found\n", "text/plain", HTTPStatus.NOT_FOUND)
            except (BrokenPipeError, ConnectionResetError, TimeoutError):
                pass

        def _events(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            st, period = session.state, 1.0 / session.config.view_rate_Hz
            seq, sv = -1, 0
            while not session._stop.is_set():
                t0 = time.monotonic()
                st.wait_newer(seq, timeout_s=1.0)
                frame, seq, sv = st.frame_since(seq, sv)
                self.wfile.write(b"event: frame\ndata: " + json.dumps(frame, allow_nan=False).encode() + b"\n\n")
                self.wfile.flush()
                if st.finished and not frame["samples"]:
                    time.sleep(1.0)  # keep the page's status fresh after the end, cheaply
                left = period - (time.monotonic() - t0)
                if left > 0:
                    time.sleep(left)

    class Server(ThreadingHTTPServer):
        daemon_threads = True
        allow_reuse_address = True
        address_family = socket.AF_INET6 if ":" in cfg.listen_host else socket.AF_INET
        slots = threading.BoundedSemaphore(cfg.max_clients)

        def process_request(self, request, client_address) -> None:
            if not self.slots.acquire(blocking=False):  # full: answer at once, hold no thread
                try:
                    request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n"
                                    b"Retry-After: 5\r\nConnection: close\r\n\r\n")
                except OSError:
                    pass
                self.shutdown_request(request)
                return
            super().process_request(request, client_address)

        def process_request_thread(self, request, client_address) -> None:
            try:
                super().process_request_thread(request, client_address)
            finally:
                self.slots.release()

    return Server((cfg.listen_host, cfg.http_port), Handler)
