"""The tracking stage's record: :class:`PoseTrack`, what every tracker reader returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softphantom.errors import FileFormatError


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
