"""The phantom in Foxglove: a live session as Foxglove's well-known messages (docs/stream.md).

Foxglove's 3D panel draws these, in the recording (:class:`~softphantom.stream.SessionRecorder`
writes them beside the JSON channels) and live (``softphantom live --foxglove``, a Foxglove
WebSocket server). Encoded with the message classes of ``foxglove-sdk`` (protobuf, the schemas it
ships), metres and seconds:

- ``/foxglove/surface`` (``foxglove.SceneUpdate``, 10 Hz): entity ``surface``, the deformed outer
  surface as one triangle list coloured per vertex by |u| (viridis, 0 … a round top ≥ 0.4 mm,
  written in a label and in the entity's metadata ``colour_max_mm``; 55 % opaque, as the page);
  entity ``cavities``, one triangle list per cavity wall in its arm's colour (:func:`arm_colour`,
  the arms in the geometry's ``arms`` order); entity
  ``tracker_body``, the rest surface in the frame ``phantom_tracker`` (once a tracker pose came).
- ``/foxglove/overlay`` (``foxglove.SceneUpdate``, every estimate): entity ``force``, the force as
  an arrow ending on the contact point (the deformed ``p_ext`` node), :data:`ARROW_MM_PER_N` mm per
  N clamped to 12 … 60 mm, a sphere at the contact point and a label in N; entity ``targets``, each
  target at rest (grey sphere), moved by its estimated shift (magenta sphere), a line between and a
  label with the shift in mm.
- ``/foxglove/tf`` (``foxglove.FrameTransforms``): the estimated pose of the marker rigid body as
  the frame ``phantom_estimate`` (every estimate) and the tracker's as ``phantom_tracker`` (every
  tracker pose), both children of ``phantom``: the model frame at rest (mm in the JSON, m here;
  y = needle insertion, z = up).

Every message's timestamp is the estimate's publication wall clock (``t_pub_unix_s``), which is
also its log time in the recording. A link event's marker (numbers null) leaves the overlay and the
frames as they were.
"""

from __future__ import annotations

import errno
import logging
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from softphantom.errors import UserError
from softphantom.records.channels import read_layout
from softphantom.records.names import POSE_COLUMNS

TOPIC_FG_SURFACE = "/foxglove/surface"
TOPIC_FG_OVERLAY = "/foxglove/overlay"
TOPIC_FG_TF = "/foxglove/tf"
FRAME_PHANTOM = "phantom"
FRAME_ESTIMATE = "phantom_estimate"
FRAME_TRACKER = "phantom_tracker"
log = logging.getLogger(__name__)

DEFAULT_FOXGLOVE_PORT = 8766
"""Not Foxglove's usual 8765: that is the live page's default port."""

ARROW_MM_PER_N = 10.0
ARROW_MIN_MM, ARROW_MAX_MM = 12.0, 60.0
SURFACE_OPACITY = 0.55
MIN_COLOUR_MAX_MM = 0.4
SURFACE_HZ = 10.0
VIRIDIS = ["#440154", "#482878", "#3e4989", "#31688e", "#26828e", "#1f9e89", "#35b779", "#6ece58", "#b5de2b",
           "#fde725"]
ARM_PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
"""The arms' colours in the sensor order (the page's too), repeating beyond eight arms."""
OTHER_CAVITY = "#8c8c8c"
TRACKER_COLOUR = "#ff6a00"
FORCE_COLOUR = "#e0201b"
TARGET_COLOUR = "#ff2d95"


def _fm():
    """The SDK's message classes (imported on first use: the SDK is a compiled extension)."""
    import foxglove.messages as fm

    return fm


def foxglove_schemas() -> dict[str, Any]:
    """Topic → the SDK's ``Schema`` (``name``, ``encoding`` ``"protobuf"``, ``data``: a
    FileDescriptorSet) of each Foxglove channel."""
    fm = _fm()
    return {TOPIC_FG_SURFACE: fm.SceneUpdate.get_schema(), TOPIC_FG_OVERLAY: fm.SceneUpdate.get_schema(),
            TOPIC_FG_TF: fm.FrameTransforms.get_schema()}


