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
from typing import Any

import numpy as np

from softphantom.errors import SoftphantomError
from softphantom.records.names import POSE_COLUMNS as _TRACKER_KEYS
from softphantom.stream.schema import encode, estimate_to_message
from softphantom.viz.live.state import OUTAGE_EVENTS, LiveConfig, LiveState

__all__ = ["OUTAGE_EVENTS", "LiveConfig", "LiveSession", "LiveState"]


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
        # the phantom's channels: the page's cavity plot, the recording's schemas and metadata, the
        # sensor messages' keys (the page plots the pressures unless they are the BIP's urethra)
        self.layout = getattr(source, "layout", None) or getattr(geo, "layout", None)
        if self.layout is None:
            raise TypeError(f"live source {type(source).__name__}: no layout and no geometry to take it from")
        self.arm_names, self.cavity_names = self.layout.sensing, self.layout.actuated
        self.geometry_json = None if geo is None else {**geo.to_json(), "arms": list(self.arm_names),
                                                       **self.layout.to_meta()}
        shows = getattr(source, "surface_shows", None)  # what the surface is, when not the estimator's field
        if self.geometry_json is not None and shows:
            self.geometry_json["surface_shows"] = str(shows)

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> "LiveSession":
        from softphantom.viz.live.web import WebServer

        cfg = self.config
        fox_server = None
        if cfg.foxglove_port is not None:  # first: a port in use stops the session before anything started
            from softphantom.stream.foxglove import FoxgloveServer
            from softphantom.viz.live.security import websocket_check

            # the page's rules (Host, Origin; the token beyond loopback) vet each client first
            fox_server = FoxgloveServer(cfg.listen_host, cfg.foxglove_port, token=cfg.token,
                                        check=websocket_check(cfg.listen_host, cfg.allowed_hosts, cfg.token))
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

            self.recorder = SessionRecorder(cfg.record, metadata={"source": type(self.source).__name__},
                                            layout=self.layout)
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
        """``ws://host:port`` of the Foxglove server (``/?token=`` when one is required), if one runs."""
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
                        self.recorder.write_sensors(measurement_to_message(m, self.layout))
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
                "has_geometry": self.geometry_json is not None, "arms": list(self.arm_names),
                **({} if self.cavity_names == ("urethra",) else {"cavities": list(self.cavity_names)}),
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
