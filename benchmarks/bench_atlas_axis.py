"""The atlas's f_x axis through the arm pair's step: 1-D interpolation error of volumes and yaw.

    .venv/bin/python benchmarks/bench_atlas_axis.py --model DIR --rows 4.73,-1.1,36.9 5.1,0,0 3.5,0,0

For each row (f_y N, f_z N, p_u kPa): converged solves along f_x over the default envelope's
[−1.5, 1.5] N (61 points, plus 41 inside ±0.1 N where the step is, walked in order from the last
solution), then for each number of points ``--points`` and stretch width ``--widths`` (N; 0 = affine)
the Chebyshev interpolant through the atlas's points on that axis (``cheb_points``, ``axis_t``:
the same polynomial as the atlas's) and its largest error against the scan: volumes (mm³) and yaw
(deg), and where the yaw error is largest. Only the f_x axis: the tensor atlas adds the other axes'
error (``bench_estimate.py --held-out-core``). Figures: docs/estimation.md (session 8).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from numpy.polynomial import chebyshev

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from softphantom.design import BIPDesign, build_model, load_model  # noqa: E402
from softphantom.estimation import EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas import _to_chebyshev, cheb_points  # noqa: E402
from softphantom.estimation.atlas_kernels import axis_t  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from softphantom.pose import Pose6, rigid_fit  # noqa: E402

FX_LO_N, FX_HI_N = -1.5, 1.5


def scan(fwd: ForwardModel, fy: float, fz: float, p_Pa: float, xs: np.ndarray) -> dict:
    """{f_x: (V1..V4 mm³, yaw, pitch, roll deg)} at ``xs``, walked in ascending order."""
    nm = fwd.n_markers
    rest = fwd.rest.sub_x[:nm]
    out, lin = {}, None
    for fx in np.sort(xs):
        lin = fwd.solve([fx, fy, fz, p_Pa], start=lin)
        ypr = Pose6.from_transform(rigid_fit(rest, lin.sub_x[:nm])).to_mm_deg()[3:]
        out[round(float(fx), 9)] = np.r_[lin.V * 1e9, ypr]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model directory (default: the default design at --mesh-size-mm)")
    ap.add_argument("--mesh-size-mm", type=float, default=6.0)
    ap.add_argument("--rows", nargs="+", default=["4.73,-1.1,36.9", "5.1,0,0", "3.5,0,0", "2.0,0,0", "0.5,0,0"],
                    help="f_y N, f_z N, p_u kPa per row")
    ap.add_argument("--points", default="9,11,13", help="f_x points per axis to compare")
    ap.add_argument("--widths", default="0,0.02,0.03,0.05", help="stretch widths w (N; 0: affine)")
    a = ap.parse_args(argv)
    model = load_model(a.model) if a.model else build_model(BIPDesign(), a.mesh_size_mm)
    fwd = ForwardModel(model, EstimatorConfig(), exact_sensitivities=False)
    ns = [int(v) for v in a.points.split(",")]
    ws = [float(v) for v in a.widths.split(",")]
    fine = np.unique(np.r_[np.linspace(FX_LO_N, FX_HI_N, 61), np.linspace(-0.1, 0.1, 41)])
    for row in a.rows:
        fy, fz, p_kPa = (float(v) for v in row.split(","))
        nodes = {round(float(x), 9) for n in ns for w in ws for x in cheb_points(n, FX_LO_N, FX_HI_N, w)}
        t0 = time.perf_counter()
        vals = scan(fwd, fy, fz, p_kPa * 1e3, np.array(sorted(nodes | {round(float(x), 9) for x in fine})))
        ref = np.array([vals[round(float(x), 9)] for x in fine])
        print(f"row f_y {fy} N, f_z {fz} N, p {p_kPa} kPa: {len(vals)} solves in {time.perf_counter() - t0:.0f} s; "
              f"yaw {ref[:, 4].min():.2f}..{ref[:, 4].max():.2f} deg", flush=True)
        for n in ns:
            for w in ws:
                xs = cheb_points(n, FX_LO_N, FX_HI_N, w)
                coef = _to_chebyshev(np.array([vals[round(float(x), 9)] for x in xs]), (n,))
                t = np.array([axis_t(x, FX_LO_N, FX_HI_N, w)[0] for x in fine])
                est = np.stack([chebyshev.chebval(t, coef[:, j]) for j in range(ref.shape[1])], 1)
                err = np.abs(est - ref)
                k = int(np.argmax(err[:, 4]))
                print(f"  {n:2d} points, w {w:.3f} N: volumes {err[:, :4].max():.3f} mm3, yaw {err[:, 4].max():.3f} deg "
                      f"(at f_x {fine[k]:+.3f} N), pitch/roll {err[:, 5:].max():.3f} deg", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