def nice_colour_max_mm(x_mm: float) -> float:
    """The colour scale's top for a largest |u| of ``x_mm``: a round number ≥ 0.4 mm (as the page).

    >>> nice_colour_max_mm(0.0), nice_colour_max_mm(0.9), nice_colour_max_mm(2.5)
    (0.4, 1.0, 3.2)
    """
    if not x_mm > 0:
        return MIN_COLOUR_MAX_MM
    p = 10.0 ** math.floor(math.log10(x_mm))
    m = x_mm / p
    for s in (1, 1.2, 1.6, 2, 2.4, 3.2, 4, 6, 8, 10):
        if m <= s * (1 + 1e-12):
            return max(round(s * p, 12), MIN_COLOUR_MAX_MM)
    return 10 * p


def arm_colour(name: str, arm_names: Sequence[str]) -> str:
    """The colour of cavity ``name`` among the arms ``arm_names`` (a cavity not an arm: grey).

    >>> arms = ("front_zpos", "front_zneg", "back_xpos", "back_xneg", "top")
    >>> [arm_colour(n, arms) for n in ("back_xneg", "top", "urethra")]
    ['#9467bd', '#8c564b', '#8c8c8c']
    """
    arms = list(arm_names)
    return ARM_PALETTE[arms.index(name) % len(ARM_PALETTE)] if name in arms else OTHER_CAVITY


def _rgb(hex_colour: str) -> tuple[float, float, float]:
    v = int(hex_colour[1:], 16)
    return ((v >> 16) & 255) / 255, ((v >> 8) & 255) / 255, (v & 255) / 255


_VIRIDIS_RGB = np.array([_rgb(c) for c in VIRIDIS])


def viridis(t: np.ndarray) -> np.ndarray:
    """(n,) values in [0, 1] (clipped) → (n, 3) RGB in [0, 1], the page's colour map.

    >>> viridis(np.array([0.0, 1.0])).round(3).tolist()
    [[0.267, 0.004, 0.329], [0.992, 0.906, 0.145]]
    """
    x = np.clip(np.asarray(t, float), 0.0, 1.0) * (len(VIRIDIS) - 1)
    return np.stack([np.interp(x, np.arange(len(VIRIDIS)), _VIRIDIS_RGB[:, k]) for k in range(3)], axis=-1)


