"""Binary serial protocol of the sensing board (docs/protocol.md specifies it byte by byte).

Version 2 (firmware 2.x): frame = 0x00 ‖ COBS(payload ‖ CRC-16/CCITT-FALSE(payload), LE) ‖ 0x00
Version 1 (firmware 1.x): frame =        COBS(payload ‖ CRC-16/CCITT-FALSE(payload), LE) ‖ 0x00

The leading delimiter of version 2 ends whatever came before a frame (a truncated frame, line
noise), so a damaged frame never takes the next one with it. The decoder reads both versions;
for version 1 streams it recovers a whole frame from the head or tail of a damaged body (a DATA
body is always 33 bytes, an INFO body 17), which gives the same guarantee.

The channel count n is the board's, fixed when its firmware is built (``make N_CHANNELS=n``):
the BIP's board reads 5 (four arms and the urethra, on the UNO's A0–A4); a phantom of other arms
n = arms + 1, up to 6 on the Arduino UNO (A0–A5) and 16 on the Mega 2560. The host's decoder is
made for the n of the model it reads (:class:`StreamDecoder`); a frame of another count is
rejected with its length, an INFO frame naming another count with that count. Version 1
(firmware 1.x) has 5 channels only.

Payloads (little-endian): byte 0 protocol version (1 or 2), byte 1 message type.

====  ============  ===================================================================
type  name          rest of payload
====  ============  ===================================================================
0x01  DATA          seq u16, t_us u32 (board µs, centre of the window), osr u16, n × u32 sums
0x02  INFO          seq u16 (of the next DATA frame), t_us u32, fw major, minor, patch u8,
                    n_channels u8, osr u16
0x10  SET_OSR       osr u16 (host → board; the board answers with INFO)
0x11  GET_INFO      (host → board; the board answers with INFO)
====  ============  ===================================================================

After the CRC every field is checked against what the firmware can send (osr 1..500, each sum
≤ 1023·osr, n channels): a CRC-valid frame with impossible content is rejected, not passed on.

COBS from the ``cobs`` package, the CRC from ``crcmod`` (predefined ``crc-ccitt-false``: poly
0x1021, init 0xFFFF, no reflection, no final xor; check value 0x29B1). The C side
(firmware/frame.c) is the same byte for byte.
"""

from __future__ import annotations

import collections
import functools
import struct
from dataclasses import dataclass

import crcmod.predefined
from cobs import cobs

from softphantom.errors import UserError

PROTOCOL_VERSION = 2
"""The version this host and firmware 2.x send."""
SUPPORTED_VERSIONS = (1, 2)
"""Versions the decoder reads."""
MSG_DATA = 0x01
MSG_INFO = 0x02
CMD_SET_OSR = 0x10
CMD_GET_INFO = 0x11
OSR_MIN, OSR_MAX = 1, 500
"""OSR range the firmware accepts (and so the only one a frame may carry)."""
N_CHANNELS = 5
"""The BIP board's channel count: four arms, then the urethra."""
MAX_CHANNELS = 16
"""The most a board reads: the Arduino Mega 2560's analog inputs (the UNO has 6)."""
ADC_MAX_CODE = 1023

_INFO = struct.Struct("<BBHIBBBBH")  # 14 bytes
_SET_OSR = struct.Struct("<BBH")
_GET_INFO = struct.Struct("<BB")
_CRC = struct.Struct("<H")


def check_channels(n: int) -> int:
    """``n`` if a board can read that many channels (2 .. :data:`MAX_CHANNELS`), else UserError."""
    if not (isinstance(n, int) and 2 <= n <= MAX_CHANNELS):
        raise UserError(f"channel count: a board reads 2..{MAX_CHANNELS} (the UNO 6, the Mega 16), got {n!r}")
    return n


@functools.cache
def _data(n: int = N_CHANNELS) -> struct.Struct:
    """The DATA payload of ``n`` channels: 10 + 4n bytes (30 for the BIP's 5)."""
    return struct.Struct(f"<BBHIH{check_channels(n)}I")


def data_body_bytes(n: int = N_CHANNELS) -> int:
    """A DATA body between its delimiters: COBS overhead 1, payload, CRC 2 (33 bytes for 5 channels).

    >>> data_body_bytes(5), data_body_bytes(6), data_body_bytes(16)
    (33, 37, 77)
    """
    return 1 + _data(n).size + _CRC.size


def data_frame_bytes(n: int = N_CHANNELS) -> int:
    """A version 2 DATA frame with its two delimiters (35 bytes for 5 channels)."""
    return 1 + data_body_bytes(n) + 1


