"""scipy.optimize.least_squares in place of the calibration's Levenberg–Marquardt loop
(:func:`softphantom.calibration.fit.fit`), to measure them side by side: rounds of forward solves,
cost, recovered parameters.

    .venv/bin/python benchmarks/research/diag_calibrate/least_squares.py standin
    .venv/bin/python benchmarks/research/diag_calibrate/least_squares.py bench [bench_calibrate.py options]

``standin``: both on the stand-in problems of tests/test_calibration.py (linear FEM stand-ins, no
solves). ``bench``: benchmarks/bench_calibrate.py with every fit (calibration and pose checks) done
by least_squares. The variant: method ``trf`` (it takes a trial whose solves give up as an
infinite cost and shrinks the step; ``lm`` cannot), ``x_scale`` the priors' spreads and 1 N for
the forces (``"jac"`` took 2x the rounds on the stand-ins), ``ftol`` the options' ``tol``, the same
Jacobian (the residuals' own), the Yeoh projection applied inside the residual function, the
warm start and history from the best evaluation so far.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

from softphantom.calibration import fit as F  # noqa: E402
from softphantom.errors import SolverError  # noqa: E402

HAND = F.fit


def fit_least_squares(problem, forces0, progress=None, identifiable_ratio=0.5):
    from scipy.optimize import least_squares

    t0 = time.perf_counter()
    free = np.concatenate([problem.free_mask(), np.ones(forces0.size, bool)])
    z0 = np.concatenate([problem.nominal(), np.asarray(forces0, float).reshape(-1)])
    seen, best, history, state = {}, {"cost": np.inf}, [], {"first": True, "m": 0}

    def full(x):
        z = z0.copy()
        z[free] = x
        return problem.feasible(z)

    def fun(x):
        z = full(x)
        try:
            r, J, sols = problem.residuals(z, trial=not state["first"])
        except SolverError:
            if state["first"]:
                raise
            return np.full(state["m"], np.inf)
        state.update(first=False, m=r.size)
        seen[x.tobytes()] = J
        c = 0.5 * float(r @ r)
        if c < best["cost"]:
            best.update(cost=c, z=z, r=r, J=J, sols=sols)
            problem.x_warm = [s.x for s in sols]
            history.append(c)
            if progress:
                progress(len(history) - 1, c, float("nan"))
        return r

    x_scale = np.concatenate([problem.prior_sd(), np.ones(forces0.size)])[free]
    least_squares(fun, z0[free], jac=lambda x: seen[x.tobytes()][:, free], method="trf", x_scale=x_scale,
                  ftol=problem.options.tol, xtol=1e-10, gtol=1e-10, max_nfev=8 * problem.options.max_iter)
    return F.fit_result(problem, best["z"], best["r"], best["J"], best["sols"], free, history, t0, identifiable_ratio)


def standin() -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    import test_calibration as T

    from softphantom.calibration.fit import FitOptions, Problem, parameter_set

    def drift(extra):
        se, fr, solve_many = T._stand_in_session(0.3, {"bulb": 1.3, "arms": 1.0}, seed=2)
        params = parameter_set()
        free = {"stiffness_bulb_factor", "stiffness_arms_factor"} | {
            f"offset_{a}_Pa" for a in ("front_zpos", "front_zneg", "back_xpos", "back_xneg")}
        fix = tuple(p.name for p in params if p.name not in free) + ("lag",) + extra
        return Problem("m", [se], fr, np.zeros((3, 3)), solve_many, FitOptions(fix=fix), params, use_pose=False), fr.known

    def all_free():
        se, fr, solve_many = T._stand_in_session(0.3, {"bulb": 1.3, "arms": 1.0}, seed=2)
        return Problem("m", [se], fr, np.zeros((3, 3)), solve_many, FitOptions(fix=("lag",)), parameter_set(),
                       use_pose=False), fr.known

    cases = {"drift free": lambda: drift(()), "drift held at 0": lambda: drift(("drift",)), "all globals free": all_free}
    for name, make in cases.items():
        for label, fn in (("hand LM", HAND), ("least_squares", fit_least_squares)):
            prob, f0 = make()
            res = fn(prob, f0)
            p = dict(zip(res.names, res.value))
            print(f"{name:18s} {label:14s} rounds {res.solves // len(prob.frames):3d}  cost {res.history[-1]:.6g}  "
                  f"bulb {p['stiffness_bulb_factor']:.4f}  arms {p['stiffness_arms_factor']:.4f}")


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in ("standin", "bench"):
        sys.exit(__doc__)
    if sys.argv[1] == "standin":
        standin()
        return
    import runpy

    import softphantom.calibration.run as R

    F.fit = R.fit = fit_least_squares
    sys.argv = ["bench_calibrate.py"] + sys.argv[2:]
    runpy.run_path(str(ROOT / "benchmarks" / "bench_calibrate.py"), run_name="__main__")


if __name__ == "__main__":
    main()
