"""OptiTrack Motive CSV exports (Format Version 1.1x–1.25, Motive 1.x–3.x).

The layout varies between Motive versions and export settings, so every header row is found by
its content, not by its position: the metadata row (starts with ``Format Version``), the type row
(holds ``Rigid Body``), the name row right below it, the property row (``Rotation``/``Position``)
and the axis row (``Frame``, ``Time…``, then ``X``/``Y``/``Z``/``W``). Blank cells are lost
frames. Lengths follow ``Length Units``; rotations are quaternions, or Euler angles in degrees
about the rotating axes in the order ``Rotation Type`` names (e.g. ``XYZ``). Motive 3.1+ (Format
Version 1.24/1.25) adds a ``Parent`` row and IDs such as ``9F:D842698FB0A611F0``; the rows are
still found by content.

Where the file does not say (a spreadsheet re-save drops ``Length Units``; some exports lack
``Rotation Type``) the caller states it (``length_unit=``, ``rotation_order=``); the lengths are
then checked against the rigid body's own markers, which sit a few centimetres apart: a scale that
puts them closer than 3 mm or further than 1 m apart is refused with the numbers.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from softphantom.errors import FileFormatError
from softphantom.records.session import cut_row_note, read_complete_lines, warn_truncated
from softphantom.tracking.track import PoseTrack, make_track, pick_body

_UNITS = {"meters": 1.0, "metres": 1.0, "m": 1.0, "centimeters": 1e-2, "centimetres": 1e-2, "cm": 1e-2,
          "millimeters": 1e-3, "millimetres": 1e-3, "mm": 1e-3}
_UNIT_NAMES = {1.0: "Meters", 1e-2: "Centimeters", 1e-3: "Millimeters"}
_HEADER_SEARCH_ROWS = 50
#: plausible median distance between a rigid body's markers (m)
MARKER_SPACING_M = (0.003, 1.0)
EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def unit_scale(unit: str) -> float:
    """Metres per unit of a length-unit name (``m``, ``cm``, ``mm``, ``Millimeters``, ...).

    >>> unit_scale("Centimeters"), unit_scale("mm")
    (0.01, 0.001)
    """
    try:
        return _UNITS[unit.strip().lower()]
    except KeyError:
        raise FileFormatError(f"unknown length unit {unit!r}; known: m, cm, mm (or Meters, Centimeters, Millimeters)") from None


def sniff(text: str) -> str | None:
    """``"motive-csv"`` when the start of a text file is a Motive CSV export (the metadata row, or
    a header with a ``Type`` row holding a ``Rigid Body``/``Marker`` cell above a ``Frame,Time`` row),
    ``"optitrack-legacy-csv"`` for the pre-1.2 row-typed export, else None."""
    rows = list(csv.reader(io.StringIO(text.lstrip("\ufeff"), newline="")))[:_HEADER_SEARCH_ROWS]
    if not rows:
        return None
    first = [c.strip() for c in rows[0]]
    if first and first[0].lower() == "format version":
        return "motive-csv"
    if any("OptiTrack Export Data" in c for r in rows[:5] for c in r) or (
        first and first[0].lower() in ("comment", "righthanded", "info")
        and any(r and r[0].strip().lower() == "frame" and len(r) > 2 and _is_int(r[1]) for r in rows)
    ):
        return "optitrack-legacy-csv"
    cells = [[c.strip() for c in r] for r in rows]
    type_i = next((i for i, r in enumerate(cells) if "Rigid Body" in r or "Marker" in r), None)
    if type_i is not None and any(
        len(r) > 1 and r[0].lower() == "frame" and r[1].lower().startswith("time") for r in cells[type_i + 1:]
    ):
        return "motive-csv"
    return None


def _is_int(s: str) -> bool:
    return s.strip().isdigit()


def read_optitrack_legacy(path: str | Path, body: str | None = None, **_options) -> PoseTrack:
    """The pre-1.2 OptiTrack export ("OptiTrack Export Data": ``comment``/``info``/``frame`` rows)
    is recognised so that it is refused for what it is, not misread as a Motive CSV."""
    raise FileFormatError(
        f"{path} (legacy OptiTrack export, 'OptiTrack Export Data' with row-typed 'frame,...' lines, before"
        " Motive's Format Version 1.2): this layout is not read; export the take again from Motive as CSV"
        " (Format Version 1.2x) with rigid bodies and their markers"
    )


def _read_rows(path: Path) -> tuple[list[list[str]], list[int], tuple[int, int, int] | None]:
    """The rows (cells stripped), their line numbers, and the last line dropped for lack of its
    newline (:func:`drop_unterminated_line`: a row cut short)."""
    data, cut = read_complete_lines(path)
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
    return rows, lines, cut


def _label(path: Path, version: str) -> str:
    return f"{path} (Motive CSV, Format Version {version})" if version else f"{path} (Motive CSV, no metadata row)"


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
    meta = _metadata(rows[meta_i]) if meta_i is not None else {}
    label = _label(path, meta.get("Format Version", ""))
    axis_i = next((i for i, r in enumerate(head) if len(r) > 1 and r[0].lower() == "frame"
                   and r[1].lower().startswith("time")), None)
    type_i = next((i for i, r in enumerate(head[: axis_i]) if "Rigid Body" in r), None)
    if type_i is None and axis_i is None and len(rows) < _HEADER_SEARCH_ROWS:
        raise FileFormatError(
            f"{label}: the file ends at line {lines[-1]}, inside its header (no 'Rigid Body' type row, no"
            " 'Frame,Time,...' row yet): truncated file?"
        )
    if type_i is None:
        kinds = sorted({c for r in head[: axis_i] for c in r[1:] if c in ("Marker", "Bone", "Skeleton", "Rigid Body Marker")})
        has = f" (it has {', '.join(kinds)} columns only)" if kinds else ""
        raise FileFormatError(
            f"{label}: no rigid body: no 'Rigid Body' cell in the header{has}; export the take with"
            " rigid bodies enabled"
        )
    if axis_i is None:
        raise FileFormatError(
            f"{label}: line {lines[type_i]} has the 'Rigid Body' type row but no 'Frame,Time,...' row follows it"
            " (header incomplete or truncated)"
        )
    if axis_i < type_i + 2:
        raise FileFormatError(f"{label}: line {lines[type_i]}: no name row between the type row and the 'Frame' row")
    # rows between the type row and the axis row, by their label cell: Name, ID, Parent (Motive 3.1+)
    named = {r[1].lower(): i for i in range(type_i + 1, axis_i) if len(r := rows[i]) > 1 and r[1]
             and r[1].lower() in ("name", "id", "parent")}
    name_i = named.get("name", type_i + 1)
    id_i = named.get("id")
    types, names, props, axes = rows[type_i], rows[name_i], rows[axis_i - 1], rows[axis_i]
    ids = rows[id_i] if id_i is not None else []
    bodies = []
    for j, ty in enumerate(types):
        if ty == "Rigid Body" and j < len(names) and names[j] and names[j] not in bodies:
            bodies.append(names[j])
    return {"meta_i": meta_i, "meta": meta, "label": label, "type_i": type_i, "axis_i": axis_i, "types": types,
            "names": names, "ids": ids, "props": props, "axes": axes, "bodies": bodies,
            "parent_row": "parent" in named}


def _cell(row: list[str], j: int) -> str:
    return row[j] if j < len(row) else ""


def _marker_columns(h: dict, body: str, body_id: str) -> list[list[int]]:
    """X, Y, Z column triples of the rigid body's own markers: 'Rigid Body Marker' columns named
    ``body:…``/``body_…`` or sharing its ID, else 'Marker' columns named ``body:…``."""
    found: dict[str, dict[str, int]] = {}
    for kind in ("Rigid Body Marker", "Marker"):
        for j, ty in enumerate(h["types"]):
            name = _cell(h["names"], j)
            if ty != kind or "Position" not in _cell(h["props"], j):
                continue
            mine = name.startswith((f"{body}:", f"{body}_")) or (
                kind == "Rigid Body Marker" and body_id and _cell(h["ids"], j) == body_id
                and not name.startswith(tuple(f"{b}:" for b in h["bodies"] if b != body)))
            if mine:
                found.setdefault(name, {}).setdefault(_cell(h["axes"], j).upper(), j)
        if found:
            break
    return [[c[a] for a in "XYZ"] for c in found.values() if all(a in c for a in "XYZ")]


def _marker_spacing(rows, data_rows, triples) -> tuple[float, int, int]:
    """Median distance between the markers (file units) over the frames where all are seen; the
    number of marker pairs and of frames it used (NaN, 0, 0 when it cannot tell)."""
    if len(triples) < 2:
        return float("nan"), 0, 0
    cols = [j for t in triples for j in t]
    pts = []
    for i in data_rows:
        r = rows[i]
        try:
            v = [float(r[j]) for j in cols]
        except (ValueError, IndexError):
            continue
        pts.append(v)
    if not pts:
        return float("nan"), 0, 0
    p = np.asarray(pts).reshape(len(pts), len(triples), 3)
    iu = np.triu_indices(len(triples), 1)
    d = np.linalg.norm(p[:, iu[0]] - p[:, iu[1]], axis=2)
    return float(np.median(d)), len(iu[0]), len(pts)


def _length_scale(label, line, stated, option, spacing, n_pairs, n_frames, body) -> tuple[float, str]:
    """Metres per file unit, and how it was decided (see the module docstring)."""
    lo, hi = MARKER_SPACING_M
    s_stated = unit_scale(stated) if stated else None
    s_option = unit_scale(option) if option else None
    if s_stated is not None and s_option is not None and s_stated != s_option:
        raise FileFormatError(
            f"{label}: line {line}: the file says Length Units {stated!r}, --length-unit says {option!r}; they disagree"
        )
    scale = s_stated if s_stated is not None else s_option
    how = stated if stated else (f"{_UNIT_NAMES[scale]} (given: the file has no Length Units)" if scale else "")
    seen = f"{spacing:.4g} file units apart (median of {n_pairs} marker pairs over {n_frames} frames)"
    if scale is not None:
        if np.isfinite(spacing) and not lo <= spacing * scale <= hi:
            raise FileFormatError(
                f"{label}: rigid body {body!r}: its markers are {seen}, i.e. {spacing * scale:.4g} m in {_UNIT_NAMES[scale]};"
                f" a rigid body's markers are a few cm apart ({lo * 1e3:g} mm to {hi:g} m): the length unit"
                f" ({how}) cannot be right"
            )
        return scale, how
    if not np.isfinite(spacing):
        raise FileFormatError(
            f"{label}: no 'Length Units' in the metadata and no marker columns of rigid body {body!r} to check the"
            " scale against: give the unit (--length-unit m|cm|mm, or length_unit=)"
        )
    fits = [u for u in (1.0, 1e-2, 1e-3) if lo <= spacing * u <= hi]
    if len(fits) == 1:
        return fits[0], f"{_UNIT_NAMES[fits[0]]} (inferred: no Length Units; the markers are {spacing * fits[0] * 1e3:.1f} mm apart only in this unit)"
    opts = ", ".join(f"{spacing * u * 1e3:.4g} mm in {_UNIT_NAMES[u]}" for u in (1.0, 1e-2, 1e-3))
    raise FileFormatError(
        f"{label}: no 'Length Units' in the metadata; rigid body {body!r}'s markers are {seen} ({opts}):"
        f" {'more than one' if fits else 'no'} unit gives a plausible spacing; give the unit (--length-unit m|cm|mm)"
    )


def _rotation_kind(label, line, stated, option, has_w) -> str:
    """'Quaternion' or an Euler order such as 'XYZ'."""
    opt = option.strip().upper() if option else ""
    if opt and opt not in EULER_ORDERS and opt != "QUATERNION":
        raise FileFormatError(f"--rotation-order must be one of {', '.join(EULER_ORDERS)} (or quaternion), got {option!r}")
    st = stated.strip()
    if st:
        if opt and opt != st.upper():
            raise FileFormatError(f"{label}: line {line}: the file says Rotation Type {stated!r}, --rotation-order says {option!r}")
        if st.lower() == "quaternion" or st.upper() in EULER_ORDERS:
            return "Quaternion" if st.lower() == "quaternion" else st.upper()
        raise FileFormatError(
            f"{label}: line {line}: Rotation Type {stated!r} not understood: expected 'Quaternion' or an Euler order"
            f" ({', '.join(EULER_ORDERS)})"
        )
    if has_w:
        return "Quaternion"
    if opt:
        return "Quaternion" if opt == "QUATERNION" else opt
    raise FileFormatError(
        f"{label}: rotation columns X, Y, Z (Euler angles) but no 'Rotation Type' in the metadata to say their order:"
        f" give it (--rotation-order, one of {', '.join(EULER_ORDERS)}; Motive's default is XYZ)"
    )


def _body_rows(label: str, rows, lines, data_rows, columns: list[int], width: int, body: str, h: dict):
    """The data rows' take time, frame number and the body's ``columns`` as numbers (NaN where
    blank): (t, frame, values, kept), ``kept`` False on blank lines; a short row or a cell that is
    not a number is refused, naming its line and column."""
    n = len(data_rows)
    t = np.full(n, np.nan)
    frame = np.full(n, np.nan)
    vals = np.full((n, len(columns)), np.nan)
    keep = np.zeros(n, bool)
    for k, i in enumerate(data_rows):
        r = rows[i]
        if not any(r):
            continue  # blank line (e.g. at the end)
        if len(r) < width:
            raise FileFormatError(f"{label}: line {lines[i]}: row has {len(r)} cells, rigid body {body!r} needs {width}")
        try:
            t[k] = float(r[1])
        except ValueError:
            raise FileFormatError(f"{label}: line {lines[i]}: time cell {r[1]!r} is not a number") from None
        frame[k] = float(r[0]) if _is_int(r[0]) else np.nan
        for c, j in enumerate(columns):
            cell = r[j]
            if cell:
                try:
                    vals[k, c] = float(cell)
                except ValueError:
                    raise FileFormatError(
                        f"{label}: line {lines[i]}, column {j + 1} ({body} {h['props'][j]} {h['axes'][j]}):"
                        f" {cell!r} is not a number"
                    ) from None
        keep[k] = True
    return t, frame, vals, keep


def _euler_quaternions(ang: np.ndarray, rot_type: str) -> np.ndarray:
    """(n, 4) xyzw of Euler angles ``ang`` (n, 3) in degrees, columns X, Y, Z, applied in the order
    ``rot_type`` (e.g. ``XYZ``); NaN rows where an angle is blank."""
    ok = np.all(np.isfinite(ang), axis=1)
    quat = np.full((len(ang), 4), np.nan)
    if ok.any():
        by_axis = {"X": ang[ok, 0], "Y": ang[ok, 1], "Z": ang[ok, 2]}
        seq = np.column_stack([by_axis[a] for a in rot_type])
        quat[ok] = Rotation.from_euler(rot_type, seq, degrees=True).as_quat()
    return quat


def read_motive_csv(path: str | Path, body: str | None = None, *, length_unit: str | None = None,
                    rotation_order: str | None = None) -> PoseTrack:
    """Read one rigid body of a Motive CSV export into a :class:`PoseTrack` (m, quaternion xyzw).

    ``body`` names the rigid body; it may be left out when the file has only one. The clock is the
    take's ``Time`` column (s from the take's start); the metadata (frame rate, start time,
    units, rotation type, format version) goes to ``meta``. ``length_unit`` (m, cm, mm) and
    ``rotation_order`` (e.g. ``XYZ``) say what the file does not; where the file says it too, they
    must agree.
    """
    path = Path(path)
    rows, lines, cut = _read_rows(path)
    if not rows:
        raise FileFormatError(f"{path} (Motive CSV): " + (f"no complete line: the file ends at byte {cut[2]} inside its"
                                                          " first line (truncated file)" if cut else "empty file"))
    h = _find_header(path, rows, lines)
    meta_row, label = h["meta"], h["label"]
    bodies = h["bodies"]
    if not bodies:
        raise FileFormatError(f"{label}: line {lines[h['type_i'] + 1]}: the rigid body columns have no names")
    body = pick_body(label, bodies, body)

    cols: dict[tuple[str, str], int] = {}
    body_id = ""
    for j, ty in enumerate(h["types"]):
        if ty != "Rigid Body" or _cell(h["names"], j) != body:
            continue
        body_id = body_id or _cell(h["ids"], j)
        prop, ax = _cell(h["props"], j), _cell(h["axes"], j).upper()
        if prop in ("Rotation", "Position") and ax in ("X", "Y", "Z", "W"):
            cols.setdefault((prop, ax), j)
    axis_line = lines[h["axis_i"]]
    meta_line = lines[h["meta_i"]] if h["meta_i"] is not None else 1
    missing_pos = [a for a in "XYZ" if ("Position", a) not in cols]
    if missing_pos:
        raise FileFormatError(
            f"{label}: line {axis_line}: rigid body {body!r} has no Position {'/'.join(missing_pos)} column"
        )
    rot_type = _rotation_kind(label, meta_line, meta_row.get("Rotation Type", ""), rotation_order,
                              ("Rotation", "W") in cols)
    need = ["X", "Y", "Z", "W"] if rot_type == "Quaternion" else ["X", "Y", "Z"]
    missing_rot = [a for a in need if ("Rotation", a) not in cols]
    if missing_rot:
        raise FileFormatError(
            f"{label}: line {axis_line}: rigid body {body!r} lacks Rotation {'/'.join(missing_rot)} column(s) for"
            f" rotation type {rot_type!r}"
        )

    jp = [cols[("Position", a)] for a in "XYZ"]
    jr = [cols[("Rotation", a)] for a in need]
    width = max(jp + jr) + 1
    data_rows = range(h["axis_i"] + 1, len(rows))
    t, frame, vals, keep = _body_rows(label, rows, lines, data_rows, jp + jr, width, body, h)
    if not keep.any():
        raise FileFormatError(f"{label}: line {axis_line}: header found but no data rows follow (truncated file?)")
    t, vals, frame = t[keep], vals[keep], frame[keep]
    total = _float_or_nan(meta_row.get("Total Exported Frames", ""))
    short = f"{len(t)} of the {total:.0f} frames its metadata counts (Total Exported Frames) are in the file"
    truncated = ([cut_row_note(cut)] if cut else []) + ([short] if len(t) < total else [])
    seen = np.all(np.isfinite(vals), axis=1)
    if not seen.any():
        raise FileFormatError(
            f"{label}: rigid body {body!r} is blank in all {len(t)} frames (never tracked in this take)"
            + (f"; the other rigid bodies: {', '.join(b for b in bodies if b != body)}" if len(bodies) > 1 else "")
        )
    spacing, n_pairs, n_frames = _marker_spacing(rows, data_rows, _marker_columns(h, body, body_id))
    scale, units = _length_scale(label, meta_line, meta_row.get("Length Units", ""), length_unit, spacing,
                                 n_pairs, n_frames, body)
    pos = vals[:, :3] * scale
    quat = vals[:, 3:7] if len(jr) == 4 else _euler_quaternions(vals[:, 3:6], rot_type)
    fr = frame[np.isfinite(frame)]
    meta = {
        "format": "motive-csv",
        "format_version": meta_row.get("Format Version", ""),
        "length_units": units,
        "rotation_type": rot_type if meta_row.get("Rotation Type") else
        (f"{rot_type} (given)" if rotation_order else f"{rot_type} (from the W column)"),
        "marker_spacing_mm": spacing * scale * 1e3 if np.isfinite(spacing) else float("nan"),
        "frame_rate_hz": _float_or_nan(meta_row.get("Capture Frame Rate", "")),
        "export_frame_rate_hz": _float_or_nan(meta_row.get("Export Frame Rate", "")),
        "capture_start_time": meta_row.get("Capture Start Time", ""),
        "take_name": meta_row.get("Take Name", ""),
        "body_id": body_id,
        "bodies": bodies,
        "frames_missing": int(fr[-1] - fr[0] + 1 - len(fr)) if len(fr) > 1 else 0,
    }
    if truncated:
        warn_truncated(f"{label}: " + "; ".join(truncated))
    return make_track(t, pos, quat, clock="take_time", source=f"{path} (motive-csv)", name=body, meta=meta)


def _float_or_nan(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        return float("nan")
