"""The atlas's f_z and pressure axes: 1-D interpolation error, Lagrange against Hermite points.

    .venv/bin/python benchmarks/bench_atlas_other_axes.py --model DIR --axes f_z p_u --rows 0,1 0.5,3 " -1,2"

(a row starting with a minus sign is quoted with a leading space). For each axis and row (f_x N,
f_y N; the other of f_z / p_u held at ``--held-fz-N`` / ``--held-p-kPa``): converged
force-controlled solves along the axis over the quadratic default envelope's range
(``default_atlas_config(2)``: f_z −2…2 N, p_u −2…40 kPa), ``--scan-points`` uniform plus every
scheme's nodes, walked in ascending order from the last solution, each with the exact derivative
along the axis (``EquilibriumSolver.exact_column``). Then per scheme, Lagrange through n
Chebyshev–Lobatto points (``cheb_points``, the atlas's polynomial) or Hermite through n points
(values and derivatives, ``to_chebyshev(..., hermite=...)``: degree 2n − 1; ``--lagrange``,
``--hermite``), its largest error over the scan: arm volumes (mm³), tracked points (markers and
targets, distance in mm), and the marker pose's yaw and pitch/roll (deg), the pose fitted
(``pose_of_markers``) to the interpolated markers, as the atlas's pose is. Only one axis: the tensor
atlas adds the other axes' errors. Writes benchmarks/results/atlas_other_axes.md
(``--results-name``): the largest errors over the rows per axis and scheme, then per row. Each
scan's exact derivatives are checked against its secants (printed).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from numpy.polynomial import chebyshev

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import add_results_option, markdown_table, write_result  # noqa: E402
from softphantom.design import BIPDesign, build_model, load_model  # noqa: E402
from softphantom.estimation import EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas.basis import cheb_points, to_chebyshev  # noqa: E402
from softphantom.estimation.atlas.config import default_atlas_config  # noqa: E402
from softphantom.estimation.atlas.kernels import axis_t  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from softphantom.pose import pose_of_markers  # noqa: E402

AXES = {"f_z": 2, "p_u": 3}
UNIT = {2: ("N", 1.0), 3: ("kPa", 1e-3)}  # the axis's display unit and its factor from SI
SCHEMES = [("Lagrange", n) for n in (2, 3, 4, 5, 6, 7, 9)] + [("Hermite", n) for n in (2, 3, 4, 5)]  # the default


def axis_range(a: int) -> tuple[float, float, float]:
    """(lo, hi, stretch width) of load ``a`` (SI) on the quadratic model's default atlas."""
    c = default_atlas_config(2)
    return float(c.lower[a]), float(c.upper[a]), float(c.stretch[a])


def key(x: float) -> float:
    return round(float(x), 9)


def scan_axis(fwd: ForwardModel, lam0, a: int, xs) -> dict:
    """{load a: (outputs, d outputs / d load a)} at ``xs`` (SI), the other loads at ``lam0``, walked
    in ascending order; outputs: V1..V4 mm³ then the tracked points' coordinates (mm), flattened."""
    out, lin = {}, None
    for x in np.sort(np.asarray(xs, float)):
        lam = np.array(lam0, float)
        lam[a] = x
        lin = fwd.solve(lam, start=lin)
        dV, dP, _ = fwd.eq.exact_column(lin, a)
        out[key(x)] = (np.r_[lin.V * 1e9, lin.sub_x.ravel() * 1e3], np.r_[dV * 1e9, dP.ravel() * 1e3])
    return out


def derivative_check(scan: dict) -> float:
    """The exact derivatives against the scan's secants: the largest |secant − mean of the two ends'
    derivatives| over neighbouring points, relative to the largest derivative (volumes and points)."""
    xs = sorted(scan)
    d = max(np.abs(s[1]).max() for s in scan.values())
    return max(np.abs((scan[b][0] - scan[a][0]) / (b - a) - 0.5 * (scan[a][1] + scan[b][1])).max()
               for a, b in zip(xs, xs[1:])) / d


def interpolate(nodes, values, derivs, lo: float, hi: float, w: float, xs, hermite: bool) -> np.ndarray:
    """The axis's interpolant at ``xs``: the Chebyshev polynomial through ``values`` (n, m) at the
    n points ``nodes`` (``cheb_points(n, lo, hi, w)``), with ``hermite`` also through ``derivs`` (n, m,
    per unit load): degree 2n − 1, else n − 1."""
    g = np.array([axis_t(x, lo, hi, w)[1] for x in nodes])  # dt/dx at the nodes
    herm = (0, np.asarray(derivs, float) / g[:, None]) if hermite else None
    coef = to_chebyshev(np.asarray(values, float), (len(nodes),), hermite=herm)
    t = np.array([axis_t(x, lo, hi, w)[0] for x in xs])
    return chebyshev.chebval(t, coef).T


def pose_deg(markers_mm: np.ndarray, rest_m: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) deg of the markers' rigid fit from rest."""
    return pose_of_markers(rest_m, markers_mm * 1e-3).to_mm_deg()[3:]


def errors(pred: np.ndarray, ref: np.ndarray, rest_m: np.ndarray) -> np.ndarray:
    """Largest |pred − ref| over the scan (rows): volumes mm³, point distance mm, yaw deg, pitch/roll
    deg (the pose fitted to each side's first ``len(rest_m)`` points, the markers)."""
    nm = len(rest_m)
    dv = np.abs(pred[:, :4] - ref[:, :4]).max()
    pp, pr = pred[:, 4:].reshape(len(pred), -1, 3), ref[:, 4:].reshape(len(ref), -1, 3)
    dp = np.linalg.norm(pp - pr, axis=2).max()
    da = np.abs(np.array([pose_deg(p[:nm], rest_m) - pose_deg(r[:nm], rest_m) for p, r in zip(pp, pr)]))
    return np.array([dv, dp, da[:, 0].max(), da[:, 1:].max()])


