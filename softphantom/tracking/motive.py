"""OptiTrack Motive CSV exports (Format Version 1.1x–1.2x).

The layout varies between Motive versions and export settings, so every header row is found by
its content, not by its position: the metadata row (starts with ``Format Version``), the type row
(holds ``Rigid Body``), the name row right below it, the property row (``Rotation``/``Position``)
and the axis row (``Frame``, ``Time…``, then ``X``/``Y``/``Z``/``W``). Blank cells are lost
frames. Lengths follow ``Length Units``; rotations are quaternions, or Euler angles in degrees
about the rotating axes in the order ``Rotation Type`` names (e.g. ``XYZ``).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from softphantom.errors import FileFormatError
from softphantom.tracking.track import PoseTrack, make_track

_UNITS = {"meters": 1.0, "metres": 1.0, "m": 1.0, "centimeters": 1e-2, "centimetres": 1e-2, "cm": 1e-2,
          "millimeters": 1e-3, "millimetres": 1e-3, "mm": 1e-3}
_HEADER_SEARCH_ROWS = 50


def _read_rows(path: Path) -> tuple[list[list[str]], list[int], bool]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise FileFormatError(f"{path}: line {line} (byte {exc.start}): not UTF-8 text; is this a Motive CSV?") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    rows, lines = [], []
    try:
        for row in reader:
            rows.append([c.strip() for c in row])
            lines.append(reader.line_num)
    except csv.Error as exc:
        raise FileFormatError(f"{path}: line {reader.line_num + 1}: {exc}") from None
    return rows, lines, text.endswith(("\n", "\r"))


def _metadata(row: list[str]) -> dict[str, str]:
    return {row[i]: row[i + 1] for i in range(0, len(row) - 1, 2) if row[i]}


def rigid_bodies(path: str | Path) -> list[str]:
    """Names of the rigid bodies in a Motive CSV export."""
    rows, lines, _ = _read_rows(Path(path))
    h = _find_header(Path(path), rows, lines)
    return h["bodies"]


def _find_header(path: Path, rows: list[list[str]], lines: list[int]) -> dict:
    head = rows[:_HEADER_SEARCH_ROWS]
    meta_i = next((i for i, r in enumerate(head) if r and r[0].lower() == "format version"), None)
    type_i = next((i for i, r in enumerate(head) if "Rigid Body" in r), None)
    if type_i is None:
        raise FileFormatError(
            f"{path}: no rigid body: none of the first {min(len(rows), _HEADER_SEARCH_ROWS)} lines has a"
            " 'Rigid Body' type cell (a Motive export with rigid bodies enabled is needed)"
        )
    axis_i = next(
        (i for i in range(type_i + 1, len(head)) if len(rows[i]) > 1 and rows[i][0].lower() == "frame"
         and rows[i][1].lower().startswith("time")),
        None,
    )
    if axis_i is None:
        raise FileFormatError(
            f"{path}: line {lines[type_i]} has the 'Rigid Body' type row but no 'Frame,Time,...' row follows it"
            " (header incomplete or truncated)"
        )
    if axis_i < type_i + 2:
        raise FileFormatError(f"{path}: line {lines[type_i]}: no name row between the type row and the 'Frame' row")
    types, names, props, axes = rows[type_i], rows[type_i + 1], rows[axis_i - 1], rows[axis_i]
    bodies = []
    for j, ty in enumerate(types):
        if ty == "Rigid Body" and j < len(names) and names[j] and names[j] not in bodies:
            bodies.append(names[j])
    return {"meta_i": meta_i, "type_i": type_i, "axis_i": axis_i, "types": types, "names": names,
            "props": props, "axes": axes, "bodies": bodies}


def read_motive_csv(path: str | Path, body: str | None = None) -> PoseTrack:
    """Read one rigid body of a Motive CSV export into a :class:`PoseTrack` (m, quaternion xyzw).

    ``body`` names the rigid body; it may be left out when the file has only one. The clock is the
    take's ``Time`` column (s from the take's start); the metadata (frame rate, start time,
    units, rotation type, format version) goes to ``meta``.
    """
    path = Path(path)
    rows, lines, ends_with_newline = _read_rows(path)
    if not rows:
        raise FileFormatError(f"{path}: empty file")
    h = _find_header(path, rows, lines)
    meta_row = _metadata(rows[h["meta_i"]]) if h["meta_i"] is not None else {}
    bodies = h["bodies"]
    if not bodies:
        raise FileFormatError(f"{path}: line {lines[h['type_i'] + 1]}: the rigid body columns have no names")
    if body is None:
        if len(bodies) > 1:
            raise FileFormatError(f"{path}: {len(bodies)} rigid bodies, choose one with body=: {', '.join(bodies)}")
        body = bodies[0]
    elif body not in bodies:
        raise FileFormatError(f"{path}: no rigid body named {body!r}; the file has: {', '.join(bodies)}")

    cols: dict[tuple[str, str], int] = {}
    for j, ty in enumerate(h["types"]):
        if ty != "Rigid Body" or j >= len(h["names"]) or h["names"][j] != body:
            continue
        prop = h["props"][j] if j < len(h["props"]) else ""
        ax = h["axes"][j].upper() if j < len(h["axes"]) else ""
        if prop in ("Rotation", "Position") and ax in ("X", "Y", "Z", "W"):
            cols.setdefault((prop, ax), j)
    axis_line = lines[h["axis_i"]]
    missing_pos = [a for a in "XYZ" if ("Position", a) not in cols]
    if missing_pos:
        raise FileFormatError(
            f"{path}: line {axis_line}: rigid body {body!r} has no Position {'/'.join(missing_pos)} column"
        )

    rot_type = meta_row.get("Rotation Type", "")
    has_w = ("Rotation", "W") in cols
    if not rot_type:
        rot_type = "Quaternion" if has_w else ""
    if rot_type.lower() == "quaternion":
        need = ["X", "Y", "Z", "W"]
    elif sorted(rot_type.upper()) == ["X", "Y", "Z"]:
        need = ["X", "Y", "Z"]
    else:
        raise FileFormatError(
            f"{path}: rotation type {rot_type or '(none)'!r} not understood: expected 'Quaternion' or an Euler"
            " order such as 'XYZ' in the metadata row"
        )
    missing_rot = [a for a in need if ("Rotation", a) not in cols]
    if missing_rot:
        raise FileFormatError(
            f"{path}: line {axis_line}: rigid body {body!r} lacks Rotation {'/'.join(missing_rot)} column(s) for"
            f" rotation type {rot_type!r}"
        )

    units = meta_row.get("Length Units", "")
    if units:
        if units.lower() not in _UNITS:
            raise FileFormatError(f"{path}: line {lines[h['meta_i']]}: unknown Length Units {units!r}")
        scale = _UNITS[units.lower()]
    else:
        scale, units = 1.0, "Meters (assumed: no 'Length Units' in the metadata)"

    jp = [cols[("Position", a)] for a in "XYZ"]
    jr = [cols[("Rotation", a)] for a in need]
    width = max(jp + jr) + 1
    data_rows = range(h["axis_i"] + 1, len(rows))
    n = len(data_rows)
    t = np.full(n, np.nan)
    vals = np.full((n, 3 + len(jr)), np.nan)
    keep = np.zeros(n, bool)
    for k, i in enumerate(data_rows):
        r = rows[i]
        if not any(r):
            continue  # blank line (e.g. at the end)
        if len(r) < width:
            last = i == len(rows) - 1
            why = " (truncated file?)" if last and not ends_with_newline else ""
            raise FileFormatError(
                f"{path}: line {lines[i]}: row has {len(r)} cells, rigid body {body!r} needs {width}{why}"
            )
        try:
            t[k] = float(r[1])
        except ValueError:
            raise FileFormatError(f"{path}: line {lines[i]}: time cell {r[1]!r} is not a number") from None
        for c, j in enumerate(jp + jr):
            cell = r[j]
            if cell:
                try:
                    vals[k, c] = float(cell)
                except ValueError:
                    raise FileFormatError(
                        f"{path}: line {lines[i]}, column {j + 1} ({body} {h['props'][j]} {h['axes'][j]}):"
                        f" {cell!r} is not a number"
                    ) from None
        keep[k] = True
    if not keep.any():
        raise FileFormatError(f"{path}: line {axis_line}: header found but no data rows follow (truncated file?)")
    t, vals = t[keep], vals[keep]
    pos = vals[:, :3] * scale
    if len(jr) == 4:
        quat = vals[:, 3:7]
    else:
        ang = vals[:, 3:6]  # columns X, Y, Z; the order of application is the rotation type's
        order = rot_type.upper()
        ok = np.all(np.isfinite(ang), axis=1)
        quat = np.full((len(t), 4), np.nan)
        if ok.any():
            by_axis = {"X": ang[ok, 0], "Y": ang[ok, 1], "Z": ang[ok, 2]}
            seq = np.column_stack([by_axis[a] for a in order])
            quat[ok] = Rotation.from_euler(order, seq, degrees=True).as_quat()
    meta = {
        "format": "motive-csv",
        "format_version": meta_row.get("Format Version", ""),
        "length_units": units,
        "rotation_type": rot_type,
        "frame_rate_hz": _float_or_nan(meta_row.get("Capture Frame Rate", "")),
        "export_frame_rate_hz": _float_or_nan(meta_row.get("Export Frame Rate", "")),
        "capture_start_time": meta_row.get("Capture Start Time", ""),
        "take_name": meta_row.get("Take Name", ""),
        "bodies": bodies,
    }
    return make_track(t, pos, quat, clock="take_time", source=f"{path} (motive-csv)", name=body, meta=meta)


def _float_or_nan(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        return float("nan")
