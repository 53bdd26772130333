"""The session file: one ``# {json}`` metadata line, a CSV header with unit-named columns, one row
per record. Estimate files, truth files, sensing recordings and tracker CSVs are all this format;
:class:`SessionWriter` is its one writer and :func:`read_session_file` its one reader (what the
columns mean belongs to the record: :mod:`softphantom.records.names`).

Versioned by ``file_version`` in the metadata: a file without it was written before the key
existed and reads the same; a newer version is refused in one line.

>>> import tempfile, os
>>> p = os.path.join(tempfile.mkdtemp(), "t.csv")
>>> with SessionWriter(p, ["t_s", "x_mm", "status"], {"softphantom": "0.1.0"}) as w:
...     w.write_row([0.0, 1.5, "ok"]); w.write_row([0.01, float("nan"), "a, b"])
>>> open(p).read().splitlines()
['# {"softphantom": "0.1.0", "file_version": 1}', 't_s,x_mm,status', '0.0,1.5,ok', '0.01,,a; b']
>>> f = read_session_file(p)
>>> f.meta["softphantom"], f.header, [cells for _, cells in f.rows]
('0.1.0', ['t_s', 'x_mm', 'status'], [['0.0', '1.5', 'ok'], ['0.01', '', 'a; b']])
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from softphantom.errors import FileFormatError, UserError

FILE_VERSION = 1
"""Version of the format this code writes and the newest it reads."""

VERSION_KEY = "file_version"


class TruncatedRecordingWarning(UserWarning):
    """A file ended inside a row or record (e.g. its writer was killed); that part was dropped."""


def cut_row_note(cut: tuple[int, int, int]) -> str:
    """What :func:`drop_unterminated_line` dropped, in words."""
    line, byte, n = cut
    return f"line {line} (byte {byte}, {n} bytes) ends without a newline: a row cut short, dropped"


def drop_unterminated_line(data: bytes) -> tuple[bytes, tuple[int, int, int] | None]:
    """``data`` without a last line that lacks its newline (a row cut short: a truncated text
    file), and ``(line number, byte offset, length)`` of what was dropped (None when the data end
    with a newline or are empty).

    >>> drop_unterminated_line(b"t_s,x_mm\\n0.0,1.5\\n0.01,-2.2")
    (b't_s,x_mm\\n0.0,1.5\\n', (3, 17, 9))
    """
    if not data or data.endswith((b"\n", b"\r")):
        return data, None
    end = max(data.rfind(b"\n"), data.rfind(b"\r")) + 1
    return data[:end], (len(data[:end].splitlines()) + 1, end, len(data) - end)


def read_complete_lines(path) -> tuple[bytes, tuple[int, int, int] | None]:
    """A text file's bytes up to its last newline, and what :func:`drop_unterminated_line`
    dropped; a FileFormatError when it cannot be read."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read ({exc.strerror})") from None
    return drop_unterminated_line(data)


def warn_truncated(message: str) -> None:
    """A file cut short that was read up to its last complete record (the message says what was
    dropped): a :class:`TruncatedRecordingWarning`, which ``read_truth`` keeps in
    ``meta["warnings"]`` for ``evaluate``."""
    warnings.warn(f"{message} (truncated file)", TruncatedRecordingWarning, stacklevel=3)


def cell(v: Any) -> str:
    """A CSV cell: numbers as their shortest exact repr, nothing for a missing or non-finite one,
    booleans as 1/0, text without the separators.

    >>> [cell(x) for x in (0.1, float("inf"), None, True, 3, "a,b\\nc")]
    ['0.1', '', '', '1', '3', 'a;b c']
    """
    if type(v) is float:                     # the common case first: a row is mostly floats
        return repr(v) if math.isfinite(v) else ""
    if v is None:
        return ""
    if isinstance(v, str):
        return v.replace(",", ";").replace("\n", " ").replace("\r", " ")
    if isinstance(v, (bool,)) or type(v).__name__ == "bool_":
        return "1" if v else "0"
    if isinstance(v, int) or (hasattr(v, "dtype") and v.dtype.kind in "iu"):
        return str(int(v))
    v = float(v)
    return repr(v) if math.isfinite(v) else ""


