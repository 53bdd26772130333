"""CPU seconds a grid point of the atlas build, by kind, on the real model with a handful of points.

A whole default build of the 28 329-node quadratic model takes hours; its cost is the points'
costs summed over the task graph. This measures each kind of point the build solves, with the
build's own code (``atlas.solves._sweep``'s solver settings, ``atlas.solves._lines``), at the grid
points of the default atlas (``default_atlas_config(2)``), f_z index ``--k`` and pressure index
``--l``, for each piece and each line given by ``--lines`` (piece:f_y index):

- **from rest**: a face point solved from rest (continuation in 1 N steps): what the centre of a
  face plane (or a segment seeded without a neighbour) costs;
- **face**: the face point one f_y grid step further, from its solved neighbour (the face walk's step);
- **line**: one line along q between the two faces (``_lines`` with every other line masked):
  its inner points (mixed-control solves, the Hermite-f_z derivatives);
- **factor**, **back-solve**: one factorization of the tangent and one solve with it.

    nice -n 10 .venv/bin/python benchmarks/bench_atlas_point_cost.py [--model DIR] [--lines 0:2 1:3 1:5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import add_results_option, write_table  # noqa: E402

import softphantom  # noqa: E402,F401 - one BLAS thread before numpy loads
import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None, help="model directory (default: the shipped quadratic model)")
    ap.add_argument("--lines", nargs="+", default=["0:2", "1:3", "1:5"], help="piece:f_y index of each line")
    ap.add_argument("--k", type=int, default=2, help="f_z index")
    ap.add_argument("--l", type=int, default=0, help="pressure index")
    add_results_option(ap, "atlas_point_cost")
    a = ap.parse_args()

    from softphantom.design import load_model
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.build import _axis_derivative, _lines
    from softphantom.estimation.atlas.config import FALLBACK_MIN_LOAD_STEP, default_atlas_config, x_patch
    from softphantom.estimation.forward import ForwardModel
    from softphantom.fem.solve import free_tangent

    path = a.model or os.path.join(os.path.dirname(softphantom.__file__), "data", "models", "bip_p2")
    model = load_model(path)
    cfg = EstimatorConfig()
    pieces = default_atlas_config(model.element_order).pieces()
    rows = []

    def fwd_new():
        return ForwardModel(model, cfg, exact_sensitivities=False, fallback_min_load_step=FALLBACK_MIN_LOAD_STEP)

    def timed(fn, *args, **kw):
        c = time.process_time()
        out = fn(*args, **kw)
        return out, time.process_time() - c

    # the linear algebra alone
    fwd = fwd_new()
    x = fwd.fem.x_rest.copy()
    _, t_asm = timed(free_tangent, fwd.fem, x, None)
    _, t_fac = timed(fwd.eq.factorize, x, 0.0)
    b = np.ones(len(fwd.fem.free_dofs))
    _, t_sol = timed(fwd.eq.lin.solve, b)
    print(f"tangent assembly {t_asm:.2f} CPU-s, factorization {t_fac:.2f}, back-solve {t_sol:.3f}", flush=True)
    rows.append(["tangent: assembly, factorization, back-solve", "", f"{t_asm:.2f}, {t_fac:.2f}, {t_sol:.3f}", "", ""])

    for spec in a.lines:
        p, j = (int(v) for v in spec.split(":"))
        acfg = pieces[p]
        ax = acfg.axes()
        n1, ny = len(ax[0]), len(ax[1])
        k, l = a.k, a.l
        where = f"piece {p} (f_y {ax[1][0]:.1f}…{ax[1][-1]:.1f} N), f_y {ax[1][j]:.2f} N, f_z {ax[2][k]:+.1f} N, " \
                f"p_u {ax[3][l] / 1e3:.0f} kPa"
        h = None
        faces = []
        for i in (0, n1 - 1):
            fwd = fwd_new()
            h = x_patch(fwd)
            lam = np.array([ax[0][i], ax[1][j], ax[2][k], ax[3][l]])
            lin, c_rest = timed(fwd.solve, lam, None, via_tol=1e-3)
            (_, _, dX, _), c_der = timed(_axis_derivative, fwd, lin, acfg.hermite_axis, None)
            faces.append((lin, dX))
            print(f"{where}: face f_x {ax[0][i]:+.1f} N from rest {c_rest:.1f} CPU-s "
                  f"({fwd.eq.factorizations} factorizations), Hermite derivative {c_der:.2f}", flush=True)
            rows.append([where, f"face f_x {ax[0][i]:+.0f} N from rest", f"{c_rest:.1f}", fwd.eq.factorizations, ""])
            if i == 0 and j + 1 < ny:  # the face walk's step along f_y, from this point
                f0 = fwd.eq.factorizations
                lam2 = lam.copy()
                lam2[1] = ax[1][j + 1]
                _, c_face = timed(fwd.solve, lam2, lin, via_tol=1e-3)
                print(f"{where}: face point from its f_y neighbour {c_face:.1f} CPU-s "
                      f"({fwd.eq.factorizations - f0} factorizations)", flush=True)
                rows.append([where, "face point from its neighbour (+ Hermite derivative)",
                             f"{c_face + c_der:.1f}", fwd.eq.factorizations - f0, ""])
        ends = [np.full(ny, np.nan), np.full(ny, np.nan)]
        starts = np.zeros((ny, fwd.fem.n_dof))
        dends = [np.zeros(ny), np.zeros(ny)]
        for e, (lin, dX) in enumerate(faces):
            ends[e][j] = float(h @ (lin.x - fwd.fem.x_rest))
            dends[e][j] = float(h @ dX)
        starts[j] = faces[0][0].x - fwd.fem.x_rest
        t = time.perf_counter()
        out = _lines(model, cfg, acfg, k, l, tuple(ends), starts, tuple(dends))
        wall = time.perf_counter() - t
        solved, cpu, n_solves = out[5], out[7], out[10]
        m = int(solved.sum())
        print(f"{where}: line of {n1 - 2} inner points: {cpu:.1f} CPU-s ({cpu / max(m, 1):.2f} a point, {m} solved, "
              f"{n_solves} solves), {wall:.0f} s wall; {out[6]}", flush=True)
        rows.append([where, f"line point (mixed control + Hermite derivatives), {m} of {n1 - 2} solved",
                     f"{cpu / max(m, 1):.2f}", "", f"{cpu:.0f} CPU-s the line"])
    write_table(a.results_name, ["where", "kind", "CPU-s a point", "factorizations", "note"], rows, right=(2,),
                caption=f"Per-point cost of the atlas build on {len(model.nodes)} nodes (element order "
                        f"{model.element_order}), the default atlas's grid (`bench_atlas_point_cost.py`).")


if __name__ == "__main__":
    main()
