"""The project's own session recordings (MCAP, :mod:`softphantom.stream.recording`) as truth:
their ``/tracker`` channel.

A ``/tracker`` message carries the body's pose in one of two forms (both may be present):

- raw, as the tracker sent it: ``position_m`` [x, y, z] m and ``quat_xyzw`` in the tracker's frame
  (``softphantom track`` writes these); the track is then registered like any tracker file;
- registered: ``x_mm … roll_deg`` relative to rest in the model frame (the live view's tracker);
  the track is then taken as it is (``meta["registered"]``).

``t_s`` is the clock, ``valid`` marks lost frames (their pose ``null``), ``name`` the body.
``meta["complete"]`` is False for a recording that was not closed after its last frame (killed,
or its session failed); its messages up to the last complete chunk are read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.pose import matrix_from_ypr, quat_from_matrix
from softphantom.tracking.track import PoseTrack, make_track, pick_body
from softphantom.records.names import POSE_COLUMNS as _REL



def _json(text: str):
    """A metadata value as ``track`` wrote it (JSON numbers, booleans, null); else the text."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def read_recorded_tracker(path: str | Path, body: str | None = None) -> PoseTrack:
    """Read one body's ``/tracker`` messages of a session recording into a :class:`PoseTrack`."""
    from softphantom.stream.recording import read_recording

    path = Path(path)
    label = f"{path} (softphantom-mcap, session recording)"
    try:
        rec = read_recording(path)
    except FileFormatError as exc:
        raise FileFormatError(f"{label}: {exc}") from None
    msgs = rec.tracker
    if not msgs and not rec.complete:
        raise FileFormatError(f"{label}: incomplete recording (the session was killed, or the file cut short): no"
                              f" /tracker message before byte {rec.bytes_read}, where its readable part ends")
    if not msgs:
        others = [k for k, v in (("/estimate", rec.estimates), ("/sensors", rec.sensors)) if v]
        raise FileFormatError(
            f"{label}: no /tracker messages (it has: {', '.join(others) or 'no messages'}); record with a tracker"
            " (softphantom track --out FILE.mcap, or live with a NatNet source)"
        )
    names = sorted({str(m.get("name", "")) for m in msgs})
    body = pick_body(label, names, body, "bodies on /tracker", "body on /tracker")
    msgs = [m for m in msgs if str(m.get("name", "")) == body]
    t = np.array([_num(m.get("t_s")) for m in msgs])
    valid = np.array([bool(m.get("valid", True)) for m in msgs])
    raw = all("position_m" in m and "quat_xyzw" in m for m in msgs)
    if raw:
        pos = np.array([[_num(x) for x in m["position_m"] or (None,) * 3] for m in msgs]).reshape(-1, 3)
        quat = np.array([[_num(x) for x in m["quat_xyzw"] or (None,) * 4] for m in msgs]).reshape(-1, 4)
    elif all(k in m for m in msgs for k in _REL):
        v = np.array([[_num(m[k]) for k in _REL] for m in msgs])
        pos = v[:, :3] * 1e-3
        ok = np.all(np.isfinite(v), axis=1)
        quat = np.full((len(v), 4), np.nan)
        if ok.any():
            quat[ok] = quat_from_matrix(matrix_from_ypr(np.radians(v[ok, 3:])))
    else:
        raise FileFormatError(
            f"{label}: /tracker message {msgs[0].get('t_s')!r} has neither position_m/quat_xyzw nor x_mm..roll_deg"
        )
    pos[~valid] = np.nan
    # complete: closed after its last frame (MCAP's footer; ``track`` also says so in its last metadata record)
    complete = rec.complete and rec.metadata.get("complete", "true") != "false"
    meta = {"format": "softphantom-mcap", "registered": not raw, "complete": complete,
            "frame": "tracker" if raw else "model (relative to rest)",
            **{k: rec.metadata[k] for k in ("softphantom", "natnet_server", "natnet_version") if k in rec.metadata},
            **{k: _json(rec.metadata[k]) for k in ("frames", "frames_body_lost", "joined_mid_take", "first_frame")
               if k in rec.metadata}}
    frames = [m["frame"] for m in msgs if "frame" in m]
    if frames:
        meta["frames_missing"] = int(frames[-1] - frames[0] + 1 - len(set(frames)))
    lat = [m["latency_ms"] for m in msgs if m.get("latency_ms") is not None]
    if lat:
        meta["latency_ms_median"] = float(np.median(lat))
    return make_track(t, pos, quat, clock="recording t_s", source=f"{path} (softphantom-mcap)", name=body, meta=meta)