DATA_BODY_BYTES = data_body_bytes()                 # COBS overhead 1: 33 bytes between delimiters
INFO_BODY_BYTES = 1 + _INFO.size + _CRC.size        # 17 bytes
DATA_FRAME_BYTES = data_frame_bytes()               # version 2: two delimiters, 35 bytes
DATA_FRAME_BYTES_V1 = DATA_BODY_BYTES + 1           # version 1: 34 bytes
MAX_ENCODED = 2 * DATA_BODY_BYTES                   # a run this long without 0x00 is an overflow

crc16 = crcmod.predefined.mkPredefinedCrcFun("crc-ccitt-false")
"""CRC-16/CCITT-FALSE of a bytes object (crcmod's C extension)."""


@dataclass(frozen=True)
class DataFrame:
    """One DATA message: ``raw`` the oversampled sums of the board's channels (the arms, then the
    urethra: 5 on the BIP's board)."""

    seq: int
    t_us: int
    osr: int
    raw: tuple[int, ...]


@dataclass(frozen=True)
class InfoFrame:
    """One INFO message: firmware version, channel count, current OSR."""

    seq: int
    t_us: int
    firmware: tuple[int, int, int]
    n_channels: int
    osr: int

    @property
    def firmware_str(self) -> str:
        return ".".join(str(v) for v in self.firmware)


@dataclass(frozen=True)
class Command:
    """A host → board command: ``kind`` is CMD_SET_OSR or CMD_GET_INFO."""

    kind: int
    osr: int | None = None


def _check_version(version: int) -> int:
    if version not in SUPPORTED_VERSIONS:
        raise UserError(f"protocol version: expected one of {SUPPORTED_VERSIONS}, got {version}")
    return version


def frame(payload: bytes) -> bytes:
    """Wrap a payload: COBS(payload + CRC16 little-endian) + 0x00, preceded by 0x00 in version 2
    (the payload's byte 0).

    >>> frame(bytes([2, 0x11])).hex()
    '000502117d7900'
    >>> frame(bytes([1, 0x11])).hex()
    '0501112e2c00'
    """
    body = cobs.encode(payload + _CRC.pack(crc16(payload))) + b"\x00"
    return body if payload[:1] == b"\x01" else b"\x00" + body


def encode_data(seq: int, t_us: int, osr: int, raw, version: int = PROTOCOL_VERSION) -> bytes:
    """A complete DATA frame (35 bytes; 34 in version 1) for the given fields; values are checked
    against the field widths (not against the content rules: a test may build an impossible frame).

    >>> len(encode_data(1, 1000, 100, [51150] * 5)), len(encode_data(1, 1000, 100, [51150] * 5, version=1))
    (35, 34)
    >>> len(encode_data(1, 1000, 100, [51150] * 6))  # a board of 6 channels (5 arms): 4 bytes more
    39
    """
    raw = [int(r) for r in raw]
    if _check_version(version) == 1 and len(raw) != N_CHANNELS:
        raise UserError(f"DATA frame: protocol version 1 carries {N_CHANNELS} channels, got {len(raw)}")
    try:
        return frame(_data(len(raw)).pack(version, MSG_DATA, seq, t_us, osr, *raw))
    except struct.error as exc:
        raise UserError(f"DATA frame: field out of range ({exc})") from None


def encode_info(seq: int, t_us: int, firmware=(2, 0, 0), n_channels: int = N_CHANNELS, osr: int = 100,
                version: int = PROTOCOL_VERSION) -> bytes:
    """A complete INFO frame."""
    return frame(_INFO.pack(_check_version(version), MSG_INFO, seq, t_us, *firmware, n_channels, osr))


def encode_set_osr(osr: int, version: int = PROTOCOL_VERSION) -> bytes:
    """Host → board: set the oversampling ratio N (the firmware accepts 1..500). Firmware 2.x
    reads commands of both versions, firmware 1.x only version 1.

    >>> encode_set_osr(25, version=1).hex()
    '0401101903fc0800'
    """
    if not OSR_MIN <= int(osr) <= OSR_MAX:
        raise UserError(f"--osr: must be {OSR_MIN}..{OSR_MAX}, got {osr}")
    return frame(_SET_OSR.pack(_check_version(version), CMD_SET_OSR, int(osr)))


def encode_get_info(version: int = PROTOCOL_VERSION) -> bytes:
    """Host → board: ask for an INFO frame."""
    return frame(_GET_INFO.pack(_check_version(version), CMD_GET_INFO))


