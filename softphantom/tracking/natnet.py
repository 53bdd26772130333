"""NatNet 3.x/4.x packets (OptiTrack Motive's streaming protocol): decode and encode.

A NatNet UDP payload is ``uint16 message id, uint16 payload size`` then the payload, little
endian. The layout of a payload depends on the NatNet version the server speaks (its server-info
reply says it): 3.0 added the high-resolution stamps and moved the rigid bodies' markers into the
model definitions; 4.0 added marker names to those; 4.1 put a byte count before every section
and a precision timestamp in the frame suffix. This module reads FrameOfData (id 7), the model
definitions (id 5) and the server info (id 1) of every version from 3.0 on, and writes the three
(3.0 and 4.1) for the virtual phantom's server.

Errors name the byte offset inside the payload (after the 4-byte header) (:class:`NatNetError`, a ``FileFormatError``).

Latencies (NatNet 3.0+): the frame carries three stamps of the server's high-resolution clock
(camera mid-exposure, data received by Motive, transmit); with the clock rate from the server info
``system_latency = transmit − mid-exposure`` and ``software_latency = transmit − data received``
(what OptiTrack's SampleClient prints).

>>> f = Frame(frame_number=7, rigid_bodies=(RigidBody(2, (0.1, 0.2, 0.3), (0.0, 0.0, 0.0, 1.0)),),
...           timestamp_s=1.5)
>>> _, g = decode_packet(encode_frame(f, (4, 1)), (4, 1))
>>> g.frame_number, g.rigid_bodies[0].id, round(g.rigid_bodies[0].position[2], 6), g.rigid_bodies[0].tracking_valid
(7, 2, 0.3, True)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from softphantom.errors import FileFormatError

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

COMMAND_PORT = 1510
DATA_PORT = 1511
MULTICAST_GROUP = "239.255.42.99"
#: versions this module reads (major, minor); older servers are refused
SUPPORTED = ((3, 0), (3, 1), (4, 0), (4, 1), (4, 2))

Version = tuple  # (major, minor[, build, revision])


class NatNetError(FileFormatError):
    """A NatNet packet that cannot be decoded (names the byte offset)."""


@dataclass(frozen=True)
class ServerInfo:
    """The server-info reply: application name and version, the NatNet version it streams, and
    (3.0+) its high-resolution clock rate (Hz), data port, multicast flag and group."""

    app_name: str
    app_version: tuple[int, int, int, int]
    natnet_version: tuple[int, int, int, int]
    clock_hz: int | None = None
    data_port: int | None = None
    multicast: bool | None = None
    multicast_group: str | None = None

    @property
    def version(self) -> tuple[int, int]:
        return self.natnet_version[:2]


@dataclass(frozen=True)
class RigidBodyDef:
    """A rigid body's definition: ``markers`` (k, 3) offsets from its pivot (m), their active
    labels and (4.0+) names."""

    id: int
    name: str
    parent_id: int = -1
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    markers: tuple[tuple[float, float, float], ...] = ()
    marker_labels: tuple[int, ...] = ()
    marker_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class ModelDefs:
    """The model definitions: marker sets (name → marker names), rigid bodies, and the names of
    the other kinds of description the packet held (skeletons, force plates, devices, cameras, assets)."""

    marker_sets: dict[str, tuple[str, ...]] = field(default_factory=dict)
    rigid_bodies: tuple[RigidBodyDef, ...] = ()
    other: tuple[str, ...] = ()

    def body_id(self, name: str) -> int | None:
        return next((b.id for b in self.rigid_bodies if b.name == name), None)


@dataclass(frozen=True)
class RigidBody:
    """A rigid body in a frame: position (m), quaternion (x, y, z, w), mean marker error (m),
    tracking valid (False: Motive lost it this frame; the pose then repeats or is zero)."""

    id: int
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    mean_error: float = 0.0
    tracking_valid: bool = True


@dataclass(frozen=True)
class LabeledMarker:
    """A labelled marker: ``id`` packs model id (high 16 bits) and marker id (low 16 bits);
    ``params`` bits: 0 occluded, 1 point-cloud solved, 2 model solved, 3 has model, 4 unlabeled,
    5 active."""

    id: int
    position: tuple[float, float, float]
    size: float
    params: int = 0
    residual: float = 0.0

    @property
    def model_id(self) -> int:
        return self.id >> 16

    @property
    def marker_id(self) -> int:
        return self.id & 0xFFFF

    @property
    def occluded(self) -> bool:
        return bool(self.params & 0x01)

    @property
    def pc_solved(self) -> bool:
        return bool(self.params & 0x02)

    @property
    def model_solved(self) -> bool:
        return bool(self.params & 0x04)


@dataclass(frozen=True)
class Frame:
    """One FrameOfData. ``timestamp_s`` is Motive's frame time (s since its clock started); the
    three ``stamp_*`` are ticks of the server's high-resolution clock (3.0+), ``precision_s`` the
    4.1 precision timestamp (s) or None; ``params`` bit 0 recording, bit 1 tracked models changed."""

    frame_number: int
    marker_sets: dict[str, tuple[tuple[float, float, float], ...]] = field(default_factory=dict)
    other_markers: tuple[tuple[float, float, float], ...] = ()
    rigid_bodies: tuple[RigidBody, ...] = ()
    skeletons: int = 0
    labeled_markers: tuple[LabeledMarker, ...] = ()
    force_plates: int = 0
    devices: int = 0
    timecode: int = 0
    timecode_sub: int = 0
    timestamp_s: float = 0.0
    stamp_mid_exposure: int = 0
    stamp_data_received: int = 0
    stamp_transmit: int = 0
    precision_s: float | None = None
    params: int = 0

    def body(self, body_id: int) -> RigidBody | None:
        return next((b for b in self.rigid_bodies if b.id == body_id), None)

    def system_latency_s(self, clock_hz: int | None) -> float | None:
        """Mid-exposure → transmit (s), from the stamps and the server's clock rate."""
        if not clock_hz or not self.stamp_transmit:
            return None
        return (self.stamp_transmit - self.stamp_mid_exposure) / clock_hz

    def software_latency_s(self, clock_hz: int | None) -> float | None:
        """Data received by Motive → transmit (s)."""
        if not clock_hz or not self.stamp_transmit:
            return None
        return (self.stamp_transmit - self.stamp_data_received) / clock_hz

    @property
    def is_recording(self) -> bool:
        return bool(self.params & 0x01)

    @property
    def models_changed(self) -> bool:
        return bool(self.params & 0x02)