def _quat_x_to(d: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) turning the +x axis onto the unit vector ``d`` (an arrow's pose)."""
    if d[0] < -1 + 1e-9:
        return 0.0, 0.0, 1.0, 0.0
    q = np.array([0.0, -d[2], d[1], 1.0 + d[0]])
    q /= np.linalg.norm(q)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _pose_values(m: Mapping[str, Any]) -> np.ndarray | None:
    v = [m.get(c) for c in POSE_COLUMNS]
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
        return None
    return np.array(v, float)


@dataclass(frozen=True)
class FoxgloveMessage:
    """One encoded message: its ``topic``, protobuf bytes ``data`` and timestamp ``t_ns``."""

    topic: str
    data: bytes
    t_ns: int


class FoxgloveScene:
    """Build the Foxglove messages of a session from its geometry (the ``/live/geometry`` JSON,
    mm: ``nodes_mm``, ``faces``, ``cavities``, ``targets_mm``, ``p_ext_node``) and its estimate,
    tracker and surface messages. Pure: no I/O; keeps the last surface for the contact point."""

    def __init__(self, geometry_json: Mapping[str, Any] | None):
        fm = _fm()
        self._fm = fm
        g = geometry_json or {}
        self.nodes_m = np.asarray(g.get("nodes_mm", []), float).reshape(-1, 3) * 1e-3
        faces = np.asarray(g.get("faces", []), np.int64).reshape(-1, 3)
        self.outer, inv = np.unique(faces, return_inverse=True)
        self.outer_faces = inv.reshape(-1, 3)  # into self.outer
        self.cavities: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for name, f in (g.get("cavities") or {}).items():
            f = np.asarray(f, np.int64).reshape(-1, 3)
            used, inv = np.unique(f, return_inverse=True)
            self.cavities[name] = (used, inv.reshape(-1, 3))
        self.targets_m = {k: np.asarray(v, float) * 1e-3 for k, v in (g.get("targets_mm") or {}).items()}
        self.arm_names = read_layout(g, "geometry message", sensing=g.get("arms")).sensing if g else ()
        self.p_ext_node = g.get("p_ext_node")
        self.p_ext_m = np.asarray(g.get("p_ext_mm", [0.0, 0.0, 0.0]), float) * 1e-3
        self.positions_m = self.nodes_m.copy()  # the drawn nodes' latest deformed positions
        self.has_geometry = len(self.outer) > 0
        self.tracker_seen = False
        self.last_t_ns = time.time_ns()
        self._identity = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        self._tracker_body = self._triangles(self.nodes_m[self.outer], self.outer_faces,
                                             colour=(*_rgb(TRACKER_COLOUR), 0.45)) if self.has_geometry else None

    # -- helpers ---------------------------------------------------------------------------
    def _ts(self, t_ns: int):
        return self._fm.Timestamp(sec=int(t_ns // 1_000_000_000), nsec=int(t_ns % 1_000_000_000))

    def _pose(self, p: Sequence[float], q: Any = None):
        fm = self._fm
        return fm.Pose(position=fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                       orientation=q if q is not None else self._identity)

    def _colour(self, rgb: Sequence[float], a: float = 1.0):
        return self._fm.Color(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(a))

    def _triangles(self, points_m: np.ndarray, faces: np.ndarray, colour=None, colours: np.ndarray | None = None):
        fm = self._fm
        # float32 positions and 8-bit colours: what a renderer uses; their doubles' zero low bits compress well
        pts = [fm.Point3(x=x, y=y, z=z) for x, y, z in np.asarray(points_m, np.float32).astype(float).tolist()]
        kw: dict[str, Any] = {}
        if colours is not None:
            c8 = np.round(np.asarray(colours, float) * 255).astype(np.float32) / np.float32(255)
            kw["colors"] = [fm.Color(r=r, g=g, b=b, a=a) for r, g, b, a in c8.astype(float).tolist()]
        else:
            kw["color"] = self._colour(colour[:3], colour[3])
        return fm.TriangleListPrimitive(points=pts, indices=np.asarray(faces).ravel().tolist(), **kw)

    def _text(self, p: Sequence[float], text: str, rgb=(0.1, 0.1, 0.1), size: float = 13.0):
        return self._fm.TextPrimitive(pose=self._pose(p), billboard=True, font_size=size, scale_invariant=True,
                                      color=self._colour(rgb), text=text)

    def _sphere(self, p: Sequence[float], d_m: float, rgb, a: float = 1.0):
        fm = self._fm
        return fm.SpherePrimitive(pose=self._pose(p), size=fm.Vector3(x=d_m, y=d_m, z=d_m), color=self._colour(rgb, a))

    # -- the messages ----------------------------------------------------------------------
    def surface(self, positions_m: np.ndarray, t_ns: int | None = None) -> FoxgloveMessage | None:
        """The ``/foxglove/surface`` message for the drawn nodes' deformed positions ``(n, 3)`` m."""
        if not self.has_geometry:
            return None
        fm = self._fm
        t_ns = self.last_t_ns if t_ns is None else int(t_ns)
        pos = np.asarray(positions_m, float).reshape(-1, 3)
        if pos.shape != self.nodes_m.shape:
            raise ValueError(f"surface positions: expected {self.nodes_m.shape}, got {pos.shape}")
        self.positions_m = pos
        ts = self._ts(t_ns)
        outer = pos[self.outer]
        u_mm = np.linalg.norm(outer - self.nodes_m[self.outer], axis=1) * 1e3
        top = nice_colour_max_mm(float(u_mm.max(initial=0.0)))
        rgba = np.concatenate([viridis(u_mm / top), np.full((len(u_mm), 1), SURFACE_OPACITY)], axis=1)
        hi = outer.max(axis=0)
        label = self._text([0.5 * (outer[:, 0].min() + hi[0]), 0.5 * (outer[:, 1].min() + hi[1]), hi[2] + 0.008],
                           f"|u| 0 (violet) … {top:g} mm (yellow); max {u_mm.max(initial=0.0):.2f} mm")
        ents = [fm.SceneEntity(timestamp=ts, frame_id=FRAME_PHANTOM, id="surface", frame_locked=True,
                               metadata=[fm.KeyValuePair(key="colour_max_mm", value=f"{top:g}"),
                                         fm.KeyValuePair(key="u_max_mm", value=f"{u_mm.max(initial=0.0):.4f}")],
                               triangles=[self._triangles(outer, self.outer_faces, colours=rgba)], texts=[label])]
        if self.cavities:
            tris = [self._triangles(pos[used], f, colour=(*_rgb(arm_colour(name, self.arm_names)), 1.0))
                    for name, (used, f) in self.cavities.items()]
            ents.append(fm.SceneEntity(timestamp=ts, frame_id=FRAME_PHANTOM, id="cavities", frame_locked=True,
                                       triangles=tris))
        if self.tracker_seen and self._tracker_body is not None:
            ents.append(fm.SceneEntity(timestamp=ts, frame_id=FRAME_TRACKER, id="tracker_body", frame_locked=True,
                                       triangles=[self._tracker_body]))
        return FoxgloveMessage(TOPIC_FG_SURFACE, fm.SceneUpdate(entities=ents).encode(), t_ns)

    def estimate(self, msg: Mapping[str, Any]) -> list[FoxgloveMessage]:
        """The ``/foxglove/tf`` and ``/foxglove/overlay`` messages of one estimate message (none for a
        link event's marker)."""
        fm = self._fm
        t_pub = msg.get("t_pub_unix_s")
        t_ns = int(round(float(t_pub) * 1e9)) if isinstance(t_pub, (int, float)) else time.time_ns()
        self.last_t_ns = t_ns
        pose = _pose_values(msg)
        f = [msg.get(k) for k in ("force_x_N", "force_y_N", "force_z_N")]
        if pose is None or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in f):
            return []
        out = [self._transform(FRAME_ESTIMATE, pose, t_ns)]
        if not self.has_geometry:
            return out
        ts = self._ts(t_ns)
        F = np.array(f, float)
        Fn = float(np.linalg.norm(F))
        tip = self.positions_m[self.p_ext_node] if self.p_ext_node is not None else self.p_ext_m
        force = fm.SceneEntity(timestamp=ts, frame_id=FRAME_PHANTOM, id="force", frame_locked=True,
                               spheres=[self._sphere(tip, 0.0036, _rgb(FORCE_COLOUR))])
        if Fn > 1e-3:
            L = min(ARROW_MAX_MM, max(ARROW_MIN_MM, ARROW_MM_PER_N * Fn)) * 1e-3
            d = F / Fn
            head = min(0.008, 0.35 * L)
            tail = tip - d * L
            qx, qy, qz, qw = _quat_x_to(d)
            arrow = fm.ArrowPrimitive(pose=self._pose(tail, fm.Quaternion(x=qx, y=qy, z=qz, w=qw)),
                                      shaft_length=L - head, shaft_diameter=0.0012, head_length=head,
                                      head_diameter=0.004, color=self._colour(_rgb(FORCE_COLOUR)))
            force = fm.SceneEntity(timestamp=ts, frame_id=FRAME_PHANTOM, id="force", frame_locked=True,
                                   spheres=[self._sphere(tip, 0.0036, _rgb(FORCE_COLOUR))], arrows=[arrow],
                                   texts=[self._text(tail, f"{Fn:.2f} N", _rgb(FORCE_COLOUR))])
        ents = [force]
        if self.targets_m:
            spheres, ends, texts = [], [], []
            for name, rest in self.targets_m.items():
                dv = [msg.get(f"{name}_d{a}_mm") for a in "xyz"]
                dv = np.array([x if isinstance(x, (int, float)) and math.isfinite(x) else 0.0 for x in dv]) * 1e-3
                now = rest + dv
                spheres += [self._sphere(rest, 0.0026, (0.13, 0.13, 0.13), 0.5),
                            self._sphere(now, 0.0028, _rgb(TARGET_COLOUR))]
                ends += [rest, now]
                texts.append(self._text(now + 0.0025, f"{name} {np.linalg.norm(dv) * 1e3:.2f} mm"))
            line = fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineList, pose=self._pose((0, 0, 0)),
                                    thickness=2.0, scale_invariant=True,
                                    points=[fm.Point3(x=p[0], y=p[1], z=p[2]) for p in np.array(ends).tolist()],
                                    color=self._colour(_rgb(TARGET_COLOUR)))
            ents.append(fm.SceneEntity(timestamp=ts, frame_id=FRAME_PHANTOM, id="targets", frame_locked=True,
                                       spheres=spheres, lines=[line], texts=texts))
        out.append(FoxgloveMessage(TOPIC_FG_OVERLAY, fm.SceneUpdate(entities=ents).encode(), t_ns))
        return out

    def tracker(self, msg: Mapping[str, Any], t_ns: int | None = None) -> list[FoxgloveMessage]:
        """The ``/foxglove/tf`` message of a ``/tracker`` message (none for a lost frame)."""
        pose = _pose_values(msg)
        if pose is None or msg.get("valid") is False:
            return []
        self.tracker_seen = True
        return [self._transform(FRAME_TRACKER, pose, time.time_ns() if t_ns is None else int(t_ns))]

    def _transform(self, child: str, pose: np.ndarray, t_ns: int) -> FoxgloveMessage:
        from softphantom.pose.rotations import quat_from_ypr

        fm = self._fm
        q = quat_from_ypr(np.radians(pose[3:6]))
        tf = fm.FrameTransform(timestamp=self._ts(t_ns), parent_frame_id=FRAME_PHANTOM, child_frame_id=child,
                               translation=fm.Vector3(x=pose[0] * 1e-3, y=pose[1] * 1e-3, z=pose[2] * 1e-3),
                               rotation=fm.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
        return FoxgloveMessage(TOPIC_FG_TF, fm.FrameTransforms(transforms=[tf]).encode(), t_ns)


@dataclass(frozen=True)
class Handshake:
    """A client's WebSocket opening request, as :class:`HandshakeGate` hands it to its check:
    ``peer`` its address, ``target`` the request target (path and query), ``headers`` by lower-case name."""

    peer: str
    target: str
    headers: Mapping[str, str]


Check = Callable[[Handshake], "tuple[int, str] | None"]
"""A handshake's refusal (HTTP status, one line of text), or None to let it through."""

MAX_HANDSHAKE_BYTES = 16384
HANDSHAKE_TIMEOUT_S = 10.0


class _QuietDisconnects(logging.Filter):
    """The SDK logs a client that drops without the closing handshake (a closed tab, a reset
    connection) as an error, on its receiving side or, when a message was on its way, its sending
    side: it is routine, so it goes to the debug level."""

    DROPPED = ("Connection reset by peer", "Broken pipe")

    def filter(self, record: logging.LogRecord) -> bool:
        msg = str(record.msg)
        if record.levelno > logging.DEBUG and (msg.startswith("Error receiving from client") or (
                msg.startswith("Error sending message to client") and any(d in msg for d in self.DROPPED))):
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
            return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)
        return True


def _quiet_disconnects() -> None:
    lg = logging.getLogger("foxglove.websocket.connected_client.poller")
    if not any(isinstance(f, _QuietDisconnects) for f in lg.filters):
        lg.addFilter(_QuietDisconnects())


class HandshakeGate:
    """A TCP front for a WebSocket server that cannot vet its clients (the SDK's accepts every
    opening request): listens on ``host:port``, reads each client's opening request, asks
    ``check`` (:data:`Check`) and answers its refusal itself (``HTTP status``, then closes), or
    hands the request and the rest of the connection on to ``backend`` (a loopback port), both
    ways, byte for byte. Runs its own event loop in a thread; :meth:`close` stops it."""

    def __init__(self, host: str, port: int, backend: tuple[str, int], check: Check):
        import asyncio
        import threading

        self._check, self._backend = check, backend
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._server = None
        self._thread = threading.Thread(target=self._run, args=(host, int(port)), name="foxglove-gate", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error
        self.port = int(self._server.sockets[0].getsockname()[1])

    def _run(self, host: str, port: int) -> None:
        import asyncio

        asyncio.set_event_loop(self._loop)
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(self._serve, host or None, port, limit=MAX_HANDSHAKE_BYTES))
        except BaseException as exc:  # a port in use: raised in the caller
            self._error = exc
            self._ready.set()
            self._loop.close()
            return
        self._ready.set()
        try:
            self._loop.run_forever()
        finally:  # the connections still open end here, each closing its sockets
            tasks = asyncio.all_tasks(self._loop)
            for task in tasks:
                task.cancel()
            self._loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            self._loop.run_until_complete(self._loop.shutdown_asyncgens())
            self._loop.close()

    async def _serve(self, reader, writer) -> None:
        import asyncio

        peer = writer.get_extra_info("peername") or ("?", 0)
        back = None
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANDSHAKE_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError, ValueError):
                return  # not a complete request within the limits: dropped
            lines = head.decode("latin-1").split("\r\n")
            parts = lines[0].split(" ")
            headers: dict[str, str] = {}
            for line in lines[1:]:
                name, colon, value = line.partition(":")
                if colon:
                    headers.setdefault(name.strip().lower(), value.strip())
            refusal = self._check(Handshake(str(peer[0]), parts[1] if len(parts) > 1 else "", headers))
            if refusal is not None:
                status, text = refusal
                body = (text + "\n").encode()
                writer.write(f"HTTP/1.1 {status} {_REASONS.get(status, 'Refused')}\r\n"
                             f"Content-Type: text/plain; charset=utf-8\r\nContent-Length: {len(body)}\r\n"
                             "Connection: close\r\n\r\n".encode() + body)
                await writer.drain()
                log.debug("Foxglove: refused %s (%s %s)", peer[0], status, text)
                return
            back = await asyncio.open_connection(*self._backend)
            back[1].write(head)
            await asyncio.gather(_pipe(reader, back[1]), _pipe(back[0], writer))
        except (ConnectionError, OSError) as exc:
            log.debug("Foxglove: client %s: %s", peer[0], exc)
        except asyncio.CancelledError:  # the gate closing: the connection ends here (asyncio's stream
            pass                        # callback would log a cancelled task as an error)
        finally:
            for w in (writer, None if back is None else back[1]):
                if w is not None:
                    w.close()

    def close(self) -> None:
        if self._loop.is_closed():
            return

        def stop() -> None:
            if self._server is not None:
                self._server.close()
            self._loop.stop()

        self._loop.call_soon_threadsafe(stop)
        self._thread.join(5.0)


