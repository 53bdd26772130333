"""Binary serial protocol of the sensing board (docs/protocol.md specifies it byte by byte).

frame = COBS(payload ‖ CRC-16/CCITT-FALSE(payload), little-endian) ‖ 0x00

Payloads (little-endian): byte 0 protocol version (1), byte 1 message type.

====  ============  ===================================================================
type  name          rest of payload
====  ============  ===================================================================
0x01  DATA          seq u16, t_us u32 (board µs, centre of the window), osr u16, 5 × u32 sums
0x02  INFO          seq u16 (of the next DATA frame), t_us u32, fw major, minor, patch u8,
                    n_channels u8, osr u16
0x10  SET_OSR       osr u16 (host → board; the board answers with INFO)
0x11  GET_INFO      (host → board; the board answers with INFO)
====  ============  ===================================================================

COBS from the ``cobs`` package, the CRC from ``crcmod`` (predefined ``crc-ccitt-false``: poly
0x1021, init 0xFFFF, no reflection, no final xor; check value 0x29B1). The C side
(firmware/frame.c) is the same byte for byte.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import crcmod.predefined
from cobs import cobs

from softphantom.errors import UserError

PROTOCOL_VERSION = 1
MSG_DATA = 0x01
MSG_INFO = 0x02
CMD_SET_OSR = 0x10
CMD_GET_INFO = 0x11

_DATA = struct.Struct("<BBHIH5I")    # 30 bytes
_INFO = struct.Struct("<BBHIBBBBH")  # 14 bytes
_SET_OSR = struct.Struct("<BBH")
_GET_INFO = struct.Struct("<BB")
_CRC = struct.Struct("<H")
DATA_FRAME_BYTES = 1 + _DATA.size + _CRC.size + 1   # COBS overhead 1, delimiter 1: 34 bytes
MAX_ENCODED = 64                                    # longest legal frame body is 33 bytes

crc16 = crcmod.predefined.mkPredefinedCrcFun("crc-ccitt-false")
"""CRC-16/CCITT-FALSE of a bytes object (crcmod's C extension)."""


@dataclass(frozen=True)
class DataFrame:
    """One DATA message: ``raw`` 5 oversampled sums (4 arms, urethra)."""

    seq: int
    t_us: int
    osr: int
    raw: tuple[int, int, int, int, int]


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


def frame(payload: bytes) -> bytes:
    """Wrap a payload: COBS(payload + CRC16 little-endian) + 0x00.

    >>> frame(bytes([1, 0x11])).hex()
    '0501112e2c00'
    """
    return cobs.encode(payload + _CRC.pack(crc16(payload))) + b"\x00"


def encode_data(seq: int, t_us: int, osr: int, raw) -> bytes:
    """A complete DATA frame (34 bytes) for the given fields; values are checked against the field widths.

    >>> len(encode_data(1, 1000, 100, [51150] * 5))
    34
    """
    try:
        return frame(_DATA.pack(PROTOCOL_VERSION, MSG_DATA, seq, t_us, osr, *[int(r) for r in raw]))
    except struct.error as exc:
        raise UserError(f"DATA frame: field out of range ({exc})") from None


def encode_info(seq: int, t_us: int, firmware=(1, 0, 0), n_channels: int = 5, osr: int = 100) -> bytes:
    """A complete INFO frame."""
    return frame(_INFO.pack(PROTOCOL_VERSION, MSG_INFO, seq, t_us, *firmware, n_channels, osr))


def encode_set_osr(osr: int) -> bytes:
    """Host → board: set the oversampling ratio N (the firmware accepts 1..500).

    >>> encode_set_osr(25).hex()
    '0401101903fc0800'
    """
    if not 1 <= int(osr) <= 500:
        raise UserError(f"--osr: must be 1..500, got {osr}")
    return frame(_SET_OSR.pack(PROTOCOL_VERSION, CMD_SET_OSR, int(osr)))


def encode_get_info() -> bytes:
    """Host → board: ask for an INFO frame."""
    return frame(_GET_INFO.pack(PROTOCOL_VERSION, CMD_GET_INFO))


class FrameError(Exception):
    """Why one frame body was rejected (``kind``: cobs, crc, length, version, type)."""

    def __init__(self, kind: str, msg: str):
        super().__init__(msg)
        self.kind = kind


def decode_body(body: bytes) -> DataFrame | InfoFrame | Command:
    """Decode one frame body (the bytes between delimiters, without the 0x00).

    Raises :class:`FrameError` with the reason; never anything else.

    >>> decode_body(encode_data(7, 5, 100, [1, 2, 3, 4, 5])[:-1])
    DataFrame(seq=7, t_us=5, osr=100, raw=(1, 2, 3, 4, 5))
    """
    try:
        data = cobs.decode(body)
    except cobs.DecodeError as exc:
        raise FrameError("cobs", f"COBS: {exc}") from None
    if len(data) < 4:
        raise FrameError("length", f"frame too short ({len(data)} bytes)")
    payload, (crc,) = data[:-2], _CRC.unpack(data[-2:])
    if crc16(payload) != crc:
        raise FrameError("crc", f"CRC mismatch (got {crc:#06x}, computed {crc16(payload):#06x})")
    if payload[0] != PROTOCOL_VERSION:
        raise FrameError("version", f"protocol version {payload[0]}, expected {PROTOCOL_VERSION}")
    kind = payload[1]
    sizes = {MSG_DATA: _DATA, MSG_INFO: _INFO, CMD_SET_OSR: _SET_OSR, CMD_GET_INFO: _GET_INFO}
    if kind not in sizes:
        raise FrameError("type", f"unknown message type {kind:#04x}")
    if len(payload) != sizes[kind].size:
        raise FrameError("length", f"type {kind:#04x}: {len(payload)} bytes, expected {sizes[kind].size}")
    f = sizes[kind].unpack(payload)
    if kind == MSG_DATA:
        if f[4] == 0:
            raise FrameError("field", "DATA frame with osr 0 (byte offset 8)")
        return DataFrame(f[2], f[3], f[4], tuple(f[5:10]))
    if kind == MSG_INFO:
        return InfoFrame(f[2], f[3], (f[4], f[5], f[6]), f[7], f[8])
    if kind == CMD_SET_OSR:
        return Command(CMD_SET_OSR, f[2])
    return Command(CMD_GET_INFO)


@dataclass(frozen=True)
class DecoderStats:
    """Counters of a :class:`StreamDecoder` (all since it was created).

    ``frames_ok`` DATA frames accepted, ``info_frames`` INFO accepted, ``crc_errors`` bodies whose
    CRC failed, ``malformed`` bodies rejected for COBS/length/version/type, ``overflows`` runs of
    more than 64 bytes without a delimiter (dropped up to the next delimiter), ``sync_discards`` an invalid partial first
    body (joining mid-frame; not an error), ``seq_gaps`` jumps in the sequence number,
    ``frames_lost`` sequence numbers missing in them, ``resets`` times the board clock ran
    backwards (the board restarted; gaps are not counted across a restart),
    ``bytes_in``, ``bytes_discarded``.
    """

    frames_ok: int = 0
    info_frames: int = 0
    crc_errors: int = 0
    malformed: int = 0
    overflows: int = 0
    sync_discards: int = 0
    seq_gaps: int = 0
    frames_lost: int = 0
    resets: int = 0
    bytes_in: int = 0
    bytes_discarded: int = 0

    @property
    def rejected(self) -> int:
        return self.crc_errors + self.malformed + self.overflows


class StreamDecoder:
    """Incremental decoder of the board's byte stream: feed bytes, get frames.

    Splits on 0x00, resynchronises on garbage (a bad body costs only itself), rejects and counts bad
    CRCs, counts sequence gaps (seq is u16 and wraps). Never raises on any input.

    >>> dec = StreamDecoder()
    >>> stream = encode_data(1, 0, 100, [0] * 5) + b"\\x13garbage\\x00" + encode_data(3, 0, 100, [0] * 5)
    >>> [f.seq for f in dec.feed(stream)], dec.stats.frames_ok, dec.stats.malformed, dec.stats.frames_lost
    ([1, 3], 2, 1, 1)
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._synced = False
        self._skipping = False      # inside an overlong run: drop everything up to the next 0x00
        self._last_seq: int | None = None
        self._last_t_us: int | None = None
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
            if self._skipping:             # the tail of an overlong run: part of that overflow
                c["bytes_discarded"] += len(body) + 1
                self._skipping = False
            elif body:
                self._body(body, out)
            self._synced = True
        del buf[:start]
        if len(buf) > MAX_ENCODED:         # no delimiter for too long: garbage, drop it
            if not self._skipping:
                c["overflows"] += 1
            c["bytes_discarded"] += len(buf)
            buf.clear()
            self._skipping = True
        return out

    def _body(self, body: bytes, out: list) -> None:
        c = self._c
        try:
            f = decode_body(body)
        except FrameError as exc:
            c["bytes_discarded"] += len(body) + 1
            if not self._synced:
                c["sync_discards"] += 1
            elif exc.kind == "crc":
                c["crc_errors"] += 1
            else:
                c["malformed"] += 1
            return
        if isinstance(f, Command):          # our own echo on a loopback: not a board frame
            c["malformed"] += 1
            return
        # a board clock that runs backwards means the board restarted (u32 µs wraps after 71 min)
        if self._last_t_us is not None and ((f.t_us - self._last_t_us) & 0xFFFFFFFF) >= 0x80000000:
            c["resets"] += 1
            self._last_seq = None
        self._last_t_us = f.t_us
        if isinstance(f, DataFrame):        # seq counts DATA frames only (INFO carries the next one)
            if self._last_seq is not None:
                gap = (f.seq - self._last_seq - 1) & 0xFFFF
                if gap:
                    c["seq_gaps"] += 1
                    c["frames_lost"] += gap
            self._last_seq = f.seq
        if isinstance(f, DataFrame):
            c["frames_ok"] += 1
        else:
            c["info_frames"] += 1
        out.append(f)
