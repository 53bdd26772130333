"""report.html and its PNGs: 6-DoF plots like the paper's Figs. 8–10, force, error tables,
Table I comparison, and a 3-D view of the deformed phantom (from a VTU snapshot)."""

from __future__ import annotations

import html
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.evaluation.clinical import ClinicalRow, compare_table_i
from softphantom.evaluation.files import Series6
from softphantom.evaluation.metrics import DOF_NAMES, DOF_UNITS, ErrorStats, Evaluation, signed

TRUTH_COLOR = "#1f4e79"
EST_COLOR = "#c0392b"
OUTSIDE_COLOR = "#f0b429"  # estimates clamped at the envelope (the live page's amber)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_6dof(truth: Series6, estimate: Series6, ev: Evaluation, path: Path, title: str = "") -> Path:
    """2×3 panels (x, y, z mm; yaw, pitch, roll deg): truth solid, estimate dashed, the estimate
    shifted back by the lag (stated in the title)."""
    plt = _plt()
    vt, ve = truth.mm_deg(), estimate.mm_deg()
    t0 = ev.t_truth[0]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.2), sharex=True, constrained_layout=True)
    for k, ax in enumerate(axes.flat):
        ax.plot(ev.t_truth - t0, vt[:, k], "-", color=TRUTH_COLOR, lw=1.4, label="truth (tracker)")
        ax.plot(ev.t_est - t0, ve[:, k], "--", color=EST_COLOR, lw=1.4, label="estimate")
        shade_outside(ax, ev.t_est - t0, estimate.in_envelope, label=k == 0)
        ax.set_ylabel(f"{DOF_NAMES[k]} ({DOF_UNITS[k]})")
        ax.grid(True, alpha=0.3)
        s = ev.dof[k]
        ax.set_title(f"{DOF_NAMES[k]}: RMSE {s.rmse:.2f} {s.unit}", fontsize=10)
        if k >= 3:
            ax.set_xlabel("time (s)")
    axes[0, 0].legend(loc="best", fontsize=8)
    shift = lag_caption(ev)
    # a scenario's description can be long: wrap it so the figure never crops it
    fig.suptitle(textwrap.fill(title, 120) + "\n" + shift if title else shift, fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def shade_outside(ax, t: np.ndarray, inside: np.ndarray | None, label: bool = False) -> None:
    """Shade the spans of ``t`` where an estimate was clamped at the envelope (``inside`` False)."""
    if inside is None or inside.all() or len(t) != len(inside):
        return
    out = np.r_[False, ~inside, False].astype(int)
    starts, ends = np.flatnonzero(np.diff(out) == 1), np.flatnonzero(np.diff(out) == -1) - 1
    for j, (a, b) in enumerate(zip(starts, ends)):
        ax.axvspan(t[a], t[b], color=OUTSIDE_COLOR, alpha=0.25, lw=0,
                   label="clamped at the envelope" if label and j == 0 else None)


def tube_advance_ms(estimate: Series6, truth: Series6 | None = None) -> tuple[float, str] | None:
    """How far the lag compensation moved the arm volumes ahead, measured by cross-correlation, with
    the name of the recording it was measured against: the transducers' own volumes (the
    recording's ``dV_*``) against those the estimator was given (the estimate file's ``dVmeas_*``).
    With a truth file that holds the cavities' volumes (a virtual run's ``truth.csv``), each is
    measured against those and the advance is the difference (a slow load, e.g. an inflation, would
    otherwise show the noise both share, at no lag); without one, a measured advance outside half to
    one and a half times the tubes' τ is not reported. The recording is the replayed one (``source``
    ``replay:FILE``) or a ``recording.csv`` beside the estimate (a virtual run's, the demo's); None
    without one, when the arms hardly move, or when the estimate is not compensated."""
    from softphantom.evaluation.files import read_table
    from softphantom.tracking import estimate_lag

    if estimate.meta.get("lag_compensation") != "model" or not estimate.source:
        return None
    here = Path(estimate.source).parent
    src = str(estimate.meta.get("source", ""))
    found = [p for p in ([Path(src[7:]), here / src[7:]] if src.startswith("replay:") else []) + [here / "recording.csv"]
             if p.is_file()]
    if not found:
        return None

    def series(cols, fmt, arms):  # the rows with numbers (marker rows dropped)
        ok = np.isfinite(cols["t_s"]) & np.all([np.isfinite(cols[fmt.format(a)]) for a in arms], axis=0)
        return cols["t_s"][ok], np.column_stack([cols[fmt.format(a)][ok] for a in arms])

    try:
        rec, est = read_table(found[0]).columns, read_table(estimate.source).columns
        arms = [k[len("dVmeas_"):-len("_mm3")] for k in est if k.startswith("dVmeas_") and k.endswith("_mm3")
                and f"dV_{k[len('dVmeas_'):]}" in rec]
        if not arms:
            return None
        r_rec, r_est = series(rec, "dV_{}_mm3", arms), series(est, "dVmeas_{}_mm3", arms)
        tru = read_table(truth.source).columns if truth is not None and truth.source else {}
        if "t_s" in tru and all(f"dV_{a}_mm3" in tru for a in arms):
            ref = series(tru, "dV_{}_mm3", arms)
            before, after = estimate_lag(*ref, *r_rec, max_lag_s=1.0), estimate_lag(*ref, *r_est, max_lag_s=1.0)
            if min(before.peak_corr, after.peak_corr) < 0.8 or before.at_edge or after.at_edge:
                return None
            return before.lag_ms - after.lag_ms, found[0].name
        r = estimate_lag(*r_rec, *r_est, max_lag_s=1.0)
    except (ValueError, OSError, KeyError):  # too short, unreadable: the report says what the model says
        return None
    tau = estimate.meta.get("tube_tau_ms") or [float("nan")]
    if r.peak_corr < 0.8 or r.at_edge or not 0.5 * np.mean(tau) <= -r.lag_ms <= 1.5 * np.mean(tau):
        return None
    return -r.lag_ms, found[0].name


def tube_lag_line(meta: dict, lag_ms: float, advance: tuple[float, str] | None = None) -> str:
    """The report's line about the tubes' lag, from the estimate file's metadata: the tubes' mean
    delay (the model's), the lag before compensation (measured: the lag after plus the advance the
    compensation made, ``advance`` from :func:`tube_advance_ms`, when a recording was found) and after
    (measured by cross-correlation).

    >>> meta = {"lag_compensation": "model", "tube_tau_ms": [102.2, 101.9], "lag_noise_gain_rest": 1.3}
    >>> tube_lag_line(meta, 4.0)
    'compensated (model): the tubes delay the pressures by τ 101.9 … 102.2 ms (model); +4.0 ms remain (measured); noise gain at rest 1.3'
    >>> print(tube_lag_line(meta, 4.0, (98.0, "recording.csv")))  # doctest: +NORMALIZE_WHITESPACE
    compensated (model): the tubes delay the pressures by τ 101.9 … 102.2 ms (model); lag before compensation
    +102.0 ms, after +4.0 ms (measured; the compensation moved the arm volumes 98.0 ms ahead of those in
    recording.csv); noise gain at rest 1.3
    """
    tau = meta.get("tube_tau_ms") or []
    span = (f"{min(tau):.1f} … {max(tau):.1f} ms" if len(set(tau)) > 1 else f"{tau[0]:.1f} ms") if tau else "unknown"
    if meta.get("lag_compensation") == "model":
        gain = f"noise gain at rest {meta.get('lag_noise_gain_rest', float('nan')):g}"
        if advance is not None:
            return (f"compensated (model): the tubes delay the pressures by τ {span} (model); lag before compensation "
                    f"{signed(lag_ms + advance[0])} ms, after {signed(lag_ms)} ms (measured; the compensation moved "
                    f"the arm volumes {advance[0]:.1f} ms ahead of those in {advance[1]}); {gain}")
        return f"compensated (model): the tubes delay the pressures by τ {span} (model); {signed(lag_ms)} ms remain (measured); {gain}"
    note = f" ({meta['lag_compensation_note']})" if meta.get("lag_compensation_note") else ""
    return f"not compensated{note}: the tubes' delay τ {span} is part of the lag above"


def lag_caption(ev: Evaluation) -> str:
    """The 6-DoF figure's line about the lag (signed once, with a true minus).

    >>> from types import SimpleNamespace as E
    >>> lag_caption(E(lag_ms=-148.23, lag=object()))
    'estimate drawn at t − lag, lag −148.2 ms (measured)'
    """
    return f"estimate drawn at t − lag, lag {signed(ev.lag_ms)} ms ({'measured' if ev.lag is not None else 'given'})"


def plot_force(truth: Series6, estimate: Series6, ev: Evaluation, path: Path) -> Path:
    """Force components over time (estimate dashed; the truth solid where known)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(12, 3.4), constrained_layout=True)
    t0 = ev.t_truth[0]
    colors = ("#2e86c1", "#28b463", "#8e44ad")
    for k, a in enumerate("xyz"):
        if truth.force is not None:
            ax.plot(ev.t_truth - t0, truth.force[:, k], "-", color=colors[k], lw=1.4, label=f"F{a} truth")
        ax.plot(ev.t_est - t0, estimate.force[:, k], "--", color=colors[k], lw=1.4, label=f"F{a} estimate")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("force (N)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8, ncol=2)
    ax.set_title("Force at p_ext" + ("" if truth.force is not None else " (estimate only: the truth does not know it)"), fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


@dataclass(frozen=True)
class SnapshotView:
    """The 3-D view's outcome: ``png`` (None if not drawn) and ``note`` (why, or what it shows)."""

    png: Path | None
    note: str


# a tet's faces, outward for a positively oriented tet, by local corner index; VTK's 10-node tet adds
# the mid-edge nodes of (0,1), (1,2), (0,2), (0,3), (1,3), (2,3) as nodes 4..9
_TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
_TET10_EDGE = {(0, 1): 4, (1, 2): 5, (0, 2): 6, (0, 3): 7, (1, 3): 8, (2, 3): 9}
_TET10_FACES = np.array([[a, b, c, _TET10_EDGE[tuple(sorted((a, b)))], _TET10_EDGE[tuple(sorted((b, c)))],
                          _TET10_EDGE[tuple(sorted((c, a)))]] for a, b, c in _TET_FACES])
# a 6-node triangle (corners, then the mid-edge nodes of (0,1), (1,2), (2,0)) as 4 flat ones of the
# same orientation, through all six nodes: the curved face drawn bent
_TRI6_SPLIT = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])