_REASONS = {400: "Bad Request", 401: "Unauthorized", 403: "Forbidden"}


async def _pipe(reader, writer) -> None:
    """Copy ``reader`` into ``writer`` until either ends (then both are closed)."""
    try:
        while data := await reader.read(65536):
            writer.write(data)
            await writer.drain()
    except (ConnectionError, OSError):
        pass
    finally:
        writer.close()


class FoxgloveServer:
    """Foxglove's WebSocket server (``foxglove-sdk``) on ``host:port`` (``port=0``: any free one),
    advertising the Foxglove channels and the JSON ``/estimate`` and ``/tracker`` channels.
    ``check`` (:data:`Check`) vets each client's opening request first: the SDK then serves on a
    private loopback port behind a :class:`HandshakeGate` (the live session's rules:
    :func:`softphantom.viz.live.security.websocket_check`). ``token``: shown in :attr:`url`.

    A port in use is a :class:`~softphantom.errors.UserError`. Never blocks the caller: the SDK
    queues each client's messages (``backlog`` at most; a slow client loses its oldest). A client
    that drops is logged at the debug level."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_FOXGLOVE_PORT, backlog: int = 1024,
                 check: Check | None = None, token: str | None = None):
        import foxglove

        from softphantom.stream.schema import TRACKER_JSON_SCHEMA
        from softphantom.stream.schema import ESTIMATE_JSON_SCHEMA

        _quiet_disconnects()
        self._ctx = foxglove.Context()
        self._gate = None
        self._closed = False
        self.token = token
        try:
            self._server = foxglove.start_server(name="softphantom", host="127.0.0.1" if check else host,
                                                 port=0 if check else int(port), context=self._ctx,
                                                 message_backlog_size=int(backlog))
        except RuntimeError as exc:
            why = "the port is in use" if "in use" in str(exc) else str(exc)
            raise UserError(f"cannot serve Foxglove on {host}:{port}: {why} (--foxglove-port)") from None
        if check is not None:
            try:
                self._gate = HandshakeGate(host, int(port), ("127.0.0.1", int(self._server.port)), check)
            except OSError as exc:
                self._server.stop()
                why = "the port is in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
                raise UserError(f"cannot serve Foxglove on {host}:{port}: {why} (--foxglove-port)") from None
        self.host, self.port = host, int(self._gate.port if self._gate else self._server.port)
        self._channels = {t: foxglove.Channel(t, schema=s, message_encoding="protobuf", context=self._ctx)
                          for t, s in foxglove_schemas().items()}
        self._channels["/estimate"] = foxglove.Channel("/estimate", schema=ESTIMATE_JSON_SCHEMA, context=self._ctx)
        self._later = {"/tracker": TRACKER_JSON_SCHEMA}  # advertised with its first message: not every session has one
        self.sent = 0

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}" + (f"/?token={self.token}" if self.token else "")

    def watched(self, topic: str) -> bool:
        """True if a client subscribes to ``topic`` (skip building what nobody watches)."""
        return topic in self._channels and self._channels[topic].has_sinks()

    def log(self, topic: str, data: bytes, t_ns: int) -> None:
        if topic not in self._channels:
            import foxglove

            self._channels[topic] = foxglove.Channel(topic, schema=self._later[topic], context=self._ctx)
        self._channels[topic].log(data, log_time=int(t_ns))
        self.sent += 1

    def close(self) -> None:
        """Stop serving (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._gate is not None:
            self._gate.close()
        self._server.stop()
        for ch in self._channels.values():
            ch.close()


class FoxgloveBridge:
    """Feed a :class:`FoxgloveScene`'s messages to a recorder and/or a :class:`FoxgloveServer`.

    Called by the live pump once per estimate (:meth:`estimate`), tracker pose (:meth:`tracker`) and
    surface update (:meth:`surface`, at most :data:`SURFACE_HZ`). ``node_index``: the drawn nodes'
    model node ids, to pick them out of all model nodes' positions."""

    def __init__(self, scene: FoxgloveScene, recorder: Any = None, server: FoxgloveServer | None = None,
                 node_index: np.ndarray | None = None, surface_Hz: float = SURFACE_HZ):
        self.scene, self.recorder, self.server = scene, recorder, server
        self._node_index = None if node_index is None else np.asarray(node_index)
        self._surface_dt = 1.0 / surface_Hz
        self._last_surface = -1e9

    def _emit(self, msgs: Sequence[FoxgloveMessage]) -> None:
        for m in msgs:
            if self.recorder is not None:
                self.recorder.write(m.topic, m.data, log_time_ns=m.t_ns)
            if self.server is not None:
                self.server.log(m.topic, m.data, m.t_ns)

    def _wanted(self, topic: str) -> bool:
        return self.recorder is not None or (self.server is not None and self.server.watched(topic))

    def estimate(self, msg: Mapping[str, Any], data: bytes | None = None) -> None:
        """One estimate message (``data``: its JSON, sent on the live ``/estimate`` channel)."""
        if self._wanted(TOPIC_FG_OVERLAY) or self._wanted(TOPIC_FG_TF):
            self._emit(self.scene.estimate(msg))
        else:  # nobody watches: only the clock the next surface is stamped with
            t_pub = msg.get("t_pub_unix_s")
            self.scene.last_t_ns = int(round(float(t_pub) * 1e9)) if isinstance(t_pub, (int, float)) else time.time_ns()
        if self.server is not None and data is not None:
            self.server.log("/estimate", data, self.scene.last_t_ns)

    def tracker(self, msg: Mapping[str, Any]) -> None:
        self._emit(self.scene.tracker(msg, time.time_ns()))
        if self.server is not None:
            from softphantom.stream.schema import encode

            self.server.log("/tracker", encode(msg), time.time_ns())

    def surface(self, positions_m: np.ndarray) -> None:
        """The model's (or the drawn nodes') deformed positions, m; sent at most ``surface_Hz``."""
        now = time.monotonic()
        if now - self._last_surface < self._surface_dt or not self._wanted(TOPIC_FG_SURFACE):
            return
        pos = np.asarray(positions_m)
        if self._node_index is not None and len(pos) != len(self.scene.nodes_m):
            pos = pos[self._node_index]
        m = self.scene.surface(pos)
        if m is not None:
            self._last_surface = now
            self._emit([m])

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
            self.server = None