def meta_line(meta: dict) -> str:
    """The first line: ``# `` + the metadata as compact JSON, with :data:`VERSION_KEY`."""
    return "# " + json.dumps({**meta, VERSION_KEY: FILE_VERSION}, default=str) + "\n"


class OverSessionWriter:
    """Base of a writer of one kind of row over a :class:`SessionWriter` ``_w``: closed with it, and
    a context manager that closes it."""

    _w: "SessionWriter"

    def close(self) -> None:
        self._w.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SessionWriter:
    """Write a session file row by row; every row goes straight to the OS (``os.write``: a killed
    process loses nothing written), fsync'ed at most every ``fsync_every_s`` while rows arrive
    (None: only at :meth:`close`).

    ``meta`` None defers the metadata line and header to :meth:`start` (a writer that learns its
    metadata from the first rows). ``exclusive`` refuses an existing file. ``label`` names the
    output in errors (default ``--out PATH``). :meth:`close` with ``final_meta`` replaces the
    metadata line atomically (counts known only at the end; a crash keeps the file as it was).
    """

    def __init__(self, path, columns: Sequence[str], meta: dict | None = None, *, exclusive: bool = False,
                 fsync_every_s: float | None = None, label: str | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.path = Path(path)
        self.columns = list(columns)
        label = label or f"--out {self.path}"
        flags = os.O_WRONLY | os.O_CREAT | (os.O_EXCL if exclusive else os.O_TRUNC)
        try:
            self._fd: int | None = os.open(self.path, flags, 0o644)
        except FileExistsError:
            raise UserError(f"{label}: exists; recordings are never overwritten") from None
        except OSError as exc:
            raise UserError(f"{label}: cannot create ({exc.strerror})") from None
        self._every = fsync_every_s
        self._clock = clock
        self._dirty = False
        self._last_sync = clock()
        self.meta: dict | None = None
        self.rows = 0
        if meta is not None:
            self.start(meta)

    def start(self, meta: dict) -> None:
        """Write the metadata line and the header (once)."""
        if self.meta is not None:
            raise RuntimeError(f"{self.path}: header written already")
        self.meta = dict(meta)
        self._write(meta_line(self.meta) + ",".join(self.columns) + "\n")
        self.sync()

    def _write(self, text: str) -> None:
        data = text.encode()
        while data:                          # straight to the kernel: no user buffer to lose
            n = os.write(self._fd, data)
            data = data[n:]
        self._dirty = True

    def write_row(self, values: Iterable[Any], sync: bool = False) -> None:
        """One row (values in column order; strings are written as they are, cleaned of separators)."""
        self.write_rows([values], sync)

    def write_rows(self, rows: Iterable[Iterable[Any]], sync: bool = False) -> None:
        """Several rows in one write; ``sync``: fsync now (an outage is when a process may die)."""
        if self.meta is None:
            raise RuntimeError(f"{self.path}: start() first")
        lines = [",".join(cell(v) for v in r) + "\n" for r in rows]
        self._write("".join(lines))
        self.rows += len(lines)
        if sync:
            self.sync()
        else:
            self.tick()

    def tick(self) -> None:
        """fsync if rows were written and the last fsync is older than ``fsync_every_s``."""
        if self._every is not None and self._dirty and self._clock() - self._last_sync >= self._every:
            self.sync()

    def sync(self) -> None:
        os.fsync(self._fd)
        self._dirty = False
        self._last_sync = self._clock()

    def close(self, final_meta: dict | None = None) -> None:
        """fsync and close (idempotent); ``final_meta`` replaces the metadata line."""
        if self._fd is None:
            return
        try:
            os.fsync(self._fd)
        finally:
            os.close(self._fd)
            self._fd = None
        if final_meta is not None and self.meta is not None:
            self.meta = dict(final_meta)
            text = self.path.read_text()
            tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
            try:
                tmp.write_text(meta_line(self.meta) + text.partition("\n")[2])
                os.replace(tmp, self.path)
            finally:
                tmp.unlink(missing_ok=True)

    @property
    def closed(self) -> bool:
        return self._fd is None

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_session_file(path, meta: dict, columns: dict[str, Sequence[Any]]) -> Path:
    """A whole file at once from named columns of equal length."""
    names = list(columns)
    cols = [list(columns[k]) for k in names]
    if len({len(c) for c in cols}) > 1:
        raise ValueError(f"columns differ in length: {dict(zip(names, map(len, cols)))}")
    with SessionWriter(path, names, meta, label=str(path)) as w:
        w.write_rows(zip(*cols))
    return w.path


@dataclass(frozen=True)
class SessionFile:
    """A session file read back: ``meta`` (``{}`` without a metadata line), ``header``,
    ``rows`` as ``(line number, cells)`` (blank lines left out), ``version`` (0: written before
    versions), ``truncated`` (a last row cut short was dropped, with a warning), ``header_line`` its number."""

    path: str
    meta: dict
    header: list[str]
    rows: list[tuple[int, list[str]]] = field(default_factory=list)
    version: int = 0
    truncated: bool = False
    header_line: int = 1

    def require(self, columns: Iterable[str], what: str) -> None:
        """A FileFormatError naming the columns of ``columns`` the header lacks."""
        missing = [c for c in columns if c not in self.header]
        if missing:
            raise FileFormatError(f"{self.path}: the {what} lacks column(s) {', '.join(missing)} "
                                  f"(has: {', '.join(self.header) or 'none'})")


def parse_meta(line: str, path) -> dict:
    """The metadata of a ``# {json}`` first line; a FileFormatError naming the column otherwise."""
    body = line[1:]
    try:
        meta = json.loads(body.strip() or "{}")
    except json.JSONDecodeError as exc:
        col = exc.colno + len(body) - len(body.lstrip()) + 1
        raise FileFormatError(f"{path}: line 1: metadata is not JSON ({exc.msg} at column {col})") from None
    if not isinstance(meta, dict):
        raise FileFormatError(f"{path}: line 1: metadata must be a JSON object")
    v = meta.get(VERSION_KEY, 0)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise FileFormatError(f"{path}: line 1: {VERSION_KEY} must be a whole number, got {v!r}")
    if v > FILE_VERSION:
        raise FileFormatError(f"{path}: line 1: {VERSION_KEY} {v} is newer than this softphantom reads "
                              f"({FILE_VERSION}); update softphantom")
    return meta


def read_session_file(path, *, require_meta: bool = False) -> SessionFile:
    """Read a session file (the metadata line optional unless ``require_meta``). A last line
    without its newline is a row cut short: dropped with a :class:`TruncatedRecordingWarning`
    naming its byte offset. Errors are :class:`~softphantom.errors.FileFormatError` naming the
    line: not UTF-8, bad metadata, no header, duplicate columns, a row of the wrong length."""
    path = Path(path)
    data, cut = read_complete_lines(path)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"{path}: byte {exc.start}: not UTF-8 text") from None
    lines = text.lstrip("\ufeff").splitlines()
    meta: dict = {}
    first = 0
    if lines and lines[0].startswith("#"):
        meta = parse_meta(lines[0], path)
        first = 1
    elif require_meta:
        raise FileFormatError(f"{path}: line 1: expected '# ' + JSON metadata")
    while first < len(lines) and not lines[first].strip():
        first += 1
    if first >= len(lines):
        raise FileFormatError(f"{path}: line {first + 1}: no CSV header line (file empty, only metadata, "
                              "or truncated)")
    rows = list(csv.reader(lines[first:]))
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise FileFormatError(f"{path}: line {first + 1}: duplicate columns {', '.join(dup)}")
    body = []
    for k, r in enumerate(rows[1:]):
        lineno = first + 2 + k
        if not any(c.strip() for c in r):
            continue
        if len(r) != len(header):
            raise FileFormatError(f"{path}: line {lineno}: {len(r)} cells, the header has {len(header)}")
        body.append((lineno, r))
    if cut:
        warnings.warn(f"{path}: {cut_row_note(cut)} (truncated file); {len(body)} complete rows read before "
                      "the incomplete one", TruncatedRecordingWarning, stacklevel=2)
    return SessionFile(str(path), meta, header, body, int(meta.get(VERSION_KEY, 0)), cut is not None, first + 1)