# ------------------------------------------------------------------------------------- reading
class _Reader:
    def __init__(self, data: bytes, what: str, start: int = 0):
        self.data = memoryview(data)
        self.off = start
        self.what = what

    def fail(self, msg: str, at: int | None = None) -> NatNetError:
        return NatNetError(f"{self.what}: payload byte {self.off if at is None else at}: {msg}")

    def unpack(self, fmt: str, what: str):
        s = struct.Struct("<" + fmt)
        if self.off + s.size > len(self.data):
            raise self.fail(f"{what} needs {s.size} bytes, the packet ends at byte {len(self.data)} (truncated?)")
        v = s.unpack_from(self.data, self.off)
        self.off += s.size
        return v

    def one(self, fmt: str, what: str):
        return self.unpack(fmt, what)[0]

    def count(self, what: str, limit: int = 100_000) -> int:
        at = self.off
        n = self.one("i", f"{what} count")
        if not 0 <= n <= limit:
            raise self.fail(f"{what} count {n} is not plausible (wrong NatNet version?)", at)
        return n

    def string(self, what: str, fixed: int | None = None) -> str:
        buf = bytes(self.data[self.off: self.off + fixed] if fixed else self.data[self.off:])
        end = buf.find(b"\0")
        if end < 0:
            raise self.fail(f"{what}: no terminating NUL before the end of the packet")
        text = buf[:end].decode("utf-8", "replace")
        self.off += fixed if fixed else end + 1
        return text

    def section(self, version, what: str) -> tuple[int, int | None]:
        """A section's count and (4.1+) its byte size."""
        n = self.count(what)
        size = self.one("i", f"{what} byte count") if version >= (4, 1) else None
        return n, size

    def vec(self, n: int, what: str) -> tuple[float, ...]:
        return self.unpack("f" * n, what)


