"""The value object every tracker reader returns, and what the readers share (the body picker, the
handling of a file cut short)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PoseTrack:
    """A rigid body's pose over time, in the tracker's own frame and clock (SI units).

    ``t`` (n,) s on the clock named by ``clock``; ``position`` (n, 3) m; ``quat_xyzw`` (n, 4);
    ``valid`` (n,) bool (False for lost frames: their position/quaternion are NaN); ``source``
    the file and its format; ``name`` the rigid body; ``meta`` what the file said besides
    (frame rate, units, the other clock's offset, ...).
    """

    t: np.ndarray
    position: np.ndarray
    quat_xyzw: np.ndarray
    valid: np.ndarray
    clock: str
    source: str
    name: str
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.t)
        if self.position.shape != (n, 3) or self.quat_xyzw.shape != (n, 4) or self.valid.shape != (n,):
            raise ValueError(
                f"PoseTrack arrays disagree: t {self.t.shape}, position {self.position.shape},"
                f" quat_xyzw {self.quat_xyzw.shape}, valid {self.valid.shape}"
            )

    def __len__(self) -> int:
        return len(self.t)

    def only_valid(self) -> "PoseTrack":
        """A new track with the lost frames dropped."""
        v = self.valid
        return PoseTrack(
            self.t[v], self.position[v], self.quat_xyzw[v], self.valid[v], self.clock, self.source, self.name,
            dict(self.meta),
        )

    @property
    def rate_hz(self) -> float:
        """Median sample rate over the valid frames (NaN with fewer than 2)."""
        tv = self.t[self.valid]
        return float(1.0 / np.median(np.diff(tv))) if len(tv) > 1 else float("nan")


def pick_body(label: str, available: list[str], body: str | None, what: str = "rigid bodies",
              one: str = "rigid body") -> str:
    """``body``, or the only one ``available``; a FileFormatError listing them otherwise.

    >>> pick_body("take.csv", ["bip"], None)
    'bip'
    """
    from softphantom.errors import FileFormatError

    if body is None:
        if len(available) != 1:
            raise FileFormatError(f"{label}: {len(available)} {what}, choose one with body=: {', '.join(available)}")
        return available[0]
    if body not in available:
        raise FileFormatError(f"{label}: no {one} named {body!r}; the file has: {', '.join(available)}")
    return body


def make_track(t, position, quat_xyzw, *, clock: str, source: str, name: str, meta: dict | None = None) -> PoseTrack:
    """Build a :class:`PoseTrack`, marking non-finite or zero-norm samples invalid (set to NaN)."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(position, dtype=float).reshape(-1, 3)
    q = np.asarray(quat_xyzw, dtype=float).reshape(-1, 4)
    qn = np.linalg.norm(q, axis=1)
    valid = np.isfinite(t) & np.all(np.isfinite(p), axis=1) & np.isfinite(qn) & (qn > 0.5)
    p = np.where(valid[:, None], p, np.nan)
    q = np.where(valid[:, None], q / np.where(qn > 0, qn, 1.0)[:, None], np.nan)
    order = np.argsort(t, kind="stable")
    if np.any(order != np.arange(len(t))):
        t, p, q, valid = t[order], p[order], q[order], valid[order]
    return PoseTrack(t, p, q, valid, clock, source, name, dict(meta or {}))


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


def cut_row_note(cut: tuple[int, int, int]) -> str:
    """What :func:`drop_unterminated_line` dropped, in words."""
    line, byte, n = cut
    return f"line {line} (byte {byte}, {n} bytes) ends without a newline: a row cut short, dropped"


def warn_truncated(message: str) -> None:
    """A file cut short that was read up to its last complete record (the message says what was
    dropped): a :class:`~softphantom.sensing.recording.TruncatedRecordingWarning`, which
    ``read_truth`` keeps in ``meta["warnings"]`` for ``evaluate``."""
    import warnings

    from softphantom.sensing.recording import TruncatedRecordingWarning

    warnings.warn(f"{message} (truncated file)", TruncatedRecordingWarning, stacklevel=3)
