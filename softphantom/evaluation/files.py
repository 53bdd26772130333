"""The estimate and truth files (docs/architecture.md): a ``# `` + JSON metadata line, then CSV with
unit-named columns. A truth input may also be any tracker file :mod:`softphantom.tracking` reads;
then it is registered by its rest window (the rest pose is the model's rest pose)."""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.pose import Pose6
from softphantom.records.names import FORCE_COLUMNS, POSE_COLUMNS, pressure_names_of, target_columns, target_names
from softphantom.records.session import TruncatedRecordingWarning, read_session_file, write_session_file


@dataclass(frozen=True)
class Table:
    """A metadata dict and named columns (float arrays; text columns stay str arrays)."""

    meta: dict
    columns: dict[str, np.ndarray]
    path: str = ""


@dataclass(frozen=True)
class Series6:
    """A 6-DoF pose series relative to rest in the model frame, and what else the file knows.

    ``t`` (n,) s; ``pose`` a stack of :class:`Pose6` (m, rad); ``force`` (n, 3) N or None;
    ``p_urethra`` (n,) Pa or None; ``targets`` name → (n, 3) m displacement; ``meta`` the file's
    metadata plus how it was read (registration, clock); ``in_envelope`` (n,) bool, an estimate
    file's flag (False: clamped at the estimator's load envelope), or None; ``pressures``
    internal cavity name → (n,) Pa gauge (its ``p_<cavity>_kPa`` column; the urethra's is also
    ``p_urethra``)."""

    t: np.ndarray
    pose: Pose6
    force: np.ndarray | None = None
    p_urethra: np.ndarray | None = None
    targets: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    source: str = ""
    in_envelope: np.ndarray | None = None
    pressures: dict[str, np.ndarray] = field(default_factory=dict)

    def mm_deg(self) -> np.ndarray:
        """(n, 6): x, y, z mm; yaw, pitch, roll deg."""
        return self.pose.to_mm_deg()


def write_table(path: str | Path, meta: dict, columns: dict[str, np.ndarray]) -> Path:
    """Write a session file (:mod:`softphantom.records.session`) from named columns (floats as
    their shortest exact repr, so epoch timestamps keep their microseconds).

    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "t.csv")
    >>> _ = write_table(p, {"softphantom": "0.1.0"}, {"t_s": [0.0, 0.01], "x_mm": [0.0, 1.5]})
    >>> open(p).read().splitlines()
    ['# {"softphantom": "0.1.0", "file_version": 1}', 't_s,x_mm', '0.0,0.0', '0.01,1.5']
    >>> read_table(p).columns["x_mm"]
    array([0. , 1.5])
    """
    return write_session_file(path, meta, {k: np.asarray(v) for k, v in columns.items()})


def read_table(path: str | Path) -> Table:
    """Read a session file (metadata line optional) into named columns: cells must be numbers
    (empty: NaN) except in the text columns (``qp_status``, ``status`` and any column whose cells
    are all non-numeric). A last line without its newline is a row cut short (a truncated file):
    it is dropped with a :class:`~softphantom.records.TruncatedRecordingWarning` naming its byte
    offset."""
    f = read_session_file(path)
    if not f.rows:
        raise FileFormatError(f"{path}: line {f.header_line}: header but no data rows")
    cols: dict[str, np.ndarray] = {}
    for j, name in enumerate(f.header):
        cells = [r[j].strip() for _, r in f.rows]
        vals = np.empty(len(cells))
        bad = None
        for i, c in enumerate(cells):
            try:
                vals[i] = float(c) if c else np.nan
            except ValueError:
                bad = i
                break
        if bad is None:
            cols[name] = vals
        elif name in ("qp_status", "status") or not any(_is_number(c) for c in cells):
            cols[name] = np.array(cells, dtype=str)
        else:
            raise FileFormatError(f"{path}: line {f.rows[bad][0]}, column {name!r}: {cells[bad]!r} is not a number")
    return Table(f.meta, cols, str(path))


