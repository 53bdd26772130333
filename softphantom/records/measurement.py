"""The sensing stage's records: :class:`Measurement` (one sensor sample) and :class:`SourceEvent`
(something that happened to the link), and the one flat form of a measurement."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from softphantom.records.channels import ChannelLayout
from softphantom.records.names import BIP_CAVITIES, EVENT_PREFIX, MEASUREMENT_COLUMNS


@dataclass(frozen=True, eq=False)
class Measurement:
    """One sample of the sensing chain (SI units).

    ``t`` s host clock, ``seq`` frame sequence number, ``t_board`` s board clock (centre of the
    sampling window), ``raw`` ``(n_arms + M,)`` oversampled ADC sums (the arms, then one per
    internal cavity, each in ``0 .. 1023·osr``; the BIP's board: 5), ``osr`` readings summed per
    channel, ``dp`` ``(n_arms,)`` Pa gauge pressure change since tare, ``dV`` ``(n_arms,)`` m³
    cavity volume change (Boyle over cavity + tube), ``p_urethra`` Pa gauge (NaN without a
    urethra), ``status`` ``"ok"`` or a reason (e.g. ``"rail:back_xneg"``), ``pressures_Pa`` the
    internal cavities' gauge pressures by name (None: the BIP's, the urethra's ``p_urethra``).

    >>> m = Measurement(0.0, 1, 0.0, np.array([51200] * 5), 100, np.zeros(4), np.zeros(4), 0.0)
    >>> m.status, m.raw.shape, m.cavity_pressures
    ('ok', (5,), {'urethra': 0.0})
    """

    t: float
    seq: int
    t_board: float
    raw: np.ndarray
    osr: int
    dp: np.ndarray
    dV: np.ndarray
    p_urethra: float
    status: str = "ok"
    pressures_Pa: Mapping[str, float] | None = None

    @property
    def ok(self) -> bool:
        """True when ``status == "ok"``."""
        return self.status == "ok"

    @property
    def cavity_pressures(self) -> dict[str, float]:
        """The internal cavities' gauge pressures (Pa) by name, in the board's order."""
        return _cavity_pressures(self)


EVENT_KINDS = ("silent", "disconnected", "reconnected", "restart", "resumed", "retared")
"""``silent`` no valid frame for ``silence_s``; ``disconnected`` the port failed (unplugged);
``reconnected`` the port opened again; ``restart`` the board clock ran backwards (a reset, a new
board: the UNO resets whenever its port is opened); ``resumed`` frames flow again after one of
these (``detail`` says how long the hole was); ``retared`` a new tare is in force."""


@dataclass(frozen=True)
class SourceEvent:
    """Something that happened to the link at host time ``t`` (s, the measurements' clock)."""

    t: float
    kind: str
    detail: str = ""

    @property
    def status(self) -> str:
        """The ``status`` of its marker row: ``event:<kind>: <detail>``."""
        return f"{EVENT_PREFIX}{self.kind}: {self.detail}"

    @classmethod
    def from_status(cls, t: float, status: str) -> "SourceEvent | None":
        """The event of a marker row's ``status`` (None for a sample's)."""
        if not status.startswith(EVENT_PREFIX):
            return None
        kind, _, detail = status[len(EVENT_PREFIX):].partition(": ")
        return cls(float(t), kind, detail)


def _cavity_pressures(m) -> dict[str, float]:
    given = getattr(m, "pressures_Pa", None)
    return {BIP_CAVITIES[0]: float(m.p_urethra)} if given is None else {k: float(v) for k, v in given.items()}


def measurement_to_message(m: Measurement, layout: ChannelLayout) -> dict[str, Any]:
    """The flat, unit-named form of a measurement of a board of ``layout`` (keys
    :func:`~softphantom.records.names.measurement_columns`): the ``/sensors`` message of a
    recording (read by attribute, so any object with those fields).

    >>> from softphantom.records.channels import BIP_LAYOUT
    >>> msg = measurement_to_message(Measurement(0.5, 3, 0.49, np.arange(5), 100, np.full(4, 1e3),
    ...                                          np.full(4, 1e-9), 2e3), BIP_LAYOUT)
    >>> tuple(msg) == MEASUREMENT_COLUMNS, msg["dp_front_zpos_kPa"], msg["dV_back_xneg_mm3"], msg["raw_urethra"]
    (True, 1.0, 1.0, 4)
    """
    arms = layout.sensing
    if len(np.asarray(m.dV).ravel()) != len(arms):
        raise ValueError(f"a measurement of {len(np.asarray(m.dV).ravel())} volume channels on a board of "
                         f"{len(arms)} ({', '.join(arms)})")
    pressures = _cavity_pressures(m)
    if tuple(pressures) != layout.actuated:
        raise ValueError(f"a measurement of cavities {list(pressures)} on a board of {list(layout.actuated)}")
    msg: dict[str, Any] = {"t_s": float(m.t), "seq": int(m.seq), "t_board_s": float(m.t_board), "osr": int(m.osr)}
    for name, v in zip((*arms, *pressures), np.asarray(m.raw).ravel()):
        msg[f"raw_{name}"] = int(v)
    for a, v in zip(arms, np.asarray(m.dp, float) * 1e-3):
        msg[f"dp_{a}_kPa"] = float(v)
    for a, v in zip(arms, np.asarray(m.dV, float) * 1e9):
        msg[f"dV_{a}_mm3"] = float(v)
    for c, v in pressures.items():
        msg[f"p_{c}_kPa"] = v * 1e-3
    msg["status"] = str(m.status)
    return msg


def measurement_row(m: Measurement, layout: ChannelLayout) -> list[str]:
    """The sensing recording's row of a measurement: its message, times and pressures to 1e-6 of
    their unit (µs, mPa, 1e-6 mm³), raw sums exact."""
    f = lambda x: "nan" if not math.isfinite(x) else f"{x:.6f}"  # noqa: E731
    msg = measurement_to_message(m, layout)
    return [f(v) if isinstance(v, float) else str(v) for v in msg.values()]


def event_row(ev: SourceEvent, layout: ChannelLayout) -> list[str]:
    """The marker row of a link event: its time, ``seq`` −1, ``osr`` 0, empty numbers, its status."""
    n_arms, n_cavities = len(layout.sensing), len(layout.actuated)
    return ([f"{ev.t:.6f}", "-1", "nan", "0"] + ["0"] * (n_arms + n_cavities)
            + ["nan"] * (2 * n_arms + n_cavities) + [ev.status])