def split_packet(data: bytes, what: str = "NatNet packet") -> tuple[int, bytes]:
    """``(message id, payload)`` of a UDP payload, checking the size field."""
    if len(data) < 4:
        raise NatNetError(f"{what}: byte 0: {len(data)} bytes, shorter than the 4-byte NatNet header")
    msg_id, size = struct.unpack_from("<HH", data, 0)
    if size > len(data) - 4:
        raise NatNetError(f"{what}: byte 2: payload size {size} but only {len(data) - 4} bytes follow (truncated?)")
    return msg_id, bytes(data[4: 4 + size])


def _check_version(version, what: str) -> tuple[int, int]:
    v = tuple(int(x) for x in version[:2])
    if v < (3, 0):
        raise NatNetError(f"{what}: NatNet {'.'.join(map(str, v))} is older than 3.0, which this reader needs")
    return v


def decode_server_info(payload: bytes, what: str = "server info") -> ServerInfo:
    """The server-info payload (message id 1)."""
    r = _Reader(payload, what)
    name = r.string("application name", fixed=256)
    app = r.unpack("4B", "application version")
    nn = r.unpack("4B", "NatNet version")
    clock = port = mc = group = None
    if len(payload) - r.off >= 15:
        clock = r.one("Q", "high-resolution clock rate")
        port = r.one("H", "data port")
        mc = bool(r.one("B", "multicast flag"))
        group = ".".join(str(b) for b in r.unpack("4B", "multicast group"))
    return ServerInfo(name, app, nn, clock, port, mc, group)


def _rigid_body(r: _Reader, v) -> RigidBody:
    rid = r.one("i", "rigid body id")
    pos = r.vec(3, "rigid body position")
    quat = r.vec(4, "rigid body quaternion")
    err = r.one("f", "rigid body mean error")
    params = r.one("h", "rigid body params")
    return RigidBody(rid, pos, quat, err, bool(params & 0x01))


def decode_frame(payload: bytes, version, what: str = "FrameOfData") -> Frame:
    """A FrameOfData payload (message id 7) sent by a NatNet ``version`` server."""
    return _decode_frame(payload, version, what)[0]


def _decode_frame(payload: bytes, version, what: str = "FrameOfData") -> tuple[Frame, int]:
    v = _check_version(version, what)
    r = _Reader(payload, f"{what} (NatNet {v[0]}.{v[1]})")
    frame = r.one("i", "frame number")
    n, _ = r.section(v, "marker set")
    msets = {}
    for _ in range(n):
        name = r.string("marker set name")
        k = r.count("marker")
        msets[name] = tuple(r.vec(3, "marker") for _ in range(k))
    n, _ = r.section(v, "other marker")
    other = tuple(r.vec(3, "other marker") for _ in range(n))
    n, _ = r.section(v, "rigid body")
    bodies = tuple(_rigid_body(r, v) for _ in range(n))
    n, _ = r.section(v, "skeleton")
    for _ in range(n):
        r.one("i", "skeleton id")
        for _ in range(r.count("skeleton rigid body")):
            _rigid_body(r, v)
    n_sk = n
    if v >= (4, 1):
        n, size = r.section(v, "asset")
        r.off += size  # asset rigid bodies and markers: not used here
    n, _ = r.section(v, "labeled marker")
    labeled = []
    for _ in range(n):
        mid = r.one("i", "labeled marker id")
        pos = r.vec(3, "labeled marker position")
        size = r.one("f", "labeled marker size")
        params = r.one("h", "labeled marker params")
        resid = r.one("f", "labeled marker residual")
        labeled.append(LabeledMarker(mid, pos, size, params, resid))
    counts = []
    for what_ in ("force plate", "device"):
        n, _ = r.section(v, what_)
        for _ in range(n):
            r.one("i", f"{what_} id")
            for _ in range(r.count(f"{what_} channel")):
                r.vec(r.count(f"{what_} sample"), f"{what_} samples")
        counts.append(n)
    tc, tcs = r.unpack("II", "timecode")
    ts = r.one("d", "timestamp")
    s_mid, s_rx, s_tx = r.unpack("QQQ", "high-resolution stamps")
    prec = None
    if v >= (4, 1):
        sec, frac = r.unpack("II", "precision timestamp")
        prec = sec + frac / 2**32
    params = r.one("h", "frame params")
    return Frame(frame, msets, other, bodies, n_sk, tuple(labeled), counts[0], counts[1], tc, tcs, ts,
                 s_mid, s_rx, s_tx, prec, params), r.off


