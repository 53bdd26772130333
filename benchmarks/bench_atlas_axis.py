"""The atlas's first axis through the arm pair's step: 1-D interpolation error of volumes and yaw.

    .venv/bin/python benchmarks/bench_atlas_axis.py --model DIR --rows 4.73,-1.1,36.9 5.1,0,0 3.5,0,0

For each row (f_y N, f_z N, p_u kPa): converged solves along f_x over the default envelope's
[−1.5, 1.5] N (61 points, plus 41 inside ±0.1 N where the step is, walked in order from the last
solution), then for each number of points ``--points`` and stretch width ``--widths`` (N; 0 = affine)
the Chebyshev interpolant through the atlas's points on that axis (``cheb_points``, ``axis_t``:
the same polynomial as the atlas's) and its largest error against the scan: volumes (mm³) and yaw
(deg), and where the yaw error is largest. Only the f_x axis: the tensor atlas adds the other axes'
error (``bench_estimate.py --held-out-core``). Figures: docs/estimation.md.

``--x-control displacement``: the same for a displacement-controlled axis
(``AtlasConfig.x_control``): the scan is uniform in the patch's x-displacement ū_x between the
faces' (``--scan-points``, each point solved at its ū_x by ``_solve_ux`` from the last: one
mixed-control solve; ``--compare-trials`` also times force-controlled trials only in the same run),
the nodes are Chebyshev–Lobatto in q (ū_x mapped onto [−1.5, 1.5] N), and f_x joins the outputs (its error
in N: the force the atlas reports).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial

import numpy as np
from numpy.polynomial import chebyshev

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from softphantom.design import BIPDesign, build_model, load_model  # noqa: E402
from softphantom.estimation import EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas.basis import cheb_points, to_chebyshev  # noqa: E402
from softphantom.estimation.atlas.build import _solve_ux, x_patch  # noqa: E402
from softphantom.estimation.atlas.kernels import axis_t  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from softphantom.pose import pose_of_markers  # noqa: E402

FX_LO_N, FX_HI_N = -1.5, 1.5


def scan(fwd: ForwardModel, fy: float, fz: float, p_Pa: float, xs: np.ndarray) -> dict:
    """{f_x: (V1..V4 mm³, yaw, pitch, roll deg)} at ``xs``, walked in ascending order."""
    nm = fwd.n_markers
    rest = fwd.rest.sub_x[:nm]
    out, lin = {}, None
    for fx in np.sort(xs):
        lin = fwd.solve([fx, fy, fz, p_Pa], start=lin)
        ypr = pose_of_markers(rest, lin.sub_x[:nm]).to_mm_deg()[3:]
        out[round(float(fx), 9)] = np.r_[lin.V * 1e9, ypr]
    return out


def scan_u(fwd: ForwardModel, fy: float, fz: float, p_Pa: float, qs: np.ndarray, bordered: bool = True,
           counter: list | None = None) -> dict:
    """{q: (V1..V4 mm³, yaw, pitch, roll deg, f_x N)} at the q values ``qs`` (N-equivalent: the
    patch displacement ū_x mapped from the faces' onto [FX_LO_N, FX_HI_N]), walked in ascending
    order, each solved to 1e-7 of the faces' ū_x range (``bordered``: by the mixed-control solve,
    else by force-controlled trials only; ``counter`` [0] gets the converged solves added)."""
    nm = fwd.n_markers
    rest = fwd.rest.sub_x[:nm]
    h = x_patch(fwd)

    def row(lin):
        ypr = pose_of_markers(rest, lin.sub_x[:nm]).to_mm_deg()[3:]
        return np.r_[lin.V * 1e9, ypr, lin.lam[0]]

    lo = fwd.solve([FX_LO_N, fy, fz, p_Pa])
    hi = fwd.solve([FX_HI_N, fy, fz, p_Pa])
    u0, u1 = (float(h @ (lin.x - fwd.fem.x_rest)) for lin in (lo, hi))
    out, lin = {}, lo
    for q in np.sort(qs):
        if q <= FX_LO_N or q >= FX_HI_N:
            out[round(float(q), 9)] = row(lo if q <= FX_LO_N else hi)
            continue
        target = u0 + (q - FX_LO_N) / (FX_HI_N - FX_LO_N) * (u1 - u0)
        guess = np.array([lin.lam[0], fy, fz, p_Pa])
        lin, n = _solve_ux(fwd, h, guess, target, lin, (FX_LO_N, FX_HI_N), 1e-7 * abs(u1 - u0), bordered)
        if counter is not None:
            counter[0] += n
        out[round(float(q), 9)] = row(lin)
    return out


def scan_row(scan_fn, fwd, row: str, ns, ws, fine):
    """One row "f_y,f_z,p_kPa" scanned by ``scan_fn`` at every axis point of ``ns`` × ``ws`` and at
    ``fine``: (f_y, f_z, p_kPa, {axis value: outputs}, outputs at ``fine``, seconds)."""
    fy, fz, p_kPa = (float(v) for v in row.split(","))
    nodes = {round(float(x), 9) for n in ns for w in ws for x in cheb_points(n, FX_LO_N, FX_HI_N, w)}
    t0 = time.perf_counter()
    vals = scan_fn(fwd, fy, fz, p_kPa * 1e3, np.array(sorted(nodes | {round(float(x), 9) for x in fine})))
    return fy, fz, p_kPa, vals, np.array([vals[round(float(x), 9)] for x in fine]), time.perf_counter() - t0


def interpolation_errors(vals: dict, fine: np.ndarray, ref: np.ndarray, ns, ws):
    """Per number of points ``n`` and stretch ``w``: (n, w, |interpolant − scan| (len(fine), m), the
    index of the largest yaw error) — the Chebyshev interpolant through the axis's points
    (``cheb_points``, ``axis_t``: the atlas's polynomial) of the scanned values ``vals``."""
    for n in ns:
        for w in ws:
            xs = cheb_points(n, FX_LO_N, FX_HI_N, w)
            coef = to_chebyshev(np.array([vals[round(float(x), 9)] for x in xs]), (n,))
            t = np.array([axis_t(x, FX_LO_N, FX_HI_N, w)[0] for x in fine])
            err = np.abs(np.stack([chebyshev.chebval(t, coef[:, j]) for j in range(ref.shape[1])], 1) - ref)
            yield n, w, err, int(np.argmax(err[:, 4]))


def main_displacement(a, fwd) -> int:
    ns = [int(v) for v in a.points.split(",")]
    ws = [float(v) for v in a.widths.split(",")]
    fine = np.linspace(FX_LO_N, FX_HI_N, a.scan_points)
    for r in a.rows:
        n_b = [0]
        c0 = time.process_time()
        fy, fz, p_kPa, vals, ref, secs = scan_row(partial(scan_u, counter=n_b), fwd, r, ns, ws, fine)
        cpu = time.process_time() - c0
        print(f"row f_y {fy} N, f_z {fz} N, p {p_kPa} kPa: {len(vals)} points at their ū_x in {secs:.0f} s "
              f"({cpu:.0f} CPU-s of this process, {n_b[0]} converged solves, mixed control); yaw "
              f"{ref[:, 4].min():.2f}..{ref[:, 4].max():.2f} deg; f_x at q = 0: "
              f"{vals[0.0][7] if 0.0 in vals else float('nan'):+.4f} N", flush=True)
        if a.compare_trials:  # the peer: force-controlled trials only, same points, same run
            n_t = [0]
            c0 = time.process_time()
            *_, ref_t, secs_t = scan_row(partial(scan_u, bordered=False, counter=n_t), fwd, r, ns, ws, fine)
            cpu_t = time.process_time() - c0
            print(f"  peer, force-controlled trials: {secs_t:.0f} s ({cpu_t:.0f} CPU-s, {n_t[0]} converged "
                  f"solves): {secs_t / secs:.2f}x the wall time, {cpu_t / cpu:.2f}x the CPU; the two scans "
                  f"differ by at most volumes {np.abs(ref_t[:, :4] - ref[:, :4]).max():.2e} mm3, yaw "
                  f"{np.abs(ref_t[:, 4] - ref[:, 4]).max():.2e} deg, f_x {np.abs(ref_t[:, 7] - ref[:, 7]).max():.2e} N",
                  flush=True)
        for n, w, err, k in interpolation_errors(vals, fine, ref, ns, ws):
            print(f"  {n:2d} points in q, w {w:.3f}: volumes {err[:, :4].max():.3f} mm3, yaw {err[:, 4].max():.3f} deg "
                  f"(at q {fine[k]:+.3f}, f_x {ref[k, 7]:+.4f} N), pitch/roll {err[:, 5:7].max():.3f} deg, "
                  f"f_x {err[:, 7].max():.4f} N", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model directory (default: the default design at --mesh-size-mm)")
    ap.add_argument("--mesh-size-mm", type=float, default=6.0)
    ap.add_argument("--rows", nargs="+", default=["4.73,-1.1,36.9", "5.1,0,0", "3.5,0,0", "2.0,0,0", "0.5,0,0"],
                    help="f_y N, f_z N, p_u kPa per row")
    ap.add_argument("--points", default="9,11,13", help="f_x points per axis to compare")
    ap.add_argument("--widths", default="0,0.02,0.03,0.05", help="stretch widths w (N; 0: affine)")
    ap.add_argument("--x-control", choices=("force", "displacement"), default="force",
                    help="the axis: f_x (force-controlled) or the patch displacement (AtlasConfig.x_control)")
    ap.add_argument("--scan-points", type=int, default=121, help="displacement scan: points uniform in q")
    ap.add_argument("--compare-trials", action="store_true",
                    help="displacement scan: the same points again by force-controlled trials only (the peer)")
    a = ap.parse_args(argv)
    model = load_model(a.model) if a.model else build_model(BIPDesign(), a.mesh_size_mm)
    fwd = ForwardModel(model, EstimatorConfig(), exact_sensitivities=False)
    if a.x_control == "displacement":
        return main_displacement(a, fwd)
    ns = [int(v) for v in a.points.split(",")]
    ws = [float(v) for v in a.widths.split(",")]
    fine = np.unique(np.r_[np.linspace(FX_LO_N, FX_HI_N, 61), np.linspace(-0.1, 0.1, 41)])
    for row in a.rows:
        fy, fz, p_kPa, vals, ref, secs = scan_row(scan, fwd, row, ns, ws, fine)
        print(f"row f_y {fy} N, f_z {fz} N, p {p_kPa} kPa: {len(vals)} solves in {secs:.0f} s; "
              f"yaw {ref[:, 4].min():.2f}..{ref[:, 4].max():.2f} deg", flush=True)
        for n, w, err, k in interpolation_errors(vals, fine, ref, ns, ws):
            print(f"  {n:2d} points, w {w:.3f} N: volumes {err[:, :4].max():.3f} mm3, yaw {err[:, 4].max():.3f} deg "
                  f"(at f_x {fine[k]:+.3f} N), pitch/roll {err[:, 5:].max():.3f} deg", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
