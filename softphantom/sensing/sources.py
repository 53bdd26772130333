"""Sensor sources: one interface for the serial board, a byte stream, and a recorded file.

Every source is a :class:`SensorSource`: ``read(timeout_s)`` returns the measurements that arrived
(possibly none) or ``None`` once the source has ended; iterate it for a plain stream of
:class:`Measurement`; ``stats()`` says how it is going; ``events()`` hands over what happened to
the link (:class:`SourceEvent`: silent, disconnected, reconnected, restart, resumed, with host
times), so every consumer can record an outage as part of the data; ``close()`` releases it. No
exception from the link escapes ``read``: a bad frame is counted, a lost port is reopened.

A simulated phantom plugs in either by producing frame bytes (``protocol.encode_data``) into a
:class:`FrameSource`, or by subclassing :class:`SensorSource` and returning Measurements.
"""

from __future__ import annotations

import collections
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from softphantom.records.measurement import EVENT_KINDS, Measurement, SourceEvent  # noqa: F401  (EVENT_KINDS, SourceEvent: re-exported)
from softphantom.sensing.board import frame_rate_Hz
from softphantom.sensing.chain import SensorChain, Tare, nominal_tare, to_measurement
from softphantom.sensing.protocol import (
    DataFrame,
    DecoderStats,
    InfoFrame,
    StreamDecoder,
    encode_get_info,
    encode_set_osr,
)

SILENCE_S = 0.5
"""A board that sent no valid frame for this long is reported silent."""

CLOCK_DRIFT = 0.005
"""How fast the host↔board clock offset may grow (the UNO's ceramic resonator: ±0.5 %)."""


@dataclass(frozen=True)
class SourceStats:
    """How a source is going: ``state`` is ``connecting``, ``ok``, ``silent``, ``disconnected`` or
    ``ended``; decoder counters (see :class:`~softphantom.sensing.protocol.DecoderStats`);
    ``silent_events`` times the board went silent, ``reconnects`` times the port was reopened,
    ``rate_Hz`` frames per second over the last second, ``firmware`` and ``osr`` from the board's
    INFO frame, ``last`` the latest measurement."""

    state: str
    decoder: DecoderStats
    silent_events: int = 0
    reconnects: int = 0
    rate_Hz: float = 0.0
    firmware: str | None = None
    osr: int | None = None
    last: Measurement | None = None