def decode_model_defs(payload: bytes, version, what: str = "model definitions") -> ModelDefs:
    """The model-definitions payload (message id 5)."""
    v = _check_version(version, what)
    r = _Reader(payload, f"{what} (NatNet {v[0]}.{v[1]})")
    msets: dict[str, tuple[str, ...]] = {}
    bodies: list[RigidBodyDef] = []
    other: list[str] = []
    kinds = {2: "skeleton", 3: "force plate", 4: "device", 5: "camera", 6: "asset"}
    for _ in range(r.count("description")):
        at = r.off
        kind = r.one("i", "description type")
        size = r.one("i", "description byte count") if v >= (4, 1) else None
        start = r.off
        if kind == 0:
            name = r.string("marker set name")
            msets[name] = tuple(r.string("marker name") for _ in range(r.count("marker set marker")))
        elif kind == 1:
            bodies.append(_rigid_body_def(r, v))
        elif kind in kinds and size is not None:
            other.append(kinds[kind])
            r.off += size
        elif kind == 2:
            other.append("skeleton")
            r.string("skeleton name")
            r.one("i", "skeleton id")
            for _ in range(r.count("skeleton rigid body")):
                _rigid_body_def(r, v)
        elif kind in (3, 4):
            other.append(kinds[kind])
            _skip_plate_or_device(r, kind)
        elif kind == 5:
            other.append("camera")
            r.string("camera name")
            r.vec(7, "camera pose")
        else:
            raise r.fail(f"unknown description type {kind}", at)
        if size is not None and r.off != start + size:
            raise r.fail(f"description type {kind} read {r.off - start} bytes, its byte count says {size}", at)
    return ModelDefs(msets, tuple(bodies), tuple(other))


def _rigid_body_def(r: _Reader, v) -> RigidBodyDef:
    name = r.string("rigid body name")
    rid, parent = r.unpack("ii", "rigid body id and parent")
    off = r.vec(3, "rigid body offset")
    if v >= (4, 2):
        r.vec(4, "rigid body orientation offset")
    k = r.count("rigid body marker")
    pts = tuple(r.vec(3, "rigid body marker offset") for _ in range(k))
    labels = tuple(r.one("i", "rigid body marker label") for _ in range(k))
    names = tuple(r.string("rigid body marker name") for _ in range(k)) if v >= (4, 0) else ()
    return RigidBodyDef(rid, name, parent, off, pts, labels, names)


def _skip_plate_or_device(r: _Reader, kind: int) -> None:
    r.one("i", "id")
    if kind == 3:
        r.string("force plate serial")
        r.vec(2 + 3 + 144 + 12, "force plate geometry and calibration")
        r.unpack("ii", "force plate type")
    else:
        r.string("device name")
        r.string("device serial")
        r.unpack("ii", "device type")
    for _ in range(r.count("channel")):
        r.string("channel name")


def decode_packet(data: bytes, version=None, what: str = "NatNet packet"):
    """A whole UDP payload → ``(message id, ServerInfo | ModelDefs | Frame | payload bytes)``;
    ``version`` is needed for frames and model definitions."""
    msg_id, payload = split_packet(data, what)
    if msg_id == NAT_SERVERINFO:
        return msg_id, decode_server_info(payload, what)
    if msg_id in (NAT_FRAMEOFDATA, NAT_MODELDEF):
        if version is None:
            raise NatNetError(f"{what}: message {msg_id} before the server info: the NatNet version is not known")
        if msg_id == NAT_FRAMEOFDATA:
            return msg_id, decode_frame(payload, version, f"{what}: FrameOfData")
        return msg_id, decode_model_defs(payload, version, f"{what}: model definitions")
    return msg_id, payload


def frame_version_from_size(payload: bytes) -> tuple[int, int] | None:
    """The NatNet version (3.0 or 4.1 layout) that reads this frame payload to its exact end (a frame
    ends with its params and a 4-byte zero); None when neither or both do. For a capture that
    lacks the server-info reply."""
    fits = []
    for v in ((3, 0), (4, 1)):
        try:
            _, end = _decode_frame(payload, v)
        except NatNetError:
            continue
        if end == len(payload) - 4 and payload[end:] == b"\0\0\0\0":
            fits.append(v)
    return fits[0] if len(fits) == 1 else None


