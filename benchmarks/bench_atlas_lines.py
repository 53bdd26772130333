"""Line tasks of a displacement-axis atlas build, by variants of its solver path in the same
run: the default (mixed-control solves, each started on the cubic Hermite through the line's last
two points from their exact derivatives along ū) and its peers.

    .venv/bin/python benchmarks/bench_atlas_lines.py --model DIR [--tasks 0:1:1 1:1:0]
        [--variants hermite,secant,trials] [--results-name NAME]

For each task PIECE:K:L — the piece of the model's default atlas (``default_atlas_config``; a
quadratic model's has two along f_y; or ``--atlas-grid`` for ``AtlasConfig(x_control=
"displacement")``) and its (f_z, p_u) grid indices — solves the two f_x faces, then the task's
lines (``_lines``: every f_y row from face to face) once per variant:

- ``hermite`` (the default): mixed-control solves started on :class:`LinePredictor`;
- ``secant``: mixed-control solves started on the secant through the line's last two points (the
  predictor without derivatives);
- ``trials``: force-controlled trials only (no mixed control).

Prints, per variant, CPU seconds, equilibrium solves by kind, factorizations, the exact
derivative columns' CPU, failures of the mixed-control solve, and the largest difference of the
volumes and f_x from the first variant's at the points both land on; the CPU ratio of each peer to
the first; and writes the table to ``benchmarks/results/NAME.md`` (``--results-name``, default
``atlas_lines``) for docs/performance/estimation.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import softphantom.estimation.atlas.build as A  # noqa: E402
import softphantom.estimation.linearization as L  # noqa: E402
from softphantom.design import load_model  # noqa: E402
from softphantom.estimation import AtlasConfig, EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas.config import default_atlas_config  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from _results import add_results_option, write_table  # noqa: E402

VARIANTS = ("hermite", "secant", "trials")


def counted(log: list):
    """EquilibriumSolver.solve that appends (mixed control?, converged?, CPU-s, factorizations)."""
    solve = L.EquilibriumSolver.solve

    def wrapped(self, start, lam, path=None, **kw):
        c0, f0 = time.process_time(), self.factorizations
        ok = False
        try:
            lin = solve(self, start, lam, path, **kw)
            ok = True
            return lin
        finally:
            log.append((kw.get("control") is not None, ok, time.process_time() - c0, self.factorizations - f0))

    return wrapped


def timed_columns(log: list):
    """EquilibriumSolver.exact_column that appends its CPU seconds and factorizations."""
    column = L.EquilibriumSolver.exact_column

    def wrapped(self, lin, a):
        c0, f0 = time.process_time(), self.factorizations
        try:
            return column(self, lin, a)
        finally:
            log.append((time.process_time() - c0, self.factorizations - f0))

    return wrapped


def run_task(model, cfg, fwd, acfg, k: int, l: int, variants: list[str]) -> list[list]:
    """The task's faces once, then its lines once per variant: the table's rows."""
    ax = acfg.axes()
    task = (f"f_y {ax[1][0]:+.1f}…{ax[1][-1]:+.1f} N, f_z {ax[2][k]:+.2f} N, p_u {ax[3][l] / 1e3:.0f} kPa "
            f"({acfg.shape[0]} × {acfg.shape[1]} points)")
    print(f"grid {acfg.shape}; task {task}", flush=True)
    c0 = time.process_time()
    faces = [A._sweep(model, cfg, acfg, i, l) for i in (0, len(ax[0]) - 1)]
    print(f"faces: {time.process_time() - c0:.1f} CPU-s, {sum(f[-1] for f in faces)} converged solves", flush=True)
    h = A.x_patch(fwd)
    ends = tuple(f[4][:, k] @ h for f in faces)
    solve_ux, eq_solve, column, knot = A._solve_ux, L.EquilibriumSolver.solve, L.EquilibriumSolver.exact_column, A._line_knot
    out, cpu, rows = {}, {}, []
    for name in variants:
        log: list = []
        cols: list = []
        L.EquilibriumSolver.solve = counted(log)
        L.EquilibriumSolver.exact_column = timed_columns(cols)
        if name == "trials":
            A._solve_ux = partial(solve_ux, bordered=False)
        if name != "hermite":
            A._line_knot = lambda *args: None  # no derivatives along the line: the secant predictor
        try:
            c0 = time.process_time()
            out[name] = A._lines(model, cfg, acfg, k, l, ends, faces[0][4][:, k])
            cpu[name] = time.process_time() - c0
        finally:
            L.EquilibriumSolver.solve, L.EquilibriumSolver.exact_column = eq_solve, column
            A._solve_ux, A._line_knot = solve_ux, knot
        r, ref = out[name], out[variants[0]]
        mixed = [e for e in log if e[0]]
        force = [e for e in log if not e[0]]
        both = r[5] & ref[5]
        dv = float(np.abs(r[2] - ref[2])[both].max()) * 1e9 if both.any() else float("nan")
        dfx = float(np.abs(r[8] - ref[8])[both].max()) if both.any() else float("nan")
        n_fac = sum(e[3] for e in log) + sum(c[1] for c in cols)
        print(f"{name}: {cpu[name]:.1f} CPU-s; {int(r[5].sum())}/{r[5].size} points, {r[10]} converged solves; "
              f"mixed-control calls {len(mixed)} ({sum(not e[1] for e in mixed)} failed), force-controlled "
              f"{len(force)}; {n_fac} factorizations; derivative columns {len(cols)} ({sum(c[0] for c in cols):.1f} "
              f"CPU-s); vs {variants[0]}: volumes {dv:.2g} mm³, f_x {dfx:.2g} N; first failure {r[6]!r}", flush=True)
        rows.append([name, task, f"{cpu[name]:.0f} ({cpu[name] / max(int(r[5].sum()), 1):.2f})",
                     f"{cpu[name] / cpu[variants[0]]:.2f}", f"{len(mixed)} ({sum(not e[1] for e in mixed)} failed)",
                     n_fac, f"{dv:.1g} mm³, {dfx:.1g} N"])
    for name in variants[1:]:
        print(f"ratio: {name} / {variants[0]} = {cpu[name] / cpu[variants[0]]:.2f}x the CPU", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="model directory")
    ap.add_argument("--tasks", nargs="+", default=["0:1:1"], metavar="PIECE:K:L",
                    help="line tasks: the piece of a quadratic model's default atlas (0: lowest f_y; 0 for an "
                    "atlas of one piece), the f_z and the pressure grid index")
    ap.add_argument("--atlas-grid", help="points per axis NX,NY,NZ,NP of AtlasConfig(x_control='displacement') "
                    "instead of the model's default atlas")
    ap.add_argument("--variants", default="hermite,secant", help=f"comma-separated, of {','.join(VARIANTS)}; "
                    "the first is the reference of the ratios")
    add_results_option(ap, "atlas_lines")
    a = ap.parse_args(argv)
    variants = [v for v in a.variants.split(",") if v]
    if not variants or any(v not in VARIANTS for v in variants):
        ap.error(f"--variants: each of {', '.join(VARIANTS)}, got {a.variants!r}")
    try:
        tasks = [tuple(int(v) for v in t.split(":")) for t in a.tasks]
    except ValueError:
        ap.error(f"--tasks: PIECE:K:L integers, got {a.tasks}")
    if any(len(t) != 3 for t in tasks):
        ap.error(f"--tasks: PIECE:K:L, got {a.tasks}")
    model = load_model(a.model)
    cfg = EstimatorConfig()
    fwd = ForwardModel(model, cfg, exact_sensitivities=False)
    if a.atlas_grid:
        n = [int(v) for v in a.atlas_grid.split(",")]
        pieces = (AtlasConfig(x_control="displacement", n_force=tuple(n[:3]), n_pressure=n[3]),)
    else:
        acfg = default_atlas_config(fwd.fem.order)
        pieces = acfg.patches() if acfg.f_y_splits_N else (acfg,)
    rows = []
    for piece, k, l in tasks:
        if not 0 <= piece < len(pieces) or pieces[piece].x_control != "displacement":
            ap.error(f"--tasks: piece {piece} is not a displacement-axis piece of this atlas ({len(pieces)} pieces; "
                     "a force axis: give --atlas-grid)")
        rows += run_task(model, cfg, fwd, pieces[piece], k, l, variants)
    write_table(a.results_name, ["predictor", "task", "CPU-s (a point)", "× the first", "mixed-control solves",
                                 "factorizations", "values vs the first"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