class SensorSource(ABC):
    """The interface every sensor source implements."""

    @abstractmethod
    def read(self, timeout_s: float = 0.1) -> list[Measurement] | None:
        """Measurements that arrived within about ``timeout_s`` (maybe none); ``None`` when ended."""

    @abstractmethod
    def stats(self) -> SourceStats:
        """Counters and state."""

    def events(self) -> list[SourceEvent]:
        """Events since the last call, oldest first (thread-safe: a deque the reader appends to)."""
        q = getattr(self, "_events", None)
        out = []
        while q:
            out.append(q.popleft())
        return out

    def close(self) -> None:
        """Release the source (idempotent)."""

    def __iter__(self) -> Iterator[Measurement]:
        while (batch := self.read()) is not None:
            yield from batch

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FrameSource(SensorSource):
    """Decodes frame bytes from ``chunks`` (any iterable of bytes) into Measurements.

    Host time ``t``: the board time mapped by the smallest observed host−board offset (the frame
    that arrived fastest), allowed to grow by :data:`CLOCK_DRIFT`, and never decreasing; with
    ``clock=None`` (a simulation) ``t`` is the board time itself.

    >>> from softphantom.sensing.protocol import encode_data
    >>> from softphantom.sensing.chain import default_chain
    >>> chunks = [encode_data(k, 52_000 * k, 100, [51150] * 4 + [4046]) for k in range(3)]
    >>> src = FrameSource(chunks, default_chain())
    >>> [(m.seq, m.t) for m in src], src.stats().state
    ([(0, 0.0), (1, 0.052), (2, 0.104)], 'ended')
    """

    def __init__(self, chunks: Iterable[bytes] | None, chain: SensorChain, tare: Tare | None = None,
                 clock: Callable[[], float] | None = None, silence_s: float = SILENCE_S):
        self._chunks = iter(chunks) if chunks is not None else None
        self.chain = chain
        self.tare = tare or nominal_tare(chain)
        self._clock = clock
        self._silence_s = silence_s
        self._dec = StreamDecoder(chain.n_channels)  # the board's channels: the chain's arms, then the urethra
        self._state = "connecting"
        self._silent_events = 0
        self._reconnects = 0
        self._firmware: str | None = None
        self._osr: int | None = None
        self._last: Measurement | None = None
        self._last_rx: float | None = None
        self._recent: collections.deque[float] = collections.deque(maxlen=256)
        self._tb_last_us: int | None = None
        self._tb_s = 0.0
        self._offset: float | None = None
        self._tb_prev = 0.0
        self._events: collections.deque[SourceEvent] = collections.deque(maxlen=10_000)
        self._hole_since: float | None = None   # start of the outage being reported
        self._floor = -float("inf")             # the latest unplug or reconnection (host time)
        self._board_starts = 0
        self.new_board_at: int | None = None
        """Where the last read's measurements switch to a restarted or new board (its clock began
        again): an index into them, their length when the new board sent no DATA frame yet (an
        INFO frame alone); None when the board did not restart."""

    def set_tare(self, tare: Tare) -> None:
        """Use ``tare`` for the measurements from now on."""
        self.tare = tare

    def _event(self, t: float, kind: str, detail: str = "") -> None:
        if kind in ("silent", "disconnected") and self._hole_since is None:
            self._hole_since = t
        if kind in ("disconnected", "reconnected"):  # no frame after them is stamped earlier
            self._floor = max(self._floor, float(t))
        self._events.append(SourceEvent(float(t), kind, detail))

    def _board_time(self, t_us: int) -> tuple[float, bool]:
        """The board time (s) of a frame's ``t_us`` and whether its clock began again there (the
        first frame, or a board restarted)."""
        restarted = self._tb_last_us is None
        if restarted:
            self._tb_s = t_us * 1e-6
        else:
            d = (t_us - self._tb_last_us) & 0xFFFFFFFF        # u32 µs wraps after 71.6 min
            if d >= 0x80000000:                               # backwards: the board restarted
                self._tb_s, restarted = t_us * 1e-6, True
                self._board_starts += 1
            else:
                self._tb_s += d * 1e-6
        self._tb_last_us = t_us
        return self._tb_s, restarted

    def _ingest(self, data: bytes, now: float | None) -> list[Measurement]:
        out = []
        resets = self._dec._c["resets"]
        frames = self._dec.feed(data)
        if self._dec._c["resets"] != resets:
            self._event(now if now is not None else (self._last.t if self._last else 0.0), "restart",
                        "the board clock ran backwards: the board was reset or replaced")
        self.new_board_at = None
        timed = []
        for f in frames:
            starts = self._board_starts
            tb, restarted = self._board_time(f.t_us)
            if self._board_starts != starts and self.new_board_at is None:
                self.new_board_at = sum(isinstance(g, DataFrame) for g, _, _ in timed)
            timed.append((f, tb, restarted))
        # Frames read at once arrived together: the newest of a board's frames in the burst bounds the
        # host−board offset of all of them (an offset is at most every frame's arrival − its board time),
        # so a burst keeps its board-clock spacing instead of sharing the arrival time.
        newest: list[float] = [0.0] * len(timed)
        top = None
        for i in range(len(timed) - 1, -1, -1):
            f, tb, restarted = timed[i]
            top = tb if top is None else top
            newest[i] = top
            if restarted:
                top = None
        for (f, tb, restarted), tb_newest in zip(timed, newest):
            if restarted:
                self._offset = None
            if now is not None:  # every frame's arrival bounds the offset, an INFO frame's too
                obs = now - tb_newest
                prev = self._tb_prev if self._offset is not None else tb
                self._offset = obs if self._offset is None else min(obs, self._offset + CLOCK_DRIFT * (tb - prev))
            self._tb_prev = tb
            if isinstance(f, InfoFrame):
                self._firmware, self._osr = f.firmware_str, f.osr
                continue
            assert isinstance(f, DataFrame)
            if now is None:
                t = tb
            else:
                # never backwards: an early frame that arrived late is corrected by a later one
                t = max(tb + self._offset, self._floor) if self._last is None else \
                    max(tb + self._offset, self._last.t, self._floor)
            m = to_measurement(t, f.seq, tb, f.raw, f.osr, self.chain, self.tare)
            self._osr = f.osr
            self._last = m
            out.append(m)
        if out:
            stamp = now if now is not None else out[-1].t
            if self._hole_since is not None:
                self._event(out[0].t, "resumed", f"after {stamp - self._hole_since:.2f} s without frames")
                self._hole_since = None
            self._last_rx = stamp
            self._recent.extend([stamp] * len(out))
            self._last = out[-1]
            self._state = "ok"
        return out

    def silence_limit_s(self) -> float:
        """How long without a valid frame counts as silent: ``silence_s``, or two frame periods of
        the board's channels at its OSR when that is longer (16 channels at OSR 500: 0.83 s a frame)."""
        if self._osr is None:
            return self._silence_s
        return max(self._silence_s, 2.0 / frame_rate_Hz(self._osr, n_channels=self.chain.n_channels))

    def _check_silence(self, now: float) -> None:
        if self._state == "ok" and self._last_rx is not None and now - self._last_rx > self.silence_limit_s():
            self._state = "silent"
            self._silent_events += 1
            self._event(now, "silent", f"no valid frame for {now - self._last_rx:.2f} s")

    def read(self, timeout_s: float = 0.1) -> list[Measurement] | None:
        self.new_board_at = None
        if self._chunks is None:
            return None
        try:
            data = next(self._chunks)
        except StopIteration:
            self._chunks = None
            self._state = "ended"
            return None
        return self._ingest(data, self._clock() if self._clock else None)

    def _rate(self, now: float) -> float:
        window = [t for t in self._recent if t > now - 1.0]
        if len(window) < 2:
            return 0.0
        span = max(now - window[0], window[-1] - window[0])
        return (len(window) - 1) / span if span > 0 else 0.0

    def stats(self) -> SourceStats:
        now = self._clock() if self._clock else (self._last.t if self._last else 0.0)
        return SourceStats(self._state, self._dec.stats, self._silent_events, self._reconnects,
                           self._rate(now), self._firmware, self._osr, self._last)


