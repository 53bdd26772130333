"""A live NatNet client: connect to Motive (or the virtual phantom's server), receive its frames.

The client sends ``NAT_CONNECT`` from its command socket to the server's command port (1510) and
waits for the server-info reply (which says the NatNet version, the clock rate and whether data
come by multicast), then asks for the model definitions. Frames arrive on the data port (1511): by
multicast (group 239.255.42.99 joined on ``local``) or by unicast; a unicast server may also send
them to the command socket, so both are read. In unicast the client sends a keep-alive every
second. When no frame arrives for ``reconnect_s`` the client connects again (Motive restarted, a
cable pulled) and counts it; gaps in the frame numbers are counted as lost frames. Closing sends
``NAT_DISCONNECT``.

The first frame is kept in the stats: when it already carries the recording flag on a frame number
above 1, the client joined a take under way (Motive recording, or a running take of
``virtual serve --natnet``): :attr:`ClientStats.joined_mid_take`.
"""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from softphantom.errors import UserError
from softphantom.tracking.natnet import (
    COMMAND_PORT,
    DATA_PORT,
    MULTICAST_GROUP,
    NAT_CONNECT,
    NAT_DISCONNECT,
    NAT_FRAMEOFDATA,
    NAT_KEEPALIVE,
    NAT_MODELDEF,
    NAT_REQUEST_MODELDEF,
    NAT_SERVERINFO,
    Frame,
    ModelDefs,
    NatNetError,
    ServerInfo,
    decode_packet,
    encode_request,
)


def _big_buffer(s: socket.socket, size: int = 4 << 20) -> None:
    """A receive buffer for a few seconds of frames, so a busy moment on this machine loses none."""
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
    except OSError:
        pass


@dataclass(frozen=True)
class NatNetConfig:
    """Where the server is and how data come: ``multicast`` None = as the server info says."""

    server: str = "127.0.0.1"
    local: str = "0.0.0.0"
    command_port: int = COMMAND_PORT
    data_port: int = DATA_PORT
    multicast: bool | None = None
    multicast_group: str = MULTICAST_GROUP
    connect_timeout_s: float = 3.0
    reconnect_s: float = 2.0


@dataclass
class ClientStats:
    """Counters of a session: frames received, lost (gaps in the frame numbers), duplicates,
    undecodable packets, reconnections; the first frame's number, timestamp and recording flag."""

    frames: int = 0
    lost: int = 0
    duplicates: int = 0
    bad_packets: int = 0
    reconnects: int = 0
    last_frame: int | None = None
    last_error: str = ""
    started: float = field(default_factory=time.monotonic)
    first_frame: int | None = None
    first_timestamp_s: float | None = None
    first_recording: bool = False

    @property
    def joined_mid_take(self) -> bool:
        """The first frame came from a take being recorded, and was not its first."""
        return self.first_recording and (self.first_frame or 0) > 1