def scheme_errors(scan: dict, lo: float, hi: float, w: float, rest_m: np.ndarray, schemes=SCHEMES):
    """Per scheme of ``schemes`` ((name, n) pairs): (name, n, errors over every scanned point)."""
    xs = np.array(sorted(scan))
    ref = np.array([scan[x][0] for x in xs])
    for name, n in schemes:
        nodes = cheb_points(n, lo, hi, w)
        vals = np.array([scan[key(x)][0] for x in nodes])
        ders = np.array([scan[key(x)][1] for x in nodes])
        yield name, n, errors(interpolate(nodes, vals, ders, lo, hi, w, xs, name == "Hermite"), ref, rest_m)


def axis_rows(fwd: ForwardModel, axis: str, a) -> list[list[str]]:
    """Scan ``axis`` at every row of ``a.rows``, print each scheme's errors; the results table's rows."""
    rest_m = fwd.rest.sub_x[:fwd.n_markers]
    ax = AXES[axis]
    lo, hi, w = axis_range(ax)
    unit, f = UNIT[ax]
    xs = {key(x) for x in np.linspace(lo, hi, a.scan_points)}
    schemes = [("Lagrange", n) for n in a.lagrange] + [("Hermite", n) for n in a.hermite]
    xs |= {key(x) for _, n in schemes for x in cheb_points(n, lo, hi, w)}
    table = []
    for row in a.rows:
        fx, fy = (float(v) for v in row.split(","))
        lam0 = [fx, fy, a.held_fz_N, a.held_p_kPa * 1e3]
        held = f"p_u {a.held_p_kPa:g} kPa" if ax == 2 else f"f_z {a.held_fz_N:g} N"
        c0 = time.process_time()
        scan = scan_axis(fwd, lam0, ax, sorted(xs))
        v = np.array([s[0][:4] for s in scan.values()])
        print(f"row f_x {fx:g} N, f_y {fy:g} N, {held}: {len(scan)} solves along {axis} {lo * f:g}..{hi * f:g} "
              f"{unit} in {time.process_time() - c0:.0f} CPU-s; volumes span {np.ptp(v, axis=0).round(2).tolist()} "
              f"mm3; derivatives against the secants: {derivative_check(scan):.1e} of the largest", flush=True)
        for name, n, e in scheme_errors(scan, lo, hi, w, rest_m, schemes):
            print(f"  {name:8s} {n}: volumes {e[0]:.4f} mm3, points {e[1]:.4f} mm, yaw {e[2]:.4f} deg, "
                  f"pitch/roll {e[3]:.4f} deg", flush=True)
            table.append([axis, f"{fx:g}, {fy:g} N; {held}", f"{name} {n}", f"{e[0]:.4f}", f"{e[1]:.4f}",
                          f"{e[2]:.4f}", f"{e[3]:.4f}"])
    return table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model directory (default: the default design at --mesh-size-mm)")
    ap.add_argument("--mesh-size-mm", type=float, default=12.0)
    ap.add_argument("--axes", nargs="+", choices=tuple(AXES), default=list(AXES))
    ap.add_argument("--rows", nargs="+", default=["0,1", "0.5,3", "-1,2"], help="f_x N, f_y N per row")
    ap.add_argument("--held-fz-N", type=float, default=0.0, help="f_z on a pressure scan")
    ap.add_argument("--held-p-kPa", type=float, default=19.0, help="p_u on an f_z scan (the range's middle)")
    ap.add_argument("--scan-points", type=int, default=17, help="uniform scan points (plus every scheme's nodes)")
    ap.add_argument("--lagrange", nargs="+", type=int, default=[n for s, n in SCHEMES if s == "Lagrange"],
                    help="Lagrange point counts to compare")
    ap.add_argument("--hermite", nargs="+", type=int, default=[n for s, n in SCHEMES if s == "Hermite"],
                    help="Hermite point counts to compare")
    add_results_option(ap, "atlas_other_axes")
    a = ap.parse_args(argv)
    model = load_model(a.model) if a.model else build_model(BIPDesign(), a.mesh_size_mm)
    fwd = ForwardModel(model, EstimatorConfig(), exact_sensitivities=False)
    table = []
    for name in a.axes:
        table += axis_rows(fwd, name, a)
    cols = ["volumes mm³", "points mm", "yaw °", "pitch/roll °"]
    worst = {}  # (axis, scheme): the largest errors over the rows
    for r in table:
        worst[r[0], r[2]] = np.maximum(worst.get((r[0], r[2]), 0.0), [float(v) for v in r[3:]])
    summary = markdown_table(["axis", "scheme, points", *cols],
                             [[ax, sc, *(f"{v:.4f}" for v in e)] for (ax, sc), e in worst.items()], right=(2, 3, 4, 5))
    rows = markdown_table(["axis", "row (f_x, f_y; held)", "scheme, points", *cols], table, right=(3, 4, 5, 6))
    write_result(a.results_name, f"{summary}\n\nPer row:\n\n{rows}",
                 caption="Largest 1-D interpolation error along one axis of the quadratic model's default atlas "
                         f"envelope over {len(a.rows)} rows, against the converged solves of a scan ({a.scan_points} "
                         "uniform points and every scheme's nodes).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