class FrameError(Exception):
    """Why one frame body was rejected (``kind``: cobs, crc, length, version, type, field)."""

    def __init__(self, kind: str, msg: str):
        super().__init__(msg)
        self.kind = kind


def _check_content(kind: int, f: tuple, n: int = N_CHANNELS) -> None:
    """Field checks after the CRC: what the firmware can never send. Byte offsets in the payload."""
    if kind == MSG_DATA:
        osr = f[4]
        if not OSR_MIN <= osr <= OSR_MAX:
            raise FrameError("field", f"DATA osr {osr} outside {OSR_MIN}..{OSR_MAX} (byte offset 8)")
        if max(f[5:5 + n]) <= ADC_MAX_CODE * osr:
            return
        for i, r in enumerate(f[5:5 + n]):
            if r > ADC_MAX_CODE * osr:
                raise FrameError("field", f"DATA sum {r} of channel {i} above {ADC_MAX_CODE}·osr = "
                                          f"{ADC_MAX_CODE * osr} (byte offset {10 + 4 * i})")
    elif kind == MSG_INFO:
        if f[7] != n:
            raise FrameError("field", f"INFO n_channels {f[7]}, expected {n} (byte offset 11)")
        if not OSR_MIN <= f[8] <= OSR_MAX:
            raise FrameError("field", f"INFO osr {f[8]} outside {OSR_MIN}..{OSR_MAX} (byte offset 12)")
    elif kind == CMD_SET_OSR and not OSR_MIN <= f[2] <= OSR_MAX:
        raise FrameError("field", f"SET_OSR osr {f[2]} outside {OSR_MIN}..{OSR_MAX} (byte offset 2)")


_SIZES = {MSG_INFO: _INFO, CMD_SET_OSR: _SET_OSR, CMD_GET_INFO: _GET_INFO}


def decode_body(body: bytes, n_channels: int = N_CHANNELS) -> DataFrame | InfoFrame | Command:
    """Decode one frame body (the bytes between delimiters, without the 0x00) of either version,
    from a board of ``n_channels``.

    Raises :class:`FrameError` with the reason; never anything else.

    >>> decode_body(encode_data(7, 5, 100, [1, 2, 3, 4, 5])[1:-1])
    DataFrame(seq=7, t_us=5, osr=100, raw=(1, 2, 3, 4, 5))
    >>> decode_body(encode_data(7, 5, 50, [60000, 0, 0, 0, 0])[1:-1])
    Traceback (most recent call last):
    ...
    softphantom.sensing.protocol.FrameError: DATA sum 60000 of channel 0 above 1023·osr = 51150 (byte offset 10)
    >>> decode_body(encode_data(7, 5, 100, [1, 2, 3, 4, 5, 6])[1:-1], n_channels=6).raw
    (1, 2, 3, 4, 5, 6)
    >>> decode_body(encode_data(7, 5, 100, [1, 2, 3, 4, 5, 6])[1:-1])
    Traceback (most recent call last):
    ...
    softphantom.sensing.protocol.FrameError: type 0x01: 34 bytes, expected 30
    """
    return _decode(body, n_channels)[0]


def _decode(body: bytes, n: int = N_CHANNELS) -> tuple[DataFrame | InfoFrame | Command, int]:
    """(message, protocol version) of one body; see :func:`decode_body`."""
    try:
        data = cobs.decode(body)
    except cobs.DecodeError as exc:
        raise FrameError("cobs", f"COBS: {exc}") from None
    if len(data) < 4:
        raise FrameError("length", f"frame too short ({len(data)} bytes)")
    payload, (crc,) = data[:-2], _CRC.unpack(data[-2:])
    if crc16(payload) != crc:
        raise FrameError("crc", f"CRC mismatch (got {crc:#06x}, computed {crc16(payload):#06x})")
    version = payload[0]
    if version not in SUPPORTED_VERSIONS:
        raise FrameError("version", f"protocol version {version} (byte offset 0), expected one of "
                                    f"{SUPPORTED_VERSIONS}")
    kind = payload[1]
    st = _data(n) if kind == MSG_DATA else _SIZES.get(kind)
    if st is None:
        raise FrameError("type", f"unknown message type {kind:#04x} (byte offset 1)")
    if len(payload) != st.size:
        raise FrameError("length", f"type {kind:#04x}: {len(payload)} bytes, expected {st.size}")
    f = st.unpack(payload)
    _check_content(kind, f, n)
    if kind == MSG_DATA:
        return DataFrame(f[2], f[3], f[4], tuple(f[5:5 + n])), version
    if kind == MSG_INFO:
        return InfoFrame(f[2], f[3], (f[4], f[5], f[6]), f[7], f[8]), version
    if kind == CMD_SET_OSR:
        return Command(CMD_SET_OSR, f[2]), version
    return Command(CMD_GET_INFO), version