def _boundary_faces(tets: np.ndarray) -> np.ndarray:
    """The faces of ``tets`` (M, 4) or (M, 10) that belong to one tet only: (S, 3) or (S, 6), the
    6-node ones with their mid-edge nodes."""
    local = _TET10_FACES if tets.shape[1] == 10 else _TET_FACES
    faces = tets[:, local].reshape(-1, local.shape[1])
    key = np.sort(faces[:, :3], axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[cnt[inv.ravel()] == 1]


def _outer(faces: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The faces of the boundary component that reaches farthest out (the outer surface, without
    the walls of the cavities inside)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    corners = faces[:, :3]
    n = len(pts)
    rows = np.repeat(corners[:, 0], 2)
    cols = corners[:, 1:].ravel()
    _, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    used = np.unique(corners)
    far = used[np.argmax(np.linalg.norm(pts[used] - pts[used].mean(axis=0), axis=1))]
    return faces[label[corners[:, 0]] == label[far]]


def surface_triangles(mesh) -> np.ndarray | None:
    """The outer surface of a meshio mesh as flat triangles (S, 3): the boundary of its 4- or 10-node
    tets (else its 3- or 6-node triangles), each 6-node triangle as 4 flat ones through its
    mid-edge nodes; None if it has neither."""
    by = {}
    for c in mesh.cells:
        by.setdefault(c.type, []).append(np.asarray(c.data, np.int64))
    pts = np.asarray(mesh.points, float)
    parts = []
    if "tetra" in by or "tetra10" in by:
        for kind in ("tetra", "tetra10"):
            if kind in by:
                parts.append(_outer(_boundary_faces(np.concatenate(by[kind])), pts))
    else:
        parts = [np.concatenate(by[k]) for k in ("triangle", "triangle6") if k in by]
    flat = [f if f.shape[1] == 3 else f[:, _TRI6_SPLIT].reshape(-1, 3) for f in parts]
    return np.concatenate(flat) if flat and sum(map(len, flat)) else None


def plot_snapshot(vtu: Path, path: Path) -> SnapshotView:
    """Draw the outer surface of a VTU mesh (deformed node positions, m or as stored; 4- or 10-node
    tets, or 3- or 6-node triangles, :func:`surface_triangles`), coloured by the magnitude of its
    ``displacement_mm`` point array if present."""
    import meshio

    from softphantom.errors import FileFormatError

    import contextlib
    import io

    if not Path(vtu).is_file():
        raise FileFormatError(f"--snapshot {vtu}: no such file")
    said = io.StringIO()
    try:
        # meshio prints its complaint and calls sys.exit on some broken files: keep both inside
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            mesh = meshio.read(vtu, file_format="vtu")
    except (Exception, SystemExit) as exc:
        why = " ".join(said.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        raise FileFormatError(f"{vtu}: not a readable VTU mesh ({why})") from None
    pts = np.asarray(mesh.points, float)
    faces = surface_triangles(mesh)
    if faces is None:
        kinds = ", ".join(sorted({c.type for c in mesh.cells})) or "no cells"
        return SnapshotView(None, f"{vtu.name} has neither tetrahedra nor triangles ({kinds}): nothing to draw")
    scale, unit = (1e3, "mm") if np.ptp(pts, axis=0).max() < 1.0 else (1.0, "file units")
    P = pts * scale
    disp = mesh.point_data.get("displacement_mm")
    plt = _plt()
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(7.5, 6.5), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    poly = Poly3DCollection(P[faces], linewidths=0.15, edgecolors=(0, 0, 0, 0.25))
    if disp is not None:
        mag = np.linalg.norm(np.asarray(disp, float).reshape(len(pts), -1), axis=1)
        face_mag = mag[faces].mean(axis=1)
        import matplotlib as mpl

        norm = mpl.colors.Normalize(vmin=0.0, vmax=max(float(face_mag.max()), 1e-12))
        cmap = mpl.colormaps["viridis"]
        poly.set_facecolor(cmap(norm(face_mag)))
        sm = mpl.cm.ScalarMappable(norm=norm, cmap=cmap)
        fig.colorbar(sm, ax=ax, shrink=0.6, label="|displacement| (mm)")
        note = f"outer surface of {vtu.name}, coloured by |displacement_mm| (max {mag.max():.2f} mm)"
    else:
        poly.set_facecolor((0.75, 0.75, 0.8, 1.0))
        note = f"outer surface of {vtu.name}; it has no 'displacement_mm' point array, so no colouring"
    ax.add_collection3d(poly)
    lo, hi = P.min(axis=0), P.max(axis=0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")
    ax.set_zlabel(f"z ({unit})")
    ax.view_init(elev=20, azim=-60)
    ax.set_title("Deformed phantom at peak load", fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return SnapshotView(path, note)


def _fmt(v: float, d: int = 2) -> str:
    return "–" if not np.isfinite(v) else f"{v:.{d}f}"


def _table(headers: list[str], rows: list[list[str]], cls: str) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in headers)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


def _stats_rows(stats: tuple[ErrorStats, ...]) -> list[list[str]]:
    return [[html.escape(s.name), s.unit, _fmt(s.rmse), _fmt(s.bias), _fmt(s.max_abs), _fmt(s.corr, 3),
             _fmt(s.lag_ms, 1), _fmt(s.peak_truth), str(s.n)] for s in stats]


_CSS = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1200px;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}th,td{border:1px solid #bbb;padding:3px 8px;text-align:right}
th{background:#eef}td:first-child{text-align:left}.within{color:#1e7d32}.above,.below{color:#b03a2e}
img{max-width:100%;border:1px solid #ddd}.note{color:#555;font-style:italic}
.warn{color:#b36b00;font-weight:bold}"""

STAT_HEADERS = ["quantity", "unit", "RMSE", "bias", "max |error|", "Pearson r", "lag (ms)", "max |truth|", "samples"]


def write_report(
    out: Path,
    truth: Series6,
    estimate: Series6,
    ev: Evaluation,
    snapshot: Path | None = None,
    title: str = "softphantom evaluation",
    clinical: bool = True,
    tube_advance: tuple[float, str] | None | str = "find",
) -> tuple[Path, tuple[ClinicalRow, ...]]:
    """Write ``out/report.html`` and its PNGs; returns the report's path and the Table I rows
    (``clinical``: compare with the paper's Table I, the prostate-motion studies; none for another organ).
    ``tube_advance``: the lag compensation's measured advance (:func:`tube_advance_ms`; ``"find"``:
    measured here from the files next to ``estimate.source``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plot_6dof(truth, estimate, ev, out / "pose_6dof.png", title)
    parts = [f"<h1>{html.escape(title)}</h1>"]
    advance = tube_advance_ms(estimate, truth) if tube_advance == "find" else tube_advance
    lag_txt = (f"{signed(ev.lag_ms)} ms, {html.escape(ev.lag_source)}"
               + (f" (peak correlation {ev.lag.peak_corr:.3f})" if ev.lag is not None else ""))
    info = [
        ["estimate", html.escape(estimate.source)],
        ["truth", html.escape(truth.source)],
        ["truth registration", html.escape(str(truth.meta.get("registration", "as in the truth file (model frame)")))],
        ["lag of the estimate behind the truth", lag_txt],
        *([["what the lag consists of", html.escape(ev.lag_parts.explain())]] if ev.lag_parts is not None else []),
        *([["the tubes' pneumatic lag", html.escape(tube_lag_line(estimate.meta, ev.lag_ms, advance))]]
          if "lag_compensation" in estimate.meta else []),
        ["samples compared", f"{int(ev.mask.sum())} of {len(ev.mask)} estimates"],
    ]
    if estimate.in_envelope is not None:
        k = int(np.count_nonzero(~estimate.in_envelope))
        info.append(["clamped at the estimator's envelope", f"{k} of {len(estimate.in_envelope)} estimates"
                     + (f' <span class="warn">({k / len(estimate.in_envelope):.0%})</span>' if k else "")])
    parts.append('<section id="summary"><h2>Summary</h2>' + _table(["", ""], info, "info"))
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in ev.notes]
    parts.append("<p>Sign convention: a positive lag means the estimate comes later than the truth; errors are"
                 " estimate − truth with the estimate compared at t − lag. Pose: the marker rigid body relative"
                 " to rest in the model frame (translation = displacement of the bulb centre at rest;"
                 " R = Rz(yaw)·Rx(pitch)·Ry(roll)).</p></section>")
    parts.append('<section id="pose"><h2>6-DoF motion</h2><p>Truth solid, estimate dashed (as in the paper\'s'
                 ' Figs. 8–10); the estimate is drawn shifted back by the lag.</p>'
                 '<img src="pose_6dof.png" alt="6-DoF motion: truth and estimate"></section>')
    if estimate.force is not None:
        plot_force(truth, estimate, ev, out / "force.png")
        parts.append('<section id="force"><h2>Force</h2><img src="force.png" alt="force over time"></section>')
    parts.append('<section id="errors"><h2>Errors per DoF</h2>' + _table(STAT_HEADERS, _stats_rows(ev.dof), "errors"))
    if ev.force:
        parts.append("<h3>Force error</h3>" + _table(STAT_HEADERS, _stats_rows(ev.force), "force-errors"))
    if ev.targets:
        hdr = ["target", "unit", "RMS |error|", "mean |error|", "max |error|", "max |truth shift|", "samples"]
        rows_t = [r[:5] + r[7:] for r in _stats_rows(ev.targets)]  # a distance: no correlation, no lag of its own
        parts.append("<h3>Target-shift error (3-D distance)</h3>" + _table(hdr, rows_t, "target-errors"))
    parts.append("</section>")
    rows = compare_table_i(truth.mm_deg(), estimate.mm_deg()) if clinical else ()
    trows = [[r.ref.dof, r.ref.unit, html.escape(r.ref.study), html.escape(r.ref.text), f"{r.ref.lo:g}–{r.ref.hi:g}",
              _fmt(r.observed), _fmt(r.estimated), f'<span class="{r.flag}">{r.flag}</span>'] for r in rows]
    parts.append("" if not clinical else
        '<section id="table-i"><h2>Clinical comparison (paper Table I)</h2><p>Statistic: peak excursion from rest,'
        " max |Δ| over the run, of the truth (observed) and of the estimate; flagged against the range each"
        " published figure stands for (±a → [0, a]; m (lo–hi) → [lo, hi]; m ± sd → [m − sd, m + sd]).</p>"
        + _table(["DoF", "unit", "study", "published", "range", "observed max |Δ|", "estimated max |Δ|", "observed is"],
                 trows, "clinical") + "</section>"
    )
    if snapshot is None:
        snap_html = '<p class="note">No snapshot given (--snapshot FILE.vtu): no 3-D view.</p>'
    else:
        view = plot_snapshot(Path(snapshot), out / "snapshot_3d.png")
        snap_html = f'<p>{html.escape(view.note)}.</p>'
        if view.png is not None:
            snap_html += '<img src="snapshot_3d.png" alt="deformed phantom at peak load">'
    parts.append(f'<section id="snapshot"><h2>Deformed phantom at peak load</h2>{snap_html}</section>')
    doc = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>"
           + html.escape(title) + f"</title><style>{_CSS}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n")
    report = out / "report.html"
    report.write_text(doc, encoding="utf-8")
    return report, rows
