"""The :class:`Estimate` record (estimation → pose/targets → outputs) and its one flat form.

An estimate has one flat, unit-named form, :func:`estimate_to_message`: the JSON message of the
network stream and of a recording's ``/estimate`` channel, and — its values in
:func:`~softphantom.records.names.estimate_columns` order — a row of the estimate file.
:func:`message_to_estimate` reads either back.

>>> from softphantom.pose import Pose6
>>> from softphantom.records.channels import BIP_LAYOUT
>>> e = Estimate(t=1.5, force=np.array([0.0, 2.0, 0.0]), p_urethra=1000.0,
...              pose=Pose6(np.array([0.0, 0.004, 0.0]), np.radians([0.0, 3.0, 0.0])),
...              target_shift={"apex": np.array([0.0, 0.001, 0.0])},
...              volume_pred=np.full(4, 1e-9), volume_meas=np.full(4, 2e-9),
...              cond_W=12.0, qp_status="optimal", step_time=0.004, layout=BIP_LAYOUT)
>>> m = estimate_to_message(e, seq=7, t_pub_unix_s=0.0)
>>> m["seq"], m["force_y_N"], m["y_mm"], round(m["pitch_deg"], 6), m["apex_dy_mm"], m["p_urethra_kPa"]
(7, 2.0, 4.0, 3.0, 1.0, 1.0)
>>> m["dVmeas_front_zpos_mm3"], m["step_ms"]
(2.0, 4.0)
>>> e2 = message_to_estimate(m, BIP_LAYOUT)
>>> bool(np.allclose(e2.pose.xyz, e.pose.xyz)), float(e2.target_shift["apex"][1]), e2.layout == BIP_LAYOUT
(True, 0.001, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.pose import Pose6
from softphantom.records.channels import ChannelLayout, ChannelNames
from softphantom.records.names import (
    BIP_CAVITIES,
    EVENT_PREFIX,
    FORCE_COLUMNS,
    POSE_COLUMNS,
    arm_names_of,
    estimate_columns,
    pressure_names_of,
    target_columns,
    target_names,
)


@dataclass(frozen=True)
class Estimate(ChannelNames):
    """One estimate of the phantom's state at time ``t`` (SI units).

    ``force`` N (3,), ``p_urethra`` Pa (NaN without a urethra), ``pose`` of the marker rigid
    body relative to rest,
    ``target_shift`` m per named target, ``volume_pred``/``volume_meas`` cavity volume changes
    m³ (one per volume channel of ``layout``, the phantom's :class:`~softphantom.records.channels.ChannelLayout`:
    its ``sensing``, in the sensor order), ``cond_W``
    the condition number of the sensitivity matrix, ``qp_status`` the QP
    solver's status, ``step_time`` s spent on this step, ``skipped`` samples dropped since the
    previous estimate (estimation fell behind and took the newest one), ``in_envelope`` False
    when the loads lie outside the range the estimator's model covers (the atlas's envelope; the
    estimate is then clamped to it), ``pressures_Pa`` the internal cavities' gauge pressures by
    name (None: the urethra's ``p_urethra`` for a layout that actuates it; taken from
    ``extra["pressures_Pa"]`` when that is where the estimator put them).
    """

    t: float
    force: np.ndarray
    p_urethra: float
    pose: Pose6
    target_shift: dict[str, np.ndarray]
    volume_pred: np.ndarray
    volume_meas: np.ndarray
    cond_W: float
    qp_status: str
    step_time: float
    skipped: int = 0
    status: str = "ok"
    in_envelope: bool = True
    extra: dict = field(default_factory=dict)
    pressures_Pa: Mapping[str, float] | None = None
    layout: ChannelLayout = field(kw_only=True)

    def __post_init__(self) -> None:
        if self.pressures_Pa is None and self.extra.get("pressures_Pa") is not None:
            object.__setattr__(self, "pressures_Pa", dict(self.extra["pressures_Pa"]))

    @property
    def cavity_pressures(self) -> dict[str, float]:
        """The actuated cavities' gauge pressures (Pa) by name, in the layout's order."""
        given = {} if self.pressures_Pa is None else self.pressures_Pa
        return {c: float(given[c]) if c in given else float(self.p_urethra) if c == BIP_CAVITIES[0] else math.nan
                for c in self.layout.actuated}


def _num(x: Any) -> float | None:
    """A JSON-safe float: non-finite values become ``None`` (JSON has no NaN/inf)."""
    v = float(x)
    return v if math.isfinite(v) else None


def _nums(a: Any, scale: float = 1.0) -> list[float | None]:
    return [v if math.isfinite(v) else None for v in (np.asarray(a, float).ravel() * scale).tolist()]


def estimate_to_message(est: Estimate, seq: int | None = None, t_pub_unix_s: float | None = None) -> dict[str, Any]:
    """The flat, unit-named form of one estimate: the estimate-file columns (non-finite numbers
    ``None``), plus ``seq`` and ``t_pub_unix_s`` when given (the stream's)."""
    m: dict[str, Any] = {}
    if seq is not None:
        m["seq"] = int(seq)
    m["t_s"] = _num(est.t)
    if t_pub_unix_s is not None:
        m["t_pub_unix_s"] = float(t_pub_unix_s)
    m.update(zip(FORCE_COLUMNS, _nums(est.force)))
    for c, p in est.cavity_pressures.items():
        m[f"p_{c}_kPa"] = _num(p * 1e-3)
    m.update(zip(POSE_COLUMNS, _nums(est.pose.xyz, 1e3) + _nums(np.degrees(np.asarray(est.pose.ypr, float)))))
    for name, d in est.target_shift.items():
        m.update(zip(target_columns(name), _nums(d, 1e3)))
    m.update(zip([f"dVpred_{a}_mm3" for a in est.arm_names], _nums(est.volume_pred, 1e9)))
    m.update(zip([f"dVmeas_{a}_mm3" for a in est.arm_names], _nums(est.volume_meas, 1e9)))
    m["cond_W"] = _num(est.cond_W)
    m["qp_status"] = str(est.qp_status)
    m["step_ms"] = _num(est.step_time * 1e3)
    m["skipped"] = int(est.skipped)
    m["in_envelope"] = int(bool(est.in_envelope))
    m["status"] = str(est.status)
    return m


def estimate_row(est: Estimate, targets: Iterable[str]) -> list[Any]:
    """The estimate-file row of an estimate: its message's values in column order (its layout's)."""
    m = estimate_to_message(est)
    return [m.get(c) for c in estimate_columns(targets, est.layout)]


def _f(m: Mapping[str, Any], key: str) -> float:
    try:
        v = m[key]
    except KeyError:
        raise FileFormatError(f"estimate message lacks field {key!r}") from None
    return math.nan if v is None or v == "" else float(v)


def message_layout(m: Mapping[str, Any]) -> ChannelLayout:
    """The layout a bare estimate message names by its keys (``dVmeas_<channel>_mm3``,
    ``p_<cavity>_kPa``; its volume channels all as arms: the keys do not tell a measured cavity
    from an arm), for a message received without the stream's metadata. A message without volume
    keys is refused (:class:`~softphantom.errors.FileFormatError`)."""
    arms = arm_names_of(m, "dVmeas_")
    if not arms:
        raise FileFormatError("estimate message has no dVmeas_<channel>_mm3 field: its channels are unknown")
    return ChannelLayout(arms, (), pressure_names_of(m))


def message_to_estimate(m: Mapping[str, Any], layout: ChannelLayout | None = None) -> Estimate:
    """Rebuild an :class:`Estimate` (SI units) from a message or an estimate-file row (a dict), of
    ``layout`` (its file's or stream's; None: the one its keys name, :func:`message_layout`).

    Raises :class:`~softphantom.errors.FileFormatError` naming the missing field.
    """
    v = np.array([_f(m, k) for k in POSE_COLUMNS])
    shifts = {n: np.array([_f(m, k) for k in target_columns(n)]) * 1e-3 for n in target_names(m)}
    env = m.get("in_envelope")
    layout = message_layout(m) if layout is None else layout
    arms, cav = layout.sensing, layout.actuated
    pressures = {c: _f(m, f"p_{c}_kPa") * 1e3 for c in cav}
    return Estimate(
        t=_f(m, "t_s"),
        force=np.array([_f(m, c) for c in FORCE_COLUMNS]),
        p_urethra=pressures.get(BIP_CAVITIES[0], math.nan),
        pose=Pose6.from_mm_deg(v),
        target_shift=shifts,
        volume_pred=np.array([_f(m, f"dVpred_{a}_mm3") for a in arms]) * 1e-9,
        volume_meas=np.array([_f(m, f"dVmeas_{a}_mm3") for a in arms]) * 1e-9,
        cond_W=_f(m, "cond_W"),
        qp_status=str(m.get("qp_status", "")),
        step_time=_f(m, "step_ms") * 1e-3,
        skipped=int(float(m.get("skipped") or 0)),
        status=str(m.get("status", "ok") or "ok"),
        in_envelope=bool(int(float(env))) if env not in (None, "") else True,
        pressures_Pa=None if cav == BIP_CAVITIES else pressures,
        layout=layout,
    )


def marker_estimate(event, target_names: Iterable[str], layout: ChannelLayout) -> Estimate:
    """The marker of a link event: an Estimate at the event's time with every number NaN and
    ``status`` ``event:<kind>: <detail>`` (``qp_status`` ``none``, nothing skipped), of the
    model's ``layout``.

    >>> from softphantom.records.channels import BIP_LAYOUT
    >>> from softphantom.records.measurement import SourceEvent
    >>> e = marker_estimate(SourceEvent(12.5, "disconnected", "port failed"), ["apex"], BIP_LAYOUT)
    >>> e.t, e.status, bool(np.isnan(e.force).all())
    (12.5, 'event:disconnected: port failed', True)
    """
    nan3 = np.full(3, math.nan)
    na = len(layout.sensing)
    return Estimate(float(event.t), nan3, math.nan, Pose6(nan3, nan3), {k: nan3 for k in target_names},
                    np.full(na, math.nan), np.full(na, math.nan), math.nan, "none", 0.0, 0,
                    f"{EVENT_PREFIX}{event.kind}: {event.detail}", layout=layout)


def is_marker(e: Estimate) -> bool:
    return str(e.status).startswith(EVENT_PREFIX)