@contextlib.contextmanager
def collect_truncation_warnings(into: list[str]):
    """Move the truncation warnings raised inside into ``into`` (the file's ``meta["warnings"]``,
    which ``evaluate`` reports); other warnings pass on."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield into
    for w in caught:
        if issubclass(w.category, TruncatedRecordingWarning):
            into.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def series_from_table(tab: Table, what: str) -> Series6:
    """A :class:`Series6` from a softphantom table; ``what`` ("estimate"/"truth") for messages."""
    c = tab.columns
    missing = [k for k in ("t_s",) + POSE_COLUMNS if k not in c]
    if missing:
        raise FileFormatError(
            f"{tab.path}: the {what} file lacks column(s) {', '.join(missing)} (has: {', '.join(c) or 'none'})"
        )
    t = c["t_s"]
    v = np.column_stack([c[k] for k in POSE_COLUMNS])
    ok = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    force = None
    if all(k in c for k in FORCE_COLUMNS):
        force = np.column_stack([c[k] for k in FORCE_COLUMNS])[ok]
    pressures = {n: c[f"p_{n}_kPa"][ok] * 1e3 for n in pressure_names_of(c)}
    targets = {}
    for name in target_names(c):
        keys = target_columns(name)
        if all(kk in c for kk in keys):
            targets[name] = np.column_stack([c[kk] for kk in keys])[ok] * 1e-3
    order = np.argsort(t[ok], kind="stable")
    meta = dict(tab.meta)
    meta.setdefault("clock", "file t_s")
    pressures = {k: x[order] for k, x in pressures.items()}
    return Series6(
        t[ok][order], Pose6.from_mm_deg(v[ok][order]),
        None if force is None else force[order], pressures.get("urethra"),
        {k: x[order] for k, x in targets.items()}, meta, tab.path,
        c["in_envelope"][ok][order] > 0.5 if "in_envelope" in c else None, pressures,
    )


def read_estimate(path: str | Path) -> Series6:
    """Read an estimate file (``softphantom estimate --out``); ``meta["warnings"]``: a dropped
    truncated last row."""
    with collect_truncation_warnings([]) as warned:
        est = series_from_table(read_table(path), "estimate")
    est.meta["warnings"] = [*est.meta.get("warnings", ()), *warned]  # the estimator's own (an atlas off at rest)
    return est


def _is_softphantom_csv(head: bytes) -> bool:
    """The project's own CSV: a ``# {json}`` first line, or a header that starts with ``t_s,``
    (a ``#`` alone is not enough: a ROS 1 bag starts with ``#ROSBAG``)."""
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:
            return False
        text = head[: exc.start].decode("utf-8")
    first = text.lstrip("\ufeff").split("\n", 1)[0].strip()
    return first[1:].lstrip().startswith("{") if first.startswith("#") else first.replace(" ", "").startswith("t_s,")


def read_truth(
    path: str | Path,
    *,
    body: str | None = None,
    rest_window_s: tuple[float, float] | None = None,
    clock: str | None = None,
    tracker_to_model=None,
    **options,
) -> Series6:
    """Read the ground truth: a truth CSV, or any tracker file :func:`softphantom.tracking.read_track`
    reads (Motive CSV, ROS 1/2 bag, mcap, NatNet capture, a session recording's ``/tracker``),
    registered into the model frame (by ``tracker_to_model`` if given, else by its rest window:
    default the first 0.5 s of valid samples). ``options`` go to the tracker reader
    (``length_unit``, ``rotation_order``, ``natnet_version``)."""
    from softphantom.tracking import read_track, register_track, track_pose6
    from softphantom.tracking.io import sniff_bytes

    path = Path(path)
    warned: list[str] = []
    with collect_truncation_warnings(warned):
        own_csv = path.is_file() and sniff_bytes(head := _head(path)) is None and _is_softphantom_csv(head)
        if own_csv:
            tab = read_table(path)
        else:
            track = read_track(path, body=body, clock=clock, **options)
    if own_csv:
        return _truth_csv(path, tab, warned)
    if track.meta.get("registered"):  # already relative to rest in the model frame
        if tracker_to_model is not None:
            raise FileFormatError(f"{track.source}: the poses are already in the model frame; no transform applies")
        reg = track
    else:
        reg = register_track(track, tracker_to_model=tracker_to_model, rest_window_s=rest_window_s)
    v = reg.valid
    p6 = track_pose6(reg)
    meta = dict(reg.meta)
    meta.update(clock=reg.clock, body=reg.name, tracker_rate_hz=track.rate_hz, lost_frames=int((~v).sum()))
    meta["warnings"] = warned + _recording_warnings(path, meta, len(track))
    return Series6(reg.t[v], Pose6(p6.xyz[v], p6.ypr[v]), meta=meta, source=reg.source)


def _head(path: Path) -> bytes:
    try:
        with path.open("rb") as fh:
            return fh.read(8192)
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read ({exc.strerror})") from None


def _truth_csv(path: Path, tab: Table, warned: list[str]) -> Series6:
    """A truth CSV; the counts of one that ``softphantom track`` wrote (gap rows, ``complete``,
    ``frames``) checked."""
    if "t_s" in tab.columns and all(k in tab.columns for k in POSE_COLUMNS):
        pose = np.column_stack([tab.columns[k] for k in POSE_COLUMNS])
        n = len(pose)
        lost = int(np.sum(np.isfinite(tab.columns["t_s"]) & ~np.all(np.isfinite(pose), axis=1)))
        if lost == n:
            raise FileFormatError(f"{path}: no pose: the body lost in all {n} frames")
        tab.meta.setdefault("lost_frames", lost)
    series = series_from_table(tab, "truth")
    series.meta["warnings"] = warned + _recording_warnings(path, series.meta, len(tab.columns.get("t_s", ())))
    return series


def _recording_warnings(path, meta: dict, frames: int) -> list[str]:
    """What ``evaluate`` should say about how the truth was recorded: not closed after its last
    frame (``meta["complete"]`` False), fewer frames than its metadata counts, or joined a take
    already under way."""
    out = []
    lost = meta.get("lost_frames", 0)
    missing = meta.get("frames_missing", 0)
    counts = f"{frames} frames, body lost in {lost}" + (f", {missing} missing from the frame numbering" if missing else "")
    expected = meta.get("frames")
    if meta.get("complete") is False:
        out.append(f"{path}: incomplete recording: the session that wrote it did not close it (it failed or was"
                   f" killed; up to its last second may be missing): {counts}")
    elif isinstance(expected, int) and "frames_body_lost" in meta and frames < expected:  # written by track
        out.append(f"{path}: {frames} of the {expected} frames its metadata counts: the file was cut short"
                   f" (truncated copy?); body lost in {lost}")
    if meta.get("joined_mid_take") is True:
        out.append(f"{path}: the recording joined a take already under way (first frame {meta.get('first_frame')}):"
                   " the start of the take is missing, and the rest window is taken from where it joined")
    return out


def write_truth(path: str | Path, series: Series6, meta: dict | None = None) -> Path:
    """Write a :class:`Series6` as a truth file (pose, and force/cavity pressures/targets where known)."""
    cols: dict[str, np.ndarray] = {"t_s": series.t}
    v = series.mm_deg()
    for k, name in enumerate(POSE_COLUMNS):
        cols[name] = v[:, k]
    if series.force is not None:
        for k, name in enumerate(FORCE_COLUMNS):
            cols[name] = series.force[:, k]
    pressures = dict(series.pressures)
    if series.p_urethra is not None:
        pressures.setdefault("urethra", series.p_urethra)
    for name, p in pressures.items():
        cols[f"p_{name}_kPa"] = np.asarray(p) * 1e-3
    for name, d in series.targets.items():
        for k, col in enumerate(target_columns(name)):
            cols[col] = d[:, k] * 1e3
    from softphantom import __version__

    keep = {k: v for k, v in series.meta.items() if k != "warnings"}  # (what reading it found, not the data)
    return write_table(path, {"softphantom": __version__, **keep, **(meta or {})}, cols)