def _period_us(osr: int, n: int = N_CHANNELS) -> float:
    """The board's frame period for ``osr`` (n channels × osr conversions of 104 µs)."""
    return n * osr * 104.0


DUPLICATE_WINDOW = 256
"""How many recent frames a copy (the same bytes) is recognised against (3.3 s at 77 Hz): a copy
of an older frame whose clock runs backwards reads as a board restart."""


@dataclass(frozen=True)
class DecoderStats:
    """Counters of a :class:`StreamDecoder` (all since it was created).

    ``frames_ok`` DATA frames accepted, ``info_frames`` INFO accepted, ``crc_errors`` bodies whose
    CRC failed, ``malformed`` bodies rejected for COBS/length/version/type, ``content_errors``
    bodies with a valid CRC but an impossible field (osr, a sum, the channel count),
    ``overflows`` runs of more than two DATA bodies without a delimiter (66 bytes for 5 channels;
    their last two bodies' worth is kept, so a frame at the end of the run survives), ``sync_discards`` an invalid partial first body
    (joining mid-frame; not an error), ``recovered`` whole frames taken from the head or tail of
    a damaged body (version 1 streams: a lost delimiter or a truncated frame before them),
    ``duplicates`` copies of one of the last :data:`DUPLICATE_WINDOW` DATA frames (a retransmit,
    a doubled USB read: dropped, counted neither as lost nor as a restart; a copy of an INFO frame
    counts in ``info_frames`` and is not handed on),
    ``stale`` DATA frames whose seq lies behind the last one on a forward clock (dropped),
    ``seq_gaps`` jumps in the sequence number, ``frames_lost`` sequence numbers missing in them
    (beyond 65 536 the board clock tells how often seq wrapped), ``resets`` times the board clock
    ran backwards (the board restarted; gaps are not counted across a restart), ``version`` the
    protocol version of the last accepted frame (None before the first), ``bytes_in``,
    ``bytes_discarded``.
    """

    frames_ok: int = 0
    info_frames: int = 0
    crc_errors: int = 0
    malformed: int = 0
    content_errors: int = 0
    overflows: int = 0
    sync_discards: int = 0
    recovered: int = 0
    duplicates: int = 0
    stale: int = 0
    seq_gaps: int = 0
    frames_lost: int = 0
    resets: int = 0
    version: int | None = None
    bytes_in: int = 0
    bytes_discarded: int = 0

    @property
    def rejected(self) -> int:
        return self.crc_errors + self.malformed + self.content_errors + self.overflows


_ERROR_COUNTER = {"crc": "crc_errors", "field": "content_errors"}


