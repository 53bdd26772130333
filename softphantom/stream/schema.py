"""The estimate message: one flat JSON object per :class:`~softphantom.records.Estimate`.

The same object is published on the network stream (ZeroMQ topic ``estimate``), written to the
``/estimate`` channel of a session recording (MCAP) and pushed to the live page. Its keys are the
column names of the estimate file (docs/architecture.md) plus ``seq`` and ``t_pub_unix_s``, so a
message *is* a row; every key carries its unit. Both directions are
:func:`softphantom.records.estimate_to_message` / :func:`~softphantom.records.message_to_estimate`;
this module adds the JSON schema and the encoding. See docs/stream.md.
"""

from __future__ import annotations

import json
import math
from typing import Any, Mapping, Sequence

from softphantom.records.estimate import estimate_to_message, message_to_estimate
from softphantom.records.channels import BIP_LAYOUT, ChannelLayout
from softphantom.records.names import FORCE_COLUMNS, POSE_COLUMNS, target_names
from softphantom.records.names import estimate_columns as csv_columns

__all__ = ["ESTIMATE_JSON_SCHEMA", "SCHEMA_NAME", "SCHEMA_VERSION", "TOPIC_ESTIMATE", "csv_columns", "encode",
           "estimate_json_schema", "estimate_to_message", "message_to_estimate", "target_names"]

SCHEMA_NAME = "softphantom.Estimate"
SCHEMA_VERSION = 1
TOPIC_ESTIMATE = "estimate"
"""ZeroMQ topic (first frame of each multipart message) and, with a leading ``/``, MCAP channel."""


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


def estimate_json_schema(layout: ChannelLayout) -> dict[str, Any]:
    """The JSON schema of the estimate message of a phantom of ``layout``: the pressure keys
    ``p_<cavity>_kPa`` of its actuated cavities and the volume keys ``dVpred_<ch>_mm3`` and
    ``dVmeas_<ch>_mm3`` of its volume channels are listed, in that order, so a recording's schema
    names its cavities.

    >>> s = estimate_json_schema(ChannelLayout(("a", "b", "c"), actuated=("urethra", "tumour")))
    >>> [k for k in s["properties"] if k.startswith("dVmeas_")], s["properties"]["cond_W"]["description"]
    (['dVmeas_a_mm3', 'dVmeas_b_mm3', 'dVmeas_c_mm3'], 'condition number of the 3×5 sensitivity matrix W')
    >>> [k for k in s["properties"] if k.startswith("p_")]
    ['p_urethra_kPa', 'p_tumour_kPa']
    """
    arms, cav = layout.sensing, layout.actuated
    return {
        "title": SCHEMA_NAME,
        "description": f"softphantom estimate message v{SCHEMA_VERSION}; keys = estimate CSV columns "
        "(docs/architecture.md) + seq, t_pub_unix_s, status. Frame: origin at the bulb centre at rest, "
        "y = needle insertion, z = up; R = Rz(yaw)·Rx(pitch)·Ry(roll).",
        "type": "object",
        "properties": {
            "seq": {"type": "integer", "description": "publisher sequence number, +1 per estimate; a gap = lost "
                    "messages"},
            "t_s": _num_schema("estimate time, s (host clock of the sensor sample)"),
            "t_pub_unix_s": {"type": "number", "description": "wall clock at publication, s since the UNIX epoch"},
            **{c: _num_schema(f"external force at p_ext, {c[-1]}") for c in FORCE_COLUMNS},
            **{f"p_{c}_kPa": _num_schema(f"{c} cavity gauge pressure, kPa") for c in cav},
            **{c: _num_schema("pose of the marker rigid body relative to rest") for c in POSE_COLUMNS},
            **{f"dVpred_{a}_mm3": _num_schema("predicted cavity volume change, mm³") for a in arms},
            **{f"dVmeas_{a}_mm3": _num_schema("measured cavity volume change, mm³") for a in arms},
            "cond_W": _num_schema(f"condition number of the {len(arms)}×{3 + len(cav)} sensitivity matrix W"),
            "qp_status": {"type": "string"},
            "step_ms": _num_schema("time spent on this estimation step, ms"),
            "skipped": {"type": "integer", "description": "sensor samples skipped since the previous estimate"},
            "status": {"type": "string", "description": "sensor health: 'ok' or a reason; a link event's marker "
                       "(numbers null) is 'event:<kind>: <detail>' (silent, disconnected, reconnected, restart, "
                       "resumed, retared)"},
            "in_envelope": {"type": "integer", "description": "1 inside the load envelope the estimator's model "
                            "covers, 0 outside (the estimate is clamped to it)"},
        },
        "patternProperties": {"^.+_d[xyz]_mm$": _num_schema("target shift from rest, mm")},
        "required": ["seq", "t_s", "t_pub_unix_s", *FORCE_COLUMNS, *POSE_COLUMNS],
    }


ESTIMATE_JSON_SCHEMA: dict[str, Any] = estimate_json_schema(BIP_LAYOUT)
"""The BIP's estimate schema (:func:`estimate_json_schema` of its four arms)."""


TRACKER_JSON_SCHEMA = {
    "title": "softphantom.TrackerPose", "description": "marker rigid body pose relative to rest, model frame",
    "type": "object",
    "properties": {"t_s": {"type": ["number", "null"]}, **{c: {"type": ["number", "null"]} for c in POSE_COLUMNS},
                   "valid": {"type": "boolean"}, "name": {"type": "string"}}}
"""JSON schema of a tracker pose message (the recording's and the Foxglove server's ``/tracker``)."""
