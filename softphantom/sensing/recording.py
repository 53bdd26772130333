"""Crash-safe recording of Measurements: a CSV whose first line is ``# `` + JSON metadata.

Columns (units in the names): ``t_s, seq, t_board_s, osr, raw_<ch>`` (the volume channels, then
the actuated cavities; the BIP: 5), ``dp_<arm>_kPa, dV_<arm>_mm3`` (per volume channel),
``p_<cavity>_kPa`` (per actuated cavity; the BIP: ``p_urethra_kPa``), ``status``. Raw sums are
stored so a file can be re-tared. The metadata names the board's channels (``channels``: its
:class:`~softphantom.records.channels.ChannelLayout`); a file of an older release without them
reads with the names its columns give.

A session file (:mod:`softphantom.records.session`: its one writer and reader) of
:class:`~softphantom.records.Measurement` rows (:func:`~softphantom.records.measurement.measurement_row`).

Outages are part of the data: a link event (:class:`~softphantom.records.SourceEvent`:
silent, disconnected, reconnected, restart, resumed, retared) is a marker row with ``seq`` −1,
``osr`` 0, empty numbers and ``status`` = ``event:<kind>: <detail>``. Readers get the samples and
the events apart (:attr:`Recording.events`).

``t_s`` never runs backwards, marker rows included. A marker row's ``t_s`` is its event's own
host time (an unplug, a reconnection, a restart each when it happened: the serial source stamps
no frame after them earlier), never before the row above it and never after the first sample
after it when that one is known as it is written (``resumed``: the frame that ended the hole). A
silence is marked where it began, at the last frame before it: it is noticed on the host clock
after the fact, and frames sampled during it may still come, late, with the times they were
sampled (a frozen link); its ``detail`` says how long it had lasted. The reader also reads a file
whose marker row is later than the sample after it: only the samples must be in time order.

Append-only: every row goes to the OS as soon as it is written (a killed process loses nothing
already written) and the file is fsync'ed at least every 100 ms while rows arrive (a power cut
loses at most the last 100 ms). A truncated file reads back up to its last complete row, with a
warning.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.records.channels import LAYOUT_KEY, ChannelLayout, ChannelNames, read_layout
from softphantom.records.measurement import Measurement, SourceEvent, event_row, measurement_row
from softphantom.records.names import (
    BIP_CAVITIES,
    EVENT_PREFIX,
    MEASUREMENT_COLUMNS,
    arm_names_of,
    measurement_columns,
    pressure_names_of,
)
from softphantom.records.session import OverSessionWriter, SessionWriter, TruncatedRecordingWarning, read_session_file
from softphantom.sensing.chain import SensorChain, Tare, to_measurement

__all__ = ["COLUMNS", "EVENT_PREFIX", "KIND", "LAYOUT_KEY", "Recorder", "Recording", "TruncatedRecordingWarning",
           "chain_from_meta", "read_recording", "recorded_layout", "retare"]

KIND = "softphantom-sensing-recording"
COLUMNS: tuple[str, ...] = MEASUREMENT_COLUMNS
FSYNC_EVERY_S = 0.1


class Recorder(OverSessionWriter):
    """Append Measurements to a new file; ``metadata`` (JSON-able dict) goes on the first line
    with ``layout``, the board's :class:`~softphantom.records.channels.ChannelLayout` (its columns).

    Refuses to overwrite an existing file. Call :meth:`tick` when idle so a quiet period still
    gets its fsync; :meth:`close` (or the context manager) ends the file.
    """

    def __init__(self, path, metadata: dict, fsync_every_s: float = FSYNC_EVERY_S,
                 clock: Callable[[], float] = time.monotonic, *, layout: ChannelLayout):
        self.layout = layout
        self.cavity_names = layout.actuated
        self._w = SessionWriter(path, measurement_columns(layout), {"kind": KIND, **metadata, **layout.to_meta()},
                                exclusive=True, fsync_every_s=fsync_every_s, clock=clock)
        self.path = self._w.path
        self.rows = 0
        self.events = 0
        self._last_t: float | None = None    # t_s of the last row written

    def write(self, m: Measurement) -> None:
        if tuple(m.cavity_pressures) != self.cavity_names:
            raise ValueError(f"a measurement of internal cavities {list(m.cavity_pressures)} in a file of "
                             f"{list(self.cavity_names)}")
        self._w.write_row(measurement_row(m, self.layout))
        self.rows += 1
        self._last_t = float(m.t)

    def write_event(self, ev: SourceEvent, next_t: float | None = None) -> None:
        """A marker row for a link event (synced at once: an outage is exactly when the process may
        die). Its ``t_s`` is ``ev.t`` (a silence: the last row's, where it began), not before the
        last row written nor after ``next_t`` (the sample to be written next, when known)."""
        t = float(ev.t)
        if ev.kind == "silent" and self._last_t is not None:
            t = self._last_t
        if next_t is not None:
            t = min(t, float(next_t))
        if self._last_t is not None:
            t = max(self._last_t, t)
        self._w.write_row(event_row(replace(ev, t=t), self.layout), sync=True)
        self.events += 1
        self._last_t = t

    def tick(self) -> None:
        """fsync if rows were written and the last fsync is older than ``fsync_every_s``."""
        self._w.tick()


@dataclass(frozen=True, eq=False)
class Recording(ChannelNames):
    """A recording read back (SI units): ``raw`` (n, channels), ``dp`` (n, volume channels) Pa,
    ``dV`` (n, volume channels) m³, ``pressures`` (n, M) Pa the actuated cavities' gauge pressures,
    ...; ``truncated`` when the last row was incomplete and dropped, ``events`` the link events
    (:class:`~softphantom.records.SourceEvent`) of the marker rows, ``layout`` the board's
    :class:`~softphantom.records.channels.ChannelLayout` (its metadata's)."""

    meta: dict
    t: np.ndarray
    seq: np.ndarray
    t_board: np.ndarray
    osr: np.ndarray
    raw: np.ndarray
    dp: np.ndarray
    dV: np.ndarray
    pressures: np.ndarray
    status: tuple[str, ...]
    layout: ChannelLayout
    truncated: bool = False
    events: tuple = ()

    def __len__(self) -> int:
        return len(self.t)

    @property
    def p_urethra(self) -> np.ndarray:
        """(n,) Pa: the urethra's column of ``pressures`` (NaN without a urethra)."""
        names = self.layout.actuated
        if BIP_CAVITIES[0] in names:
            return self.pressures[:, names.index(BIP_CAVITIES[0])]
        return np.full(len(self.t), math.nan)

    def measurements(self) -> Iterator[Measurement]:
        bip = self.cavity_names == BIP_CAVITIES
        p_urethra = self.p_urethra
        for i in range(len(self.t)):
            yield Measurement(float(self.t[i]), int(self.seq[i]), float(self.t_board[i]), self.raw[i].copy(),
                              int(self.osr[i]), self.dp[i].copy(), self.dV[i].copy(),
                              float(p_urethra[i]), self.status[i],
                              None if bip else dict(zip(self.cavity_names, self.pressures[i].tolist())))


def chain_from_meta(meta: dict, layout: ChannelLayout | None = None) -> SensorChain:
    """The SensorChain a recording was made with (from its ``chain`` metadata), on the board of
    ``layout`` (default: the one its metadata names, :func:`recorded_layout`)."""
    try:
        v = np.asarray(meta["chain"]["v_total_mm3"], float) * 1e-9
        return SensorChain(v, recorded_layout(meta) if layout is None else layout)
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(f"metadata: no usable chain.v_total_mm3 ({exc})") from None


def recorded_layout(meta: dict, columns=(), where: str = "metadata") -> ChannelLayout:
    """A recording's channel layout: its metadata's ``channels``; a file of an older release
    without them: the channels its columns name (``columns``), else its chain's names (with its
    volumes' count), else the BIP's (:func:`~softphantom.records.channels.read_layout`)."""
    sensing, actuated = arm_names_of(columns), pressure_names_of(columns) if columns else None
    chain = meta.get("chain") if isinstance(meta.get("chain"), dict) else {}
    if not sensing and chain.get("names") and chain.get("v_total_mm3"):
        n = len(chain["v_total_mm3"])
        sensing, actuated = tuple(chain["names"][:n]), tuple(chain["names"][n:])
    return read_layout(meta, where, sensing=sensing, actuated=actuated)


def retare(rec: Recording, tare: Tare, chain: SensorChain | None = None) -> Recording:
    """A new Recording with dp, dV and the cavities' pressures recomputed from the raw sums with ``tare``."""
    chain = chain or chain_from_meta(rec.meta, rec.layout)
    ms = [to_measurement(rec.t[i], rec.seq[i], rec.t_board[i], rec.raw[i], int(rec.osr[i]), chain, tare)
          for i in range(len(rec))]
    if not ms:
        return replace(rec, meta={**rec.meta, "tare": tare.to_dict()})
    return replace(rec, meta={**rec.meta, "tare": tare.to_dict()},
                   dp=np.array([m.dp for m in ms]), dV=np.array([m.dV for m in ms]), status=tuple(m.status for m in ms),
                   pressures=np.array([list(m.cavity_pressures.values()) for m in ms], float).reshape(len(ms), -1))


def read_recording(path) -> Recording:
    """Read a recording; a truncated last row is dropped with a :class:`TruncatedRecordingWarning`.

    Raises :class:`~softphantom.errors.FileFormatError` naming the line for anything else.
    """
    f = read_session_file(path, require_meta=True)
    if f.meta.get("kind") != KIND:
        raise FileFormatError(f"{path}: line 1: not a sensing recording (kind {f.meta.get('kind')!r})")
    layout = recorded_layout(f.meta, f.header, f"{path}: line 1: metadata")
    arms, cav = layout.sensing, layout.actuated
    columns = measurement_columns(layout)
    missing = [c for c in columns if c not in f.header]
    if missing:
        raise FileFormatError(f"{path}: line {f.header_line}: missing columns {', '.join(missing)}")
    idx = [f.header.index(c) for c in columns]
    a, mc = len(arms), len(cav)
    i_p, i_st = 4 + 3 * a + mc, 4 + 3 * a + 2 * mc  # the first p_<cavity>_kPa, status
    num = lambda x: float(x) if x else math.nan  # noqa: E731
    rows = []
    events = []
    t_prev = -math.inf
    for ln, cells in f.rows:
        try:
            c = [cells[i] for i in idx]
            t = float(c[0])
            if not math.isfinite(t):
                raise ValueError(f"t_s is {c[0]}")
            ev = SourceEvent.from_status(t, c[i_st])
            if ev is not None:          # a marker's time says when it was noticed: not checked
                events.append(ev)
                continue
            if t < t_prev:
                raise ValueError(f"t_s runs backwards ({t:.6f} after {t_prev:.6f})")
            t_prev = t
            rows.append((t, int(c[1]), num(c[2]), int(c[3]), [int(x) for x in c[4:4 + a + mc]],
                         [num(x) for x in c[4 + a + mc:4 + 2 * a + mc]],
                         [num(x) for x in c[4 + 2 * a + mc:4 + 3 * a + mc]],
                         [num(x) for x in c[i_p:i_st]], c[i_st]))
        except ValueError as exc:
            raise FileFormatError(f"{path}: line {ln}: {exc}") from None
    n = len(rows)
    col = lambda k, dt=float: np.array([r[k] for r in rows], dtype=dt)  # noqa: E731
    return Recording(
        meta=f.meta, t=col(0), seq=col(1, np.int64), t_board=col(2), osr=col(3, np.int64),
        raw=np.array([r[4] for r in rows], dtype=np.int64).reshape(n, a + mc),
        dp=np.array([r[5] for r in rows], float).reshape(n, a) * 1e3,
        dV=np.array([r[6] for r in rows], float).reshape(n, a) * 1e-9,
        pressures=np.array([r[7] for r in rows], float).reshape(n, mc) * 1e3,
        status=tuple(r[8] for r in rows), layout=layout, truncated=f.truncated, events=tuple(events))