class StreamDecoder:
    """Incremental decoder of the board's byte stream (either protocol version): feed bytes, get
    frames.

    Splits on 0x00; a bad body costs only itself: with version 2's leading delimiter nothing else
    shares it, and in a version 1 stream a whole frame at its head or tail is recovered. Rejects
    and counts bad CRCs and impossible fields, counts sequence gaps (seq is u16 and wraps),
    duplicates and board restarts. Never raises on any input.

    >>> dec = StreamDecoder()
    >>> stream = encode_data(1, 0, 100, [0] * 5) + b"\\x13garbage" + encode_data(3, 0, 100, [0] * 5)
    >>> [f.seq for f in dec.feed(stream)], dec.stats.frames_ok, dec.stats.malformed, dec.stats.frames_lost
    ([1, 3], 2, 1, 1)
    """

    def __init__(self, n_channels: int = N_CHANNELS) -> None:
        self.n_channels = check_channels(n_channels)  # the board's (the model's arms + the urethra)
        self._data_body = data_body_bytes(n_channels)
        self._max_encoded = 2 * max(self._data_body, INFO_BODY_BYTES)
        self._buf = bytearray()
        self._synced = False
        self._after_overflow = False   # the next body is the kept tail of an overlong run
        self._last_seq: int | None = None
        self._last_t_us: int | None = None
        # the bodies of the last frames accepted, to recognise a copy wherever it comes
        self._recent: collections.deque = collections.deque()
        self._recent_set: set = set()
        self._c = dict(DecoderStats().__dict__)

    @property
    def stats(self) -> DecoderStats:
        return DecoderStats(**self._c)

    def feed(self, data: bytes) -> list[DataFrame | InfoFrame]:
        c = self._c
        c["bytes_in"] += len(data)
        out: list[DataFrame | InfoFrame] = []
        buf = self._buf
        buf += data
        start = 0
        while True:
            end = buf.find(0, start)
            if end < 0:
                break
            body = bytes(buf[start:end])
            start = end + 1
            if body:
                if len(body) > self._max_encoded:  # an overlong run ended here: keep its tail
                    self._overflow(len(body))
                    body = body[-self._max_encoded:]
                self._body(body, out)
                self._synced = True
            self._after_overflow = False
        del buf[:start]
        if len(buf) > self._max_encoded:   # no delimiter for too long: keep only the tail
            self._overflow(len(buf))
            del buf[:-self._max_encoded]
        return out

    def _overflow(self, n: int) -> None:
        if not self._after_overflow:
            self._c["overflows"] += 1
        self._c["bytes_discarded"] += n - self._max_encoded
        self._after_overflow = True

    def _body(self, body: bytes, out: list) -> None:
        c = self._c
        try:
            f, version = _decode(body, self.n_channels)
        except FrameError as exc:
            if self._recover(body, out):
                return
            c["bytes_discarded"] += len(body) + 1
            if self._after_overflow:       # already counted as the overflow
                return
            if not self._synced:
                c["sync_discards"] += 1
            else:
                c[_ERROR_COUNTER.get(exc.kind, "malformed")] += 1
            return
        self._accept(f, version, out, body)

    def _recover(self, body: bytes, out: list) -> bool:
        """Whole frames at the head and the tail of a damaged body (a version 1 stream merges a
        truncated frame with the next one, a lost delimiter two frames). True if any was found."""
        found = []
        for n in (self._data_body, INFO_BODY_BYTES):
            if len(body) > n:
                for part, at in ((body[:n], 0), (body[-n:], len(body) - n)):
                    try:
                        found.append((at, _decode(part, self.n_channels), part))
                    except FrameError:
                        pass
        if not found:
            return False
        found.sort(key=lambda x: x[0])
        # overlapping finds are kept: each passed its own CRC (a truncated frame whose lost last
        # byte equals the next frame's first byte is whole again at the head)
        for at, (f, version), part in found:
            self._c["recovered"] += 1
            self._accept(f, version, out, part)
        self._c["bytes_discarded"] += max(0, len(body) + 1 - sum(
            self._data_body if isinstance(f, DataFrame) else INFO_BODY_BYTES for _, (f, _), _ in found))
        return True

    def _accept(self, f, version: int, out: list, body: bytes) -> None:
        c = self._c
        if isinstance(f, Command):          # our own echo on a loopback: not a board frame
            c["malformed"] += 1
            return
        if body in self._recent_set:        # the same frame again: no data, nothing lost, no restart
            c["duplicates" if isinstance(f, DataFrame) else "info_frames"] += 1
            return
        # a board clock that runs backwards means the board restarted (u32 µs wraps after 71 min)
        dt_us = None
        if self._last_t_us is not None:
            dt_us = (f.t_us - self._last_t_us) & 0xFFFFFFFF
            if dt_us >= 0x80000000:
                c["resets"] += 1
                self._last_seq = None
                dt_us = None
                self._recent.clear()        # a new board's frames are never copies of the old one's
                self._recent_set.clear()
        if isinstance(f, DataFrame):        # seq counts DATA frames only (INFO carries the next one)
            if self._last_seq is not None:
                step = (f.seq - self._last_seq) & 0xFFFF
                if dt_us is not None and self._last_t_us is not None:
                    # the board clock says how many frames passed: resolves seq's wrap (and a
                    # repeated or older seq on a running clock)
                    expected = dt_us / _period_us(f.osr, self.n_channels)
                    step += 65536 * round((expected - step) / 65536)
                if step <= 0:
                    c["duplicates" if step == 0 else "stale"] += 1
                    return
                if step > 1:
                    c["seq_gaps"] += 1
                    c["frames_lost"] += step - 1
            self._last_seq = f.seq
            c["frames_ok"] += 1
        else:
            c["info_frames"] += 1
        self._last_t_us = f.t_us
        c["version"] = version
        if len(self._recent) >= DUPLICATE_WINDOW:
            self._recent_set.discard(self._recent.popleft())
        self._recent.append(body)
        self._recent_set.add(body)
        out.append(f)