class NatNetClient:
    """``with NatNetClient(cfg) as c: for t_recv, frame in c.frames(stop): ...``"""

    def __init__(self, config: NatNetConfig = NatNetConfig()):
        self.config = config
        self.info: ServerInfo | None = None
        self.models: ModelDefs | None = None
        self.stats = ClientStats()
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._last_keepalive = 0.0
        self._early: list[tuple[float, Frame]] = []  # frames that came while connecting

    # -- sockets -----------------------------------------------------------------------------
    def _open_command(self) -> None:
        cfg = self.config
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        _big_buffer(s)
        try:
            s.bind((cfg.local if cfg.local != "0.0.0.0" else "", 0))
        except OSError as exc:
            s.close()
            raise UserError(f"--local-ip {cfg.local}: cannot bind the command socket ({exc.strerror})") from None
        s.setblocking(False)
        self._cmd = s

    def _open_data(self, multicast: bool) -> None:
        cfg = self.config
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        _big_buffer(s)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        try:
            s.bind(("", cfg.data_port))
            if multicast:
                iface = socket.inet_aton(cfg.local if cfg.local != "0.0.0.0" else "0.0.0.0")
                mreq = socket.inet_aton(cfg.multicast_group) + iface
                s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        except OSError as exc:
            s.close()
            raise UserError(f"data port {cfg.data_port}: cannot listen ({exc.strerror})"
                            + (f" or join {cfg.multicast_group}" if multicast else "")) from None
        s.setblocking(False)
        self._data = s

    def _send(self, msg_id: int) -> None:
        try:
            self._cmd.sendto(encode_request(msg_id, "Ping" if msg_id == NAT_CONNECT else ""),
                             (self.config.server, self.config.command_port))
        except OSError as exc:
            self.stats.last_error = f"send to {self.config.server}:{self.config.command_port}: {exc.strerror}"

    def connect(self) -> ServerInfo:
        """Connect (server info, then the model definitions); UserError when nobody answers."""
        if self._cmd is None:
            self._open_command()
        deadline = time.monotonic() + self.config.connect_timeout_s
        next_ping = 0.0
        while time.monotonic() < deadline:
            if time.monotonic() >= next_ping:
                self._send(NAT_CONNECT)
                next_ping = time.monotonic() + 0.5
            self._poll_command(0.1)
            if self.info is not None:
                break
        if self.info is None:
            raise UserError(
                f"no NatNet server answered at {self.config.server}:{self.config.command_port} within"
                f" {self.config.connect_timeout_s:g} s (is Motive streaming, with this address and command port?)"
                + (f"; {self.stats.last_error}" if self.stats.last_error else "")
            )
        if self._data is None:
            mc = self.info.multicast if self.config.multicast is None else self.config.multicast
            self._open_data(bool(mc))
        self._send(NAT_REQUEST_MODELDEF)
        return self.info

    def _poll_command(self, timeout_s: float) -> None:
        """Handle what the command socket has (server info, model definitions); keep early frames."""
        for _, data in self._receive(timeout_s, command_only=True):
            f = self._handle(data)
            if f is not None and self.info is not None:
                self._early.append((time.time(), f))

    def wait_for_models(self, timeout_s: float) -> ModelDefs | None:
        """The model definitions, waiting up to ``timeout_s`` for the reply."""
        deadline = time.monotonic() + timeout_s
        while self.models is None and time.monotonic() < deadline:
            self._poll_command(0.1)
        return self.models

    def choose_body(self, body: str | None, wait_s: float = 1.0) -> tuple[int, str]:
        """The rigid body's id and name, from the model definitions (or a numeric ``body``)."""
        defs = self.wait_for_models(wait_s)
        bodies = {b.name: b.id for b in defs.rigid_bodies} if defs is not None else {}
        have = ", ".join(f"{n} (id {i})" for n, i in bodies.items()) or "none defined"
        where = f"NatNet server {self.config.server}"
        if body is None:
            if len(bodies) == 1:
                (name,) = bodies
                return bodies[name], name
            raise UserError(f"{where}: {len(bodies)} rigid bodies, choose one with --body: {have}")
        if body in bodies:
            return bodies[body], body
        if body.isdigit():
            return int(body), body
        raise UserError(f"{where}: no rigid body {body!r}; it streams: {have}")

    def _receive(self, timeout_s: float, command_only: bool = False):
        socks = [s for s in (self._cmd, None if command_only else self._data) if s is not None]
        r, _, _ = select.select(socks, [], [], timeout_s)
        for s in r:
            while True:
                try:
                    data, _ = s.recvfrom(65536)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    break
                yield s, data

    def _handle(self, data: bytes):
        version = self.info.version if self.info is not None else None
        try:
            msg_id, obj = decode_packet(data, version, "NatNet packet")
        except NatNetError as exc:
            self.stats.bad_packets += 1
            self.stats.last_error = str(exc)
            return None
        if msg_id == NAT_SERVERINFO:
            self.info = obj
        elif msg_id == NAT_MODELDEF:
            self.models = obj
        elif msg_id == NAT_FRAMEOFDATA:
            return obj
        return None

    # -- the stream --------------------------------------------------------------------------
    def frames(self, stop: Callable[[], bool] | None = None) -> Iterator[tuple[float, Frame]]:
        """Yield ``(receive time s since the epoch, Frame)`` until ``stop()``; reconnects by itself."""
        if self.info is None:
            self.connect()
        last_rx = time.monotonic()
        resync = False
        while stop is None or not stop():
            now = time.monotonic()
            unicast = not (self.info.multicast if self.config.multicast is None else self.config.multicast)
            if unicast and now - self._last_keepalive >= 1.0:
                self._send(NAT_KEEPALIVE)
                self._last_keepalive = now
            if now - last_rx > self.config.reconnect_s:
                self.stats.reconnects += 1
                self._send(NAT_CONNECT)
                last_rx = now
                resync = True  # the next frame may come from a restarted server
            got = list(self._early) + [
                (time.time(), self._handle(data)) for _, data in self._receive(0.1)]
            self._early.clear()
            for t_rx, f in got:
                if f is None:
                    continue
                last_rx = time.monotonic()
                last = self.stats.last_frame
                if resync and last is not None and f.frame_number < last:
                    last = None  # a restarted server counts from its start again
                resync = False
                if last is not None:
                    if f.frame_number == last:  # the same frame twice (multicast and unicast)
                        self.stats.duplicates += 1
                        continue
                    if last - 1000 < f.frame_number < last:  # a late packet; far lower: the server restarted
                        continue
                    if f.frame_number > last + 1:
                        self.stats.lost += f.frame_number - last - 1
                self.stats.last_frame = f.frame_number
                if self.stats.frames == 0:
                    self.stats.first_frame, self.stats.first_timestamp_s = f.frame_number, f.timestamp_s
                    self.stats.first_recording = f.is_recording
                self.stats.frames += 1
                yield t_rx, f

    def close(self) -> None:
        if self._cmd is not None and self.info is not None:
            self._send(NAT_DISCONNECT)  # the server stops sending to this client at once
        for s in (self._cmd, self._data):
            if s is not None:
                s.close()
        self._cmd = self._data = None

    def __enter__(self) -> "NatNetClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
