"""Crash-safe recording of Measurements: a CSV whose first line is ``# `` + JSON metadata.

Columns (units in the names): ``t_s, seq, t_board_s, osr, raw_<ch> (5), dp_<arm>_kPa (4),
dV_<arm>_mm3 (4), p_urethra_kPa, status``. Raw sums are stored so a file can be re-tared.

Outages are part of the data: a link event (:class:`~softphantom.sensing.sources.SourceEvent`:
silent, disconnected, reconnected, restart, resumed, retared) is a marker row at its host time with
``seq`` −1, ``osr`` 0, empty numbers and ``status`` = ``event:<kind>: <detail>``. Readers get the
samples and the events apart (:attr:`Recording.events`).

Append-only: every row goes to the OS as soon as it is written (a killed process loses nothing
already written) and the file is fsync'ed at least every 100 ms while rows arrive (a power cut
loses at most the last 100 ms). A truncated file reads back up to its last complete row, with a
warning.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from softphantom.errors import FileFormatError, UserError
from softphantom.sensing.chain import SensorChain, Tare, to_measurement
from softphantom.sensing.measurement import ARM_NAMES, CHANNEL_NAMES, Measurement

KIND = "softphantom-sensing-recording"
COLUMNS: tuple[str, ...] = (
    ("t_s", "seq", "t_board_s", "osr")
    + tuple(f"raw_{c}" for c in CHANNEL_NAMES)
    + tuple(f"dp_{a}_kPa" for a in ARM_NAMES)
    + tuple(f"dV_{a}_mm3" for a in ARM_NAMES)
    + ("p_urethra_kPa", "status")
)
FSYNC_EVERY_S = 0.1
EVENT_PREFIX = "event:"


class TruncatedRecordingWarning(UserWarning):
    """A recording ended inside a row (e.g. the recorder was killed); the row was dropped."""


def _row(m: Measurement) -> str:
    f = lambda x: "nan" if not math.isfinite(x) else f"{x:.6f}"  # noqa: E731
    cells = [f"{m.t:.6f}", str(m.seq), f"{m.t_board:.6f}", str(m.osr)]
    cells += [str(int(r)) for r in m.raw]
    cells += [f(float(x) / 1e3) for x in m.dp] + [f(float(x) * 1e9) for x in m.dV]
    cells += [f(m.p_urethra / 1e3), m.status.replace(",", ";")]
    return ",".join(cells) + "\n"


class Recorder:
    """Append Measurements to a new file; ``metadata`` (JSON-able dict) goes on the first line.

    Refuses to overwrite an existing file. Call :meth:`tick` when idle so a quiet period still
    gets its fsync; :meth:`close` (or the context manager) ends the file.
    """

    def __init__(self, path, metadata: dict, fsync_every_s: float = FSYNC_EVERY_S,
                 clock: Callable[[], float] = time.monotonic):
        self.path = Path(path)
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644)
        except FileExistsError:
            raise UserError(f"--out {self.path}: exists; recordings are never overwritten") from None
        except OSError as exc:
            raise UserError(f"--out {self.path}: cannot create ({exc.strerror})") from None
        self._fd = fd
        self._clock = clock
        self._every = fsync_every_s
        self._dirty = False
        self.rows = 0
        self.events = 0
        meta = {"kind": KIND, **metadata}
        self._write("# " + json.dumps(meta, separators=(",", ":"), default=str) + "\n"
                    + ",".join(COLUMNS) + "\n")
        os.fsync(fd)
        self._last_sync = clock()

    def _write(self, text: str) -> None:
        data = text.encode()
        while data:                          # os.write straight to the kernel: no user buffer to lose
            n = os.write(self._fd, data)
            data = data[n:]
        self._dirty = True

    def write(self, m: Measurement) -> None:
        self._write(_row(m))
        self.rows += 1
        self.tick()

    def write_event(self, ev) -> None:
        """A marker row for a :class:`~softphantom.sensing.sources.SourceEvent` (synced at once:
        an outage is exactly when the process may die)."""
        status = f"{EVENT_PREFIX}{ev.kind}: {ev.detail}".replace(",", ";").replace("\n", " ")
        self._write(",".join([f"{ev.t:.6f}", "-1", "nan", "0"] + ["0"] * 5 + ["nan"] * 9 + [status]) + "\n")
        self.events += 1
        os.fsync(self._fd)
        self._dirty = False
        self._last_sync = self._clock()

    def tick(self) -> None:
        """fsync if rows were written and the last fsync is older than ``fsync_every_s``."""
        if self._dirty and self._clock() - self._last_sync >= self._every:
            os.fsync(self._fd)
            self._dirty = False
            self._last_sync = self._clock()

    def close(self) -> None:
        if self._fd is not None:
            os.fsync(self._fd)
            os.close(self._fd)
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class Recording:
    """A recording read back (SI units): ``raw`` (n, 5), ``dp`` (n, 4) Pa, ``dV`` (n, 4) m³, ...;
    ``truncated`` when the last row was incomplete and dropped, ``events`` the link events
    (:class:`~softphantom.sensing.sources.SourceEvent`) of the marker rows."""

    meta: dict
    t: np.ndarray
    seq: np.ndarray
    t_board: np.ndarray
    osr: np.ndarray
    raw: np.ndarray
    dp: np.ndarray
    dV: np.ndarray
    p_urethra: np.ndarray
    status: tuple[str, ...]
    truncated: bool = False
    events: tuple = ()

    def __len__(self) -> int:
        return len(self.t)

    def measurements(self) -> Iterator[Measurement]:
        for i in range(len(self.t)):
            yield Measurement(float(self.t[i]), int(self.seq[i]), float(self.t_board[i]), self.raw[i].copy(),
                              int(self.osr[i]), self.dp[i].copy(), self.dV[i].copy(),
                              float(self.p_urethra[i]), self.status[i])


def chain_from_meta(meta: dict) -> SensorChain:
    """The SensorChain a recording was made with (from its ``chain`` metadata)."""
    try:
        return SensorChain(np.asarray(meta["chain"]["v_total_mm3"], float) * 1e-9)
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(f"metadata: no usable chain.v_total_mm3 ({exc})") from None


def retare(rec: Recording, tare: Tare, chain: SensorChain | None = None) -> Recording:
    """A new Recording with dp, dV, p_urethra recomputed from the raw sums with ``tare``."""
    chain = chain or chain_from_meta(rec.meta)
    ms = [to_measurement(rec.t[i], rec.seq[i], rec.t_board[i], rec.raw[i], int(rec.osr[i]), chain, tare)
          for i in range(len(rec))]
    if not ms:
        return replace(rec, meta={**rec.meta, "tare": tare.to_dict()})
    return replace(rec, meta={**rec.meta, "tare": tare.to_dict()},
                   dp=np.array([m.dp for m in ms]), dV=np.array([m.dV for m in ms]),
                   p_urethra=np.array([m.p_urethra for m in ms]), status=tuple(m.status for m in ms))


def read_recording(path) -> Recording:
    """Read a recording; a truncated last row is dropped with a :class:`TruncatedRecordingWarning`.

    Raises :class:`~softphantom.errors.FileFormatError` naming the line for anything else.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    text = data.decode("utf-8", errors="replace")
    lines = text.split("\n")
    complete_end = text.endswith("\n")
    if not complete_end:                     # the last line never got its newline: cut short
        tail = lines.pop()
    else:
        lines.pop()
        tail = ""
    if not lines or not lines[0].startswith("# "):
        raise FileFormatError(f"{path}: line 1: expected '# ' + JSON metadata")
    try:
        meta = json.loads(lines[0][2:])
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"{path}: line 1: metadata is not JSON ({exc.msg} at column {exc.colno + 2})") from None
    if meta.get("kind") != KIND:
        raise FileFormatError(f"{path}: line 1: not a sensing recording (kind {meta.get('kind')!r})")
    if len(lines) < 2:
        raise FileFormatError(f"{path}: line 2: missing the column header (file truncated)")
    header = lines[1].split(",")
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise FileFormatError(f"{path}: line 2: missing columns {', '.join(missing)}")
    idx = [header.index(c) for c in COLUMNS]
    rows = []
    events = []
    t_prev = -math.inf
    from softphantom.sensing.sources import SourceEvent

    for ln, line in enumerate(lines[2:], start=3):
        cells = line.split(",")
        try:
            if len(cells) != len(header):
                raise ValueError(f"{len(cells)} fields, expected {len(header)}")
            c = [cells[i] for i in idx]
            t = float(c[0])
            if not math.isfinite(t):
                raise ValueError(f"t_s is {c[0]}")
            if t < t_prev:
                raise ValueError(f"t_s runs backwards ({t:.6f} after {t_prev:.6f})")
            t_prev = t
            if c[18].startswith(EVENT_PREFIX):
                kind, _, detail = c[18][len(EVENT_PREFIX):].partition(": ")
                events.append(SourceEvent(t, kind, detail))
                continue
            rows.append((t, int(c[1]), float(c[2]), int(c[3]), [int(x) for x in c[4:9]],
                         [float(x) for x in c[9:13]], [float(x) for x in c[13:17]], float(c[17]), c[18]))
        except ValueError as exc:
            raise FileFormatError(f"{path}: line {ln}: {exc}") from None
    truncated = bool(tail)
    if truncated:
        warnings.warn(f"{path}: line {len(lines) + 1} is incomplete ({len(tail)} bytes, the recorder "
                      f"stopped mid-row); read {len(rows)} complete rows", TruncatedRecordingWarning,
                      stacklevel=2)
    n = len(rows)
    col = lambda k, dt=float: np.array([r[k] for r in rows], dtype=dt)  # noqa: E731
    return Recording(
        meta=meta, t=col(0), seq=col(1, np.int64), t_board=col(2), osr=col(3, np.int64),
        raw=np.array([r[4] for r in rows], dtype=np.int64).reshape(n, 5),
        dp=np.array([r[5] for r in rows], float).reshape(n, 4) * 1e3,
        dV=np.array([r[6] for r in rows], float).reshape(n, 4) * 1e-9,
        p_urethra=col(7) * 1e3, status=tuple(r[8] for r in rows), truncated=truncated,
        events=tuple(events))
