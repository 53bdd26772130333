"""One line task of a displacement-axis atlas build, by mixed-control solves and by
force-controlled trials only in the same run (the default and its peer).

    .venv/bin/python benchmarks/bench_atlas_lines.py --model DIR [--fz-index 1 --p-index 1]

Solves the two f_x faces at (f_z, p_u) grid indices ``--fz-index``, ``--p-index`` of the default
displacement atlas (``AtlasConfig(x_control="displacement")``, or ``--atlas-grid``), then the
task's lines (``_lines``: every f_y row from face to face) twice: with the mixed-control solve
(``_solve_ux``'s default) and with force-controlled trials only. Prints, per variant,
CPU seconds, equilibrium solves by kind, factorizations, failures of the mixed-control solve, and
the largest difference of the two variants' f_x at the points both land on. Figures:
docs/performance/estimation.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import softphantom.estimation.atlas_build as A  # noqa: E402
import softphantom.estimation.linearization as L  # noqa: E402
from softphantom.design import load_model  # noqa: E402
from softphantom.estimation import AtlasConfig, EstimatorConfig  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="model directory")
    ap.add_argument("--fz-index", type=int, default=1)
    ap.add_argument("--p-index", type=int, default=1)
    ap.add_argument("--atlas-grid", help="points per axis NX,NY,NZ,NP (default: AtlasConfig's)")
    a = ap.parse_args(argv)
    model = load_model(a.model)
    cfg = EstimatorConfig()
    acfg = AtlasConfig(x_control="displacement")
    if a.atlas_grid:
        n = [int(v) for v in a.atlas_grid.split(",")]
        acfg = AtlasConfig(x_control="displacement", n_force=tuple(n[:3]), n_pressure=n[3])
    ax = acfg.axes()
    k, l = a.fz_index, a.p_index
    print(f"grid {acfg.shape}; task f_z {ax[2][k]:+.2f} N, p_u {ax[3][l] / 1e3:.1f} kPa", flush=True)
    c0 = time.process_time()
    faces = [A._sweep(model, cfg, acfg, i, l) for i in (0, len(ax[0]) - 1)]
    print(f"faces: {time.process_time() - c0:.1f} CPU-s, {sum(f[-1] for f in faces)} converged solves", flush=True)
    h = A.x_patch(ForwardModel(model, cfg, exact_sensitivities=False))
    ends = tuple(f[4][:, k] @ h for f in faces)
    solve_ux, eq_solve = A._solve_ux, L.EquilibriumSolver.solve
    fx, cpu = {}, {}
    for name, bordered in (("mixed control", True), ("trials (peer)", False)):
        log: list = []
        L.EquilibriumSolver.solve = counted(log)
        A._solve_ux = partial(solve_ux, bordered=bordered)
        try:
            c0 = time.process_time()
            out = A._lines(model, cfg, acfg, k, l, ends)
            cpu[name] = time.process_time() - c0
        finally:
            L.EquilibriumSolver.solve, A._solve_ux = eq_solve, solve_ux
        mixed = [e for e in log if e[0]]
        force = [e for e in log if not e[0]]
        fx[name] = (out[8], out[5])
        print(f"{name}: {cpu[name]:.1f} CPU-s; {int(out[5].sum())}/{out[5].size} points, {out[-1]} converged solves; "
              f"mixed-control calls {len(mixed)} ({sum(not e[1] for e in mixed)} failed, "
              f"{sum(e[3] for e in mixed)} factorizations), force-controlled {len(force)} "
              f"({sum(e[3] for e in force)} factorizations); first failure {out[6]!r}", flush=True)
    (f1, s1), (f2, s2) = fx.values()
    print(f"ratio: trials / mixed control = {cpu['trials (peer)'] / cpu['mixed control']:.2f}x the CPU; f_x of the "
          f"points differ by up to {np.abs(f1 - f2)[s1 & s2].max():.4f} N (trials land within NODE_TOL of the "
          f"node, mixed control on it)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
