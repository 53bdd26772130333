"""The :class:`Estimate` record (estimation → pose/targets → outputs) and its one flat form.

An estimate has one flat, unit-named form, :func:`estimate_to_message`: the JSON message of the
network stream and of a recording's ``/estimate`` channel, and — its values in
:func:`~softphantom.records.names.estimate_columns` order — a row of the estimate file.
:func:`message_to_estimate` reads either back.

>>> from softphantom.pose import Pose6
>>> e = Estimate(t=1.5, force=np.array([0.0, 2.0, 0.0]), p_urethra=1000.0,
...              pose=Pose6(np.array([0.0, 0.004, 0.0]), np.radians([0.0, 3.0, 0.0])),
...              target_shift={"apex": np.array([0.0, 0.001, 0.0])},
...              volume_pred=np.full(4, 1e-9), volume_meas=np.full(4, 2e-9),
...              cond_W=12.0, qp_status="optimal", step_time=0.004)
>>> m = estimate_to_message(e, seq=7, t_pub_unix_s=0.0)
>>> m["seq"], m["force_y_N"], m["y_mm"], round(m["pitch_deg"], 6), m["apex_dy_mm"], m["p_urethra_kPa"]
(7, 2.0, 4.0, 3.0, 1.0, 1.0)
>>> m["dVmeas_front_zpos_mm3"], m["step_ms"]
(2.0, 4.0)
>>> e2 = message_to_estimate(m)
>>> bool(np.allclose(e2.pose.xyz, e.pose.xyz)), float(e2.target_shift["apex"][1])
(True, 0.001)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.pose import Pose6
from softphantom.records.names import (
    ARM_NAMES,
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
class Estimate:
    """One estimate of the phantom's state at time ``t`` (SI units).

    ``force`` N (3,), ``p_urethra`` Pa (NaN without a urethra), ``pose`` of the marker rigid
    body relative to rest,
    ``target_shift`` m per named target, ``volume_pred``/``volume_meas`` cavity volume changes
    m³ (one per arm of ``arm_names``, the sensor order; the BIP's four by default), ``cond_W``
    the condition number of the sensitivity matrix, ``qp_status`` the QP
    solver's status, ``step_time`` s spent on this step, ``skipped`` samples dropped since the
    previous estimate (estimation fell behind and took the newest one), ``in_envelope`` False
    when the loads lie outside the range the estimator's model covers (the atlas's envelope; the
    estimate is then clamped to it), ``pressures_Pa`` the internal cavities' gauge pressures by
    name (None: the BIP's, the urethra's ``p_urethra``; taken from ``extra["pressures_Pa"]``
    when that is where the estimator put them).
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
    arm_names: tuple[str, ...] = ARM_NAMES
    pressures_Pa: Mapping[str, float] | None = None

    def __post_init__(self) -> None:
        if self.pressures_Pa is None and self.extra.get("pressures_Pa") is not None:
            object.__setattr__(self, "pressures_Pa", dict(self.extra["pressures_Pa"]))

    @property
    def cavity_pressures(self) -> dict[str, float]:
        """The internal cavities' gauge pressures (Pa) by name, in the model's order."""
        if self.pressures_Pa is None:
            return {BIP_CAVITIES[0]: float(self.p_urethra)}
        return {k: float(v) for k, v in self.pressures_Pa.items()}

    @property
    def cavity_names(self) -> tuple[str, ...]:
        """The internal cavities (the estimate file's ``p_<cavity>_kPa`` columns)."""
        return BIP_CAVITIES if self.pressures_Pa is None else tuple(self.pressures_Pa)


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


def estimate_row(est: Estimate, targets: Iterable[str], cavity_names: Iterable[str] | None = None) -> list[Any]:
    """The estimate-file row of an estimate: its message's values in column order (the pressure
    columns of ``cavity_names``, default the estimate's own)."""
    m = estimate_to_message(est)
    cav = est.cavity_names if cavity_names is None else cavity_names
    return [m.get(c) for c in estimate_columns(targets, est.arm_names, cav)]


def _f(m: Mapping[str, Any], key: str) -> float:
    try:
        v = m[key]
    except KeyError:
        raise FileFormatError(f"estimate message lacks field {key!r}") from None
    return math.nan if v is None or v == "" else float(v)


def message_to_estimate(m: Mapping[str, Any]) -> Estimate:
    """Rebuild an :class:`Estimate` (SI units) from a message or an estimate-file row (a dict).

    Raises :class:`~softphantom.errors.FileFormatError` naming the missing field.
    """
    v = np.array([_f(m, k) for k in POSE_COLUMNS])
    shifts = {n: np.array([_f(m, k) for k in target_columns(n)]) * 1e-3 for n in target_names(m)}
    env = m.get("in_envelope")
    arms = arm_names_of(m, "dVmeas_") or ARM_NAMES
    cav = pressure_names_of(m)
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
        arm_names=arms,
        pressures_Pa=None if cav == BIP_CAVITIES else pressures,
    )


def marker_estimate(event, target_names: Iterable[str], arm_names: tuple[str, ...] = ARM_NAMES,
                    cavity_names: tuple[str, ...] = BIP_CAVITIES) -> Estimate:
    """The marker of a link event: an Estimate at the event's time with every number NaN and
    ``status`` ``event:<kind>: <detail>`` (``qp_status`` ``none``, nothing skipped), of the
    model's arms and internal cavities.

    >>> from softphantom.records.measurement import SourceEvent
    >>> e = marker_estimate(SourceEvent(12.5, "disconnected", "port failed"), ["apex"])
    >>> e.t, e.status, bool(np.isnan(e.force).all())
    (12.5, 'event:disconnected: port failed', True)
    """
    nan3 = np.full(3, math.nan)
    na, cav = len(arm_names), tuple(cavity_names)
    return Estimate(float(event.t), nan3, math.nan, Pose6(nan3, nan3), {k: nan3 for k in target_names},
                    np.full(na, math.nan), np.full(na, math.nan), math.nan, "none", 0.0, 0,
                    f"{EVENT_PREFIX}{event.kind}: {event.detail}", arm_names=tuple(arm_names),
                    pressures_Pa=None if cav == BIP_CAVITIES else dict.fromkeys(cav, math.nan))


def is_marker(e: Estimate) -> bool:
    return str(e.status).startswith(EVENT_PREFIX)