# ------------------------------------------------------------------------------------- writing
def packet(msg_id: int, payload: bytes) -> bytes:
    if len(payload) > 0xFFFF:
        raise ValueError(f"NatNet payload of {len(payload)} bytes does not fit the 16-bit size field")
    return struct.pack("<HH", msg_id, len(payload)) + payload


def _cstr(s: str) -> bytes:
    return s.encode("utf-8") + b"\0"


def encode_server_info(info: ServerInfo) -> bytes:
    """The server-info packet (with the 3.0+ clock rate and connection fields)."""
    name = info.app_name.encode("utf-8")[:255].ljust(256, b"\0")
    out = name + bytes(info.app_version) + bytes(info.natnet_version)
    group = bytes(int(x) for x in (info.multicast_group or "0.0.0.0").split("."))
    out += struct.pack("<QHB", info.clock_hz or 0, info.data_port or 0, bool(info.multicast)) + group
    return packet(NAT_SERVERINFO, out)


def _section(version, items: list[bytes]) -> bytes:
    body = b"".join(items)
    head = struct.pack("<i", len(items))
    return head + (struct.pack("<i", len(body)) if version >= (4, 1) else b"") + body


def encode_model_defs(defs: ModelDefs, version) -> bytes:
    """The model-definitions packet (marker sets and rigid bodies)."""
    v = _check_version(version, "model definitions")
    descs = []
    for name, markers in defs.marker_sets.items():
        descs.append((0, _cstr(name) + struct.pack("<i", len(markers)) + b"".join(_cstr(m) for m in markers)))
    for b in defs.rigid_bodies:
        d = _cstr(b.name) + struct.pack("<ii3f", b.id, b.parent_id, *b.offset)
        if v >= (4, 2):
            d += struct.pack("<4f", 0.0, 0.0, 0.0, 1.0)
        d += struct.pack("<i", len(b.markers)) + b"".join(struct.pack("<3f", *m) for m in b.markers)
        labels = b.marker_labels or tuple(range(1, len(b.markers) + 1))
        d += b"".join(struct.pack("<i", x) for x in labels)
        if v >= (4, 0):
            names = b.marker_names or tuple(f"Marker{i + 1}" for i in range(len(b.markers)))
            d += b"".join(_cstr(n) for n in names)
        descs.append((1, d))
    out = struct.pack("<i", len(descs))
    for kind, d in descs:
        out += struct.pack("<i", kind) + (struct.pack("<i", len(d)) if v >= (4, 1) else b"") + d
    return packet(NAT_MODELDEF, out)


def encode_frame(frame: Frame, version) -> bytes:
    """The FrameOfData packet of ``frame`` for a NatNet ``version`` client."""
    v = _check_version(version, "FrameOfData")
    out = struct.pack("<i", frame.frame_number)
    out += _section(v, [_cstr(n) + struct.pack("<i", len(m)) + b"".join(struct.pack("<3f", *p) for p in m)
                        for n, m in frame.marker_sets.items()])
    out += _section(v, [struct.pack("<3f", *p) for p in frame.other_markers])
    out += _section(v, [struct.pack("<i3f4ffh", b.id, *b.position, *b.quat_xyzw, b.mean_error, int(b.tracking_valid))
                        for b in frame.rigid_bodies])
    out += _section(v, [])  # skeletons
    if v >= (4, 1):
        out += _section(v, [])  # assets
    out += _section(v, [struct.pack("<i3ffhf", m.id, *m.position, m.size, m.params, m.residual)
                        for m in frame.labeled_markers])
    out += _section(v, []) + _section(v, [])  # force plates, devices
    out += struct.pack("<IId3Q", frame.timecode, frame.timecode_sub, frame.timestamp_s, frame.stamp_mid_exposure,
                       frame.stamp_data_received, frame.stamp_transmit)
    if v >= (4, 1):
        p = frame.precision_s if frame.precision_s is not None else frame.timestamp_s
        out += struct.pack("<II", int(p), int((p % 1.0) * 2**32) & 0xFFFFFFFF)
    out += struct.pack("<h", frame.params) + struct.pack("<i", 0)  # end of data
    return packet(NAT_FRAMEOFDATA, out)


def encode_request(msg_id: int, text: str = "") -> bytes:
    """A client → server request (connect, model definitions, keep-alive, a command string)."""
    return packet(msg_id, _cstr(text))
