"""The virtual tracker served as a NatNet server, so ``softphantom track --natnet 127.0.0.1`` (or any
NatNet client) sees Motive streaming the phantom's marker body.

It answers on its command port as Motive does: ``NAT_CONNECT`` → server info (NatNet 3.0 or 4.1,
a 10 MHz high-resolution clock), ``NAT_REQUEST_MODELDEF`` → the rigid body and its marker set,
``NAT_KEEPALIVE`` → keeps the client. Frames go by unicast to every client that connected (to the
address it connected from) or, if asked, by multicast to the group on the data port.

The take (frame 1 = the stream's first frame) starts when a client connects and no other client is
connected, so each recording run sees the whole scenario; frames then follow the tracker stream in
real time (times ``speed``); after the scenario the last pose keeps streaming (a tracker does not
stop) unless ``once``. While the take runs, every frame carries the recording flag (as Motive's
while it records a take), so a client that joins a running take sees it set on a frame number
above 1 (``NatNetClient.stats.joined_mid_take``) and can say it misses the start. A client leaves by
``NAT_DISCONNECT`` or, in unicast, by 10 s without a keep-alive; when none is left the take stops
and the next client starts it again. Lost frames of the stream are sent with the body's
tracking-valid flag cleared, as Motive does. Loopback only unless a host is given.
"""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from softphantom.tracking.natnet import (
    COMMAND_PORT,
    DATA_PORT,
    MULTICAST_GROUP,
    NAT_CONNECT,
    NAT_DISCONNECT,
    NAT_KEEPALIVE,
    NAT_REQUEST_MODELDEF,
    Frame,
    LabeledMarker,
    ModelDefs,
    RigidBody,
    RigidBodyDef,
    ServerInfo,
    encode_frame,
    encode_model_defs,
    encode_server_info,
    split_packet,
)

CLOCK_HZ = 10_000_000
CLIENT_TIMEOUT_S = 10.0
BODY_ID = 1
RECORDING = 0x01  # FrameOfData params bit 0: Motive is recording (here: the take is running)


def model_defs(stream, marker_offsets: np.ndarray, marker_names=()) -> ModelDefs:
    """The rigid body (id 1, named as the stream's body) with its markers' offsets from the pivot (m)."""
    body = stream.config.body
    k = len(marker_offsets)
    names = tuple(marker_names) or tuple(f"Marker{i + 1}" for i in range(k))
    rb = RigidBodyDef(BODY_ID, body, -1, (0.0, 0.0, 0.0), tuple(tuple(map(float, m)) for m in marker_offsets),
                      tuple(range(1, k + 1)), names)
    return ModelDefs({body: names}, (rb,))


