"""Factorizing an indefinite tangent: what an atlas build's fold costs a refactorization.

Run: ``.venv/bin/python benchmarks/bench_factor_indefinite.py [--repeat 3] [--model DIR]``

On the displacement-controlled lines of an atlas build (the quadratic model's arm pair snapping
through in f_x), the tangent has one negative eigenvalue: a Cholesky fails there, after costing
about a factorization, and the equilibrium solver falls back to an indefinite factorization. The
matrices: the free tangent K of the default quadratic model (shipped mesh, 28 k nodes) at rest,
positive definite, and K − σI with σ halfway between its two smallest eigenvalues (from a
shift-invert Lanczos through its Cholesky factor): exactly one negative eigenvalue, K's pattern,
conditioned as the fold's tangent is near its limit point. Timed, CPU-s of this process (MKL and
CHOLMOD single-threaded as the package sets them), median of ``--repeat``:

* CHOLMOD supernodal LLᵀ on K (the definite case, the reference cost), and its failure on K − σI;
* MKL PARDISO LDLᵀ (the ``pardiso`` extra; Bunch-Kaufman within supernodes) on both, with the
  number of negative eigenvalues it reports;
* SuperLU (symmetric mode, minimum degree on A + Aᵀ: the indefinite fallback without the extra);
* each solve's relative residual;

then the same with the other core busy (a busy-loop process). Writes ``factor_indefinite``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import statistics
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from _results import grouped, write_table
from bench_fem import _busy


def _time(fn, repeat: int):
    out, cpu = None, []
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        cpu.append(time.process_time() - t)
    return statistics.median(cpu), out


def main() -> None:
    from softphantom.design import default_design, load_model, shipped_model
    from softphantom.errors import SolverError
    from softphantom.fem import SparseSolver, fem_from_phantom, free_tangent, have_pardiso

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--model", default=None, help="model directory (default: the shipped default model)")
    args = ap.parse_args()
    model = load_model(args.model) if args.model else shipped_model(default_design())
    fem = fem_from_phantom(model)
    K = free_tangent(fem, fem.x_rest).tocsc()
    chol = SparseSolver("cholmod").factorize(K)
    w = spla.eigsh(K, k=2, sigma=0.0, which="LM", OPinv=spla.LinearOperator(K.shape, matvec=chol.solve),
                   return_eigenvectors=False)
    lo, hi = sorted(w)
    sigma = 0.5 * (lo + hi)
    Kneg = (K - sigma * sp.identity(K.shape[0], format="csc")).tocsc()
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    print(f"{grouped(fem.n_free)} free DOF, K nnz {grouped(K.nnz)}; two smallest eigenvalues {lo:.4g}, {hi:.4g} N/m; "
          f"σ = {sigma:.4g}", flush=True)

    def run(label_suffix: str) -> list[list[str]]:
        rows = []
        cases = [("CHOLMOD LLᵀ", "cholmod", K, "definite"), ("CHOLMOD LLᵀ", "cholmod", Kneg, "1 negative")]
        if have_pardiso():
            cases += [("PARDISO LDLᵀ", "pardiso", K, "definite"), ("PARDISO LDLᵀ", "pardiso", Kneg, "1 negative")]
        cases += [("SuperLU", "splu", Kneg, "1 negative")]
        for label, method, A, kind in cases:
            s = SparseSolver(method)

            def once():
                try:
                    s.factorize(A)
                    return "ok"
                except SolverError:
                    return "fails (not definite)"

            cpu, status = _time(once, args.repeat)
            if status == "ok":
                x = s.solve(b)
                res = f"{np.linalg.norm(A @ x - b) / np.linalg.norm(b):.1e}"
                neg = s.negative_eigenvalues
                status = "ok" + ("" if neg is None else f", {neg} negative")
            else:
                res = "–"
            print(f"{label} on K {kind}{label_suffix}: {cpu:.2f} CPU-s, {status}, residual {res}", flush=True)
            rows.append([f"{label}{label_suffix}", kind, f"{cpu:.2f}", status, res])
        return rows

    rows = run("")
    load = mp.get_context("spawn").Process(target=_busy, daemon=True)
    load.start()
    try:
        rows += run(" (other core busy)")
    finally:
        load.terminate()
    write_table("factor_indefinite", ["factorization", "matrix", "CPU-s", "result", "residual"], rows, right=(2,),
                caption=f"The default quadratic model's free tangent at rest ({grouped(fem.n_free)} DOF, "
                        f"{grouped(K.nnz)} entries) and shifted by σ = {sigma:.3g} N/m to one negative eigenvalue; "
                        f"median of {args.repeat}, one thread.")


if __name__ == "__main__":
    main()