class SerialSource(FrameSource):
    """The sensing board on a serial port (pyserial ``serial_for_url``: ``/dev/ttyACM0``,
    ``loop://``, a pty path, ``socket://host:port``).

    Silent for more than ``silence_s`` → state ``silent`` (and a GET_INFO poke); a port error (USB
    unplugged) → ``disconnected``, then the port is reopened every ``reconnect_every_s`` until the
    board returns. ``osr`` (optional) is sent as SET_OSR on every (re)connection.
    """

    def __init__(self, url: str, chain: SensorChain, tare: Tare | None = None, baud: int = 115_200,
                 osr: int | None = None, silence_s: float = SILENCE_S, reconnect_every_s: float = 0.25,
                 opener: Callable | None = None, clock: Callable[[], float] = time.monotonic):
        super().__init__(None, chain, tare, clock, silence_s)
        import serial

        self._serial_exc = (serial.SerialException, OSError)
        self._opener = opener or serial.serial_for_url
        self.url, self.baud, self.osr_request = url, baud, osr
        self._reconnect_every = reconnect_every_s
        self._port = None
        self._next_try = 0.0
        self._ever_open = False
        self._closed = False
        self._last_poke = 0.0
        if osr is not None:
            encode_set_osr(osr)                 # validate now: a typed error, before any I/O

    def _open(self, now: float) -> None:
        self._next_try = now + self._reconnect_every
        try:
            port = self._opener(self.url, baudrate=self.baud, timeout=0.05)
        except self._serial_exc:
            return
        self._port = port
        if self._ever_open:
            self._reconnects += 1
            self._event(now, "reconnected", f"port {self.url} open again")
        self._ever_open = True
        self._state = "connecting"
        self._last_rx = now                     # silence is measured from the (re)connection
        v = self._command_version()
        self._send(encode_get_info(v) + (encode_set_osr(self.osr_request, v) if self.osr_request else b""))

    def _command_version(self) -> int:
        # the board's own version once seen; before that 1, which firmware 1.x and 2.x both read
        return self._dec.stats.version or 1

    def _send(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except self._serial_exc:
            self._drop()

    def _drop(self, reason: str = "") -> None:
        try:
            self._port.close()
        except self._serial_exc:
            pass
        self._port = None
        if self._state != "ended":
            self._state = "disconnected"
            if not self._closed:
                self._event(self._clock(), "disconnected", reason or f"port {self.url} failed")

    def read(self, timeout_s: float = 0.1) -> list[Measurement] | None:
        self.new_board_at = None
        if self._closed:
            return None
        now = self._clock()
        if self._port is None:
            if now >= self._next_try:
                self._open(now)
            if self._port is None:
                time.sleep(max(0.0, min(timeout_s, self._next_try - now)))
                return []
        try:
            self._port.timeout = max(0.001, timeout_s)
            data = self._port.read(max(1, self._port.in_waiting))
        except self._serial_exc:
            self._drop()
            return []
        now = self._clock()
        out = self._ingest(data, now) if data else []
        self._check_silence(now)
        if self._state == "silent" and now - self._last_poke > 1.0:
            self._last_poke = now
            self._send(encode_get_info(self._command_version()))
        return out

    def close(self) -> None:
        self._closed = True
        if self._port is not None:
            self._drop()
        self._state = "ended"


class ReplaySource(SensorSource):
    """Replays a recording (:func:`softphantom.sensing.recording.read_recording`) as Measurements,
    optionally re-converted (``tare``, ``chain``) from the stored raw sums; ``batch`` measurements
    per read. The recording's link events come back from :meth:`events` as the replay passes their
    times. A recording without a single sample is refused (a one-line error)."""

    def __init__(self, path, tare: Tare | None = None, batch: int = 256, chain: SensorChain | None = None):
        from softphantom.errors import FileFormatError
        from softphantom.sensing.recording import read_recording, retare

        rec = read_recording(path)
        if len(rec) == 0:
            raise FileFormatError(f"{path}: no samples to replay (the recording has only its header"
                                  f"{f' and {len(rec.events)} link events' if rec.events else ''})")
        if tare is not None or chain is not None:
            rec = retare(rec, tare if tare is not None else _recorded_tare(rec, path), chain)
        self.recording = rec
        self._it = self.recording.measurements()
        self._pending = collections.deque(rec.events)
        self._events: collections.deque[SourceEvent] = collections.deque()
        self._batch = batch
        self._n = 0
        self._ended = False
        self._last: Measurement | None = None

    def read(self, timeout_s: float = 0.1) -> list[Measurement] | None:
        if self._ended:
            return None
        out = []
        for m in self._it:
            out.append(m)
            if len(out) >= self._batch:
                break
        if not out:
            self._ended = True
            self._events.extend(self._pending)
            self._pending.clear()
            return None
        while self._pending and self._pending[0].t <= out[-1].t:
            self._events.append(self._pending.popleft())
        self._n += len(out)
        self._last = out[-1]
        return out

    def stats(self) -> SourceStats:
        meta = self.recording.meta
        return SourceStats("ended" if self._ended else "ok", DecoderStats(frames_ok=self._n),
                           firmware=meta.get("firmware"), osr=meta.get("osr"), last=self._last)


def _recorded_tare(rec, path) -> Tare:
    from softphantom.errors import FileFormatError

    if "tare" not in rec.meta:
        raise FileFormatError(f"{path}: line 1: no tare in the metadata; cannot re-convert the raw sums")
    return Tare.from_dict(rec.meta["tare"])