def stream_frame(stream, i: int, frame_number: int, params: int = RECORDING) -> Frame:
    """Frame ``i`` of a :class:`~softphantom.virtual.tracker.TrackerStream` as Motive would send it
    while recording the take."""
    ok = bool(stream.valid[i])
    pos = tuple(map(float, stream.position[i])) if ok else (0.0, 0.0, 0.0)
    quat = tuple(map(float, stream.quat_xyzw[i])) if ok else (0.0, 0.0, 0.0, 1.0)
    t = float(stream.t_take[i])
    mid = int(round(t * CLOCK_HZ))
    lat = int(round(stream.latency_s * CLOCK_HZ))
    labeled = () if not ok else tuple(
        LabeledMarker((BODY_ID << 16) | (j + 1), tuple(map(float, m)), 0.012, 0x0A, 0.0)
        for j, m in enumerate(stream.markers[i]))
    return Frame(frame_number, rigid_bodies=(RigidBody(BODY_ID, pos, quat, 0.0002 if ok else 0.0, ok),),
                 labeled_markers=labeled, timestamp_s=t, stamp_mid_exposure=mid,
                 stamp_data_received=mid + lat // 2, stamp_transmit=mid + lat, params=params)


def serve_natnet(stream, marker_offsets, *, marker_names=(), host: str = "127.0.0.1",
                 command_port: int = COMMAND_PORT, data_port: int = DATA_PORT, multicast: bool = False,
                 multicast_group: str = MULTICAST_GROUP, version=(4, 1), speed: float = 1.0, once: bool = False,
                 stop: Callable[[], bool] | None = None, on_ready: Callable[[int], None] | None = None,
                 on_event: Callable[[str], None] | None = None) -> dict:
    """Serve ``stream`` until ``stop()`` (or the end with ``once``); returns counters.
    ``on_ready(port)`` is called with the command port once it listens (port 0 = any free port);
    ``on_event(text)`` with a line for each take started, client joining a running take, client left."""
    version = tuple(version)[:2]
    cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    cmd.bind((host, command_port))
    cmd.setblocking(False)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if multicast:
        out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1 if host not in ("127.0.0.1", "localhost") else 0)
        out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        out.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(host))
    info = ServerInfo("Motive", (3, 1, 0, 0), version + (0, 0), CLOCK_HZ, data_port, multicast,
                      multicast_group if multicast else "0.0.0.0")
    info_pkt = encode_server_info(info)
    defs_pkt = encode_model_defs(model_defs(stream, marker_offsets, marker_names), version)
    clients: dict[tuple, float] = {}
    stats = {"frames_sent": 0, "clients": 0, "requests": 0, "takes": 0, "command_port": cmd.getsockname()[1]}
    event = on_event or (lambda text: None)
    if on_ready is not None:
        on_ready(stats["command_port"])
    t_take = np.asarray(stream.t_take)
    n = len(t_take)
    t0 = None
    i = 0
    try:
        while stop is None or not stop():
            now = time.monotonic()
            wait = 0.05
            if t0 is not None:
                due = t0 + (t_take[min(i, n - 1)] - t_take[0] + max(i - n + 1, 0) / stream.config.rate_Hz) / speed
                wait = max(0.0, min(wait, due - now))
            r, _, _ = select.select([cmd], [], [], wait)
            if r:
                while True:
                    try:
                        data, addr = cmd.recvfrom(65536)
                    except (BlockingIOError, InterruptedError, OSError):
                        break
                    try:
                        msg_id, _ = split_packet(data)
                    except Exception:
                        continue
                    stats["requests"] += 1
                    who = f"{addr[0]}:{addr[1]}"
                    if msg_id == NAT_CONNECT:
                        joined = addr not in clients
                        if joined:
                            stats["clients"] += 1
                        clients[addr] = time.monotonic()
                        cmd.sendto(info_pkt, addr)
                        if t0 is None:
                            t0, i = time.monotonic(), 0
                            stats["takes"] += 1
                            event(f"NatNet client {who} connected: the take starts")
                        elif joined:
                            event(f"NatNet client {who} joined the running take at frame {i + 1}"
                                  f" ({i / stream.config.rate_Hz:.1f} s in):"
                                  " it misses the start (the take restarts when no client is connected)")
                    elif msg_id == NAT_REQUEST_MODELDEF:
                        cmd.sendto(defs_pkt, addr)
                    elif msg_id == NAT_KEEPALIVE and addr in clients:
                        clients[addr] = time.monotonic()
                    elif msg_id == NAT_DISCONNECT and clients.pop(addr, None) is not None:
                        event(f"NatNet client {who} disconnected")
            if t0 is None:
                continue
            now = time.monotonic()
            if not multicast:  # (a multicast listener need not send keep-alives)
                for a in [a for a, seen in clients.items() if now - seen > CLIENT_TIMEOUT_S]:
                    del clients[a]
                    event(f"NatNet client {a[0]}:{a[1]} timed out (no keep-alive for {CLIENT_TIMEOUT_S:g} s)")
            if not clients:
                t0 = None
                event("no NatNet client left: the take stops; the next client starts it again")
                continue
            while True:
                k = min(i, n - 1)
                due = t0 + (t_take[k] - t_take[0] + max(i - n + 1, 0) / stream.config.rate_Hz) / speed
                if due > now:
                    break
                if once and i >= n:
                    return stats
                f = stream_frame(stream, k, i + 1)
                if i >= n:  # after the scenario: the last pose, with the take's clock running on
                    extra = (i - n + 1) / stream.config.rate_Hz
                    f = replace(f, timestamp_s=f.timestamp_s + extra,
                                stamp_mid_exposure=f.stamp_mid_exposure + int(extra * CLOCK_HZ),
                                stamp_data_received=f.stamp_data_received + int(extra * CLOCK_HZ),
                                stamp_transmit=f.stamp_transmit + int(extra * CLOCK_HZ))
                pkt = encode_frame(f, version)
                for a in [] if multicast else list(clients):  # as Motive: one or the other
                    try:
                        cmd.sendto(pkt, a)
                    except OSError:
                        clients.pop(a, None)
                if multicast:
                    try:
                        out.sendto(pkt, (multicast_group, data_port))
                    except OSError:
                        pass
                stats["frames_sent"] += 1
                i += 1
    finally:
        cmd.close()
        out.close()
    return stats
