"""The estimate message: one flat JSON object per :class:`~softphantom.estimation.Estimate`.

The same object is published on the network stream (ZeroMQ topic ``estimate``), written to the
``/estimate`` channel of a session recording (MCAP) and pushed to the live page. Its keys are the
column names of the estimate CSV (docs/architecture.md) plus ``seq``, ``t_pub_unix_s`` and
``status``, so a message *is* a CSV row; every key carries its unit. See docs/stream.md.

>>> import numpy as np
>>> from softphantom.pose import Pose6
>>> from softphantom.estimation import Estimate
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

import json
import math
from typing import Any, Iterable, Mapping

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.estimation.types import ARM_NAMES, Estimate

SCHEMA_NAME = "softphantom.Estimate"
SCHEMA_VERSION = 1
TOPIC_ESTIMATE = "estimate"
"""ZeroMQ topic (first frame of each multipart message) and, with a leading ``/``, MCAP channel."""

POSE_COLUMNS = ("x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg")
FORCE_COLUMNS = ("force_x_N", "force_y_N", "force_z_N")


def csv_columns(target_names: Iterable[str]) -> list[str]:
    """The estimate CSV header of docs/architecture.md, in order.

    >>> csv_columns(["apex"])[:5]
    ['t_s', 'force_x_N', 'force_y_N', 'force_z_N', 'p_urethra_kPa']
    >>> csv_columns(["apex"])[11:14]
    ['apex_dx_mm', 'apex_dy_mm', 'apex_dz_mm']
    >>> csv_columns([])[-6:]
    ['cond_W', 'qp_status', 'step_ms', 'skipped', 'status', 'in_envelope']
    """
    from softphantom.estimation.stream import estimate_columns  # one definition: the CSV's writer

    return estimate_columns(target_names)


def _num(x: Any) -> float | None:
    """A JSON-safe float: non-finite values become ``None`` (JSON has no NaN/inf)."""
    v = float(x)
    return v if math.isfinite(v) else None


def estimate_to_message(est: Estimate, seq: int, t_pub_unix_s: float) -> dict[str, Any]:
    """The flat, unit-named message of one estimate (see the module docstring)."""
    pose = np.concatenate([np.asarray(est.pose.xyz, float) * 1e3, np.degrees(np.asarray(est.pose.ypr, float))])
    f = np.asarray(est.force, float)
    m: dict[str, Any] = {
        "seq": int(seq),
        "t_s": _num(est.t),
        "t_pub_unix_s": float(t_pub_unix_s),
        "force_x_N": _num(f[0]),
        "force_y_N": _num(f[1]),
        "force_z_N": _num(f[2]),
        "p_urethra_kPa": _num(est.p_urethra * 1e-3),
    }
    for k, v in zip(POSE_COLUMNS, pose):
        m[k] = _num(v)
    for name, d in est.target_shift.items():
        d = np.asarray(d, float) * 1e3
        m[f"{name}_dx_mm"], m[f"{name}_dy_mm"], m[f"{name}_dz_mm"] = (_num(d[0]), _num(d[1]), _num(d[2]))
    vp = np.asarray(est.volume_pred, float) * 1e9
    vm = np.asarray(est.volume_meas, float) * 1e9
    for i, a in enumerate(ARM_NAMES):
        m[f"dVpred_{a}_mm3"] = _num(vp[i])
    for i, a in enumerate(ARM_NAMES):
        m[f"dVmeas_{a}_mm3"] = _num(vm[i])
    m["cond_W"] = _num(est.cond_W)
    m["qp_status"] = str(est.qp_status)
    m["step_ms"] = _num(est.step_time * 1e3)
    m["skipped"] = int(est.skipped)
    m["in_envelope"] = int(bool(est.in_envelope))
    m["status"] = str(est.status)
    return m


def target_names(message: Mapping[str, Any]) -> list[str]:
    """Names of the targets present in a message, in key order.

    >>> target_names({"apex_dx_mm": 0, "apex_dy_mm": 0, "apex_dz_mm": 0, "x_mm": 0})
    ['apex']
    """
    return [k[: -len("_dx_mm")] for k in message if k.endswith("_dx_mm")]


def _f(m: Mapping[str, Any], key: str) -> float:
    try:
        v = m[key]
    except KeyError:
        raise FileFormatError(f"estimate message lacks field {key!r}") from None
    return math.nan if v is None or v == "" else float(v)


def message_to_estimate(m: Mapping[str, Any]) -> Estimate:
    """Rebuild an :class:`Estimate` (SI units) from a message or an estimate-CSV row.

    Raises :class:`~softphantom.errors.FileFormatError` naming the missing field.
    """
    from softphantom.pose import Pose6

    xyz = np.array([_f(m, "x_mm"), _f(m, "y_mm"), _f(m, "z_mm")]) * 1e-3
    ypr = np.radians([_f(m, "yaw_deg"), _f(m, "pitch_deg"), _f(m, "roll_deg")])
    shifts = {
        n: np.array([_f(m, f"{n}_dx_mm"), _f(m, f"{n}_dy_mm"), _f(m, f"{n}_dz_mm")]) * 1e-3
        for n in target_names(m)
    }
    return Estimate(
        t=_f(m, "t_s"),
        force=np.array([_f(m, c) for c in FORCE_COLUMNS]),
        p_urethra=_f(m, "p_urethra_kPa") * 1e3,
        pose=Pose6(xyz, ypr),
        target_shift=shifts,
        volume_pred=np.array([_f(m, f"dVpred_{a}_mm3") for a in ARM_NAMES]) * 1e-9,
        volume_meas=np.array([_f(m, f"dVmeas_{a}_mm3") for a in ARM_NAMES]) * 1e-9,
        cond_W=_f(m, "cond_W"),
        qp_status=str(m.get("qp_status", "")),
        step_time=_f(m, "step_ms") * 1e-3,
        skipped=int(float(m.get("skipped") or 0)),
        status=str(m.get("status", "ok") or "ok"),
        in_envelope=bool(int(float(m.get("in_envelope", 1) if m.get("in_envelope") not in (None, "") else 1))),
    )


def encode(message: Mapping[str, Any]) -> bytes:
    """Compact JSON bytes (UTF-8, no NaN: non-finite numbers are ``null``)."""
    try:
        return json.dumps(message, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:  # a non-finite number somewhere (e.g. a lost tracker frame): rarely, so not checked first
        return json.dumps(_finite(message), separators=(",", ":"), allow_nan=False).encode()


def _finite(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, Mapping):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    return v


def _num_schema(desc: str) -> dict:
    return {"type": ["number", "null"], "description": desc}


ESTIMATE_JSON_SCHEMA: dict[str, Any] = {
    "title": SCHEMA_NAME,
    "description": f"softphantom estimate message v{SCHEMA_VERSION}; keys = estimate CSV columns "
    "(docs/architecture.md) + seq, t_pub_unix_s, status. Frame: origin at the bulb centre at rest, "
    "y = needle insertion, z = up; R = Rz(yaw)·Rx(pitch)·Ry(roll).",
    "type": "object",
    "properties": {
        "seq": {"type": "integer", "description": "publisher sequence number, +1 per estimate; a gap = lost messages"},
        "t_s": _num_schema("estimate time, s (host clock of the sensor sample)"),
        "t_pub_unix_s": {"type": "number", "description": "wall clock at publication, s since the UNIX epoch"},
        **{c: _num_schema(f"external force at p_ext, {c[-1]}") for c in FORCE_COLUMNS},
        "p_urethra_kPa": _num_schema("urethra cavity gauge pressure, kPa"),
        **{c: _num_schema("pose of the marker rigid body relative to rest") for c in POSE_COLUMNS},
        **{f"dVpred_{a}_mm3": _num_schema("predicted cavity volume change, mm³") for a in ARM_NAMES},
        **{f"dVmeas_{a}_mm3": _num_schema("measured cavity volume change, mm³") for a in ARM_NAMES},
        "cond_W": _num_schema("condition number of the 4×4 sensitivity matrix W"),
        "qp_status": {"type": "string"},
        "step_ms": _num_schema("time spent on this estimation step, ms"),
        "skipped": {"type": "integer", "description": "sensor samples skipped since the previous estimate"},
        "status": {"type": "string", "description": "sensor health: 'ok' or a reason; a link event's marker "
                   "(numbers null) is 'event:<kind>: <detail>' (silent, disconnected, reconnected, restart, "
                   "resumed, retared)"},
        "in_envelope": {"type": "integer", "description": "1 inside the load envelope the estimator's model covers, "
                        "0 outside (the estimate is clamped to it)"},
    },
    "patternProperties": {"^.+_d[xyz]_mm$": _num_schema("target shift from rest, mm")},
    "required": ["seq", "t_s", "t_pub_unix_s", *FORCE_COLUMNS, *POSE_COLUMNS],
}
