"""FEM speed on the default BIP mesh and a finer one (element size / 4^(1/3)); P1 and P2 laws.

Run: ``.venv/bin/python benchmarks/bench_fem.py [--repeat N] [--no-fine] [--no-splu-fine] [--no-p2] [--only-p2]``

Section "P1 vs P2" (same run, default design): neo-Hookean and co-rotational on linear tets and
neo-Hookean on 10-node tets of the same mesh (``element_order = 2``): internal force and tangent
(K_ff) assembly with elements/s, the default solver's factorization of K_ff, and a 3 N push solve
(on-centre, 4 mm contact patch); then force and tangent again with both cores busy (the benchmark
starts its own busy-loop process). Wall and CPU time of this process side by side: on a shared
machine the CPU time is the steadier figure.

Per mesh: build_fem (pattern + scatter indices), internal force and tangent assembly (K_ff,
consistent) with the numba kernels and with the numpy reference in the same run (and their ratio),
strain energy, factorization of K_ff by each available sparse direct solver (first = with symbolic
analysis, re-factorization of the same pattern, solve with 4 right-hand sides), one full Newton
iteration (tangent + factorization + solve + residual) with the chosen default solver, and the
full static solve of a 5 N push along +y at p_ext on-centre (5 mm patch), all under the
co-rotational law (the one with a numpy reference path). Times are medians of
``--repeat`` runs in the same process, so the solver columns compare peers on the same matrix.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np
from _results import grouped, markdown_table, write_result, write_table


def _ms(t: float) -> str:
    return f"{t * 1e3:.3g}" if t < 0.1 else grouped(t * 1e3)


def _median(fn, repeat):
    return _median_cpu(fn, repeat)[0::2]


def _median_cpu(fn, repeat):
    """(median wall s, median CPU s of this process, last result): on a shared machine the CPU
    time is the steadier figure (wall time counts the waits for a core)."""
    out, ts, cs = None, [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    return statistics.median(ts), statistics.median(cs), out


def bench(name, size_mm, repeat, solvers):
    from softphantom.design import BIPDesign, build_model
    from softphantom.fem import corotational as C
    from softphantom.fem import (
        SparseSolver,
        fem_from_phantom,
        force_actuator,
        free_tangent,
        internal_force,
        solve_static,
        strain_energy,
    )

    t = time.perf_counter()
    model = build_model(BIPDesign(), size_mm)
    t_mesh = time.perf_counter() - t
    from softphantom.fem import kernels

    t = time.perf_counter()
    kernels.warm_up()  # otherwise inside the first build_fem
    rows_w = ("numba warm-up (from the disk cache; a first compile takes seconds)", _ms(time.perf_counter() - t))
    from softphantom.fem.material import ECOFLEX_00_50

    # the co-rotational law: the one with a numpy reference path (corotational.py) to compare with
    t_build, fem = _median(lambda: fem_from_phantom(model, ECOFLEX_00_50), 1)
    x = fem.x_rest
    rows = [("mesh (gmsh, not FEM)", _ms(t_mesh)), rows_w]
    rows.append(("build_fem (once per model)", _ms(t_build)))
    # a deformed, rotated state for the kernels (the rest state would make the polar iteration trivial)
    c, s_ = np.cos(0.5), np.sin(0.5)
    Rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    noise = 2e-5 * np.random.default_rng(1).standard_normal(fem.nodes.shape)
    xd = ((fem.nodes + noise) @ Rz.T).reshape(-1)
    use = C.USE_NUMBA
    for label, fast, ref in [
        ("internal force", lambda: internal_force(fem, xd), lambda: C.internal_force_numpy(fem, xd)),
        ("tangent K_ff assembly", lambda: free_tangent(fem, xd), None),
        ("strain energy", lambda: strain_energy(fem, xd), lambda: C.strain_energy_numpy(fem, xd)),
    ]:
        t_fast = _median(fast, repeat)[0]
        if ref is None:  # free_tangent: flip the switch for the reference
            C.USE_NUMBA = False
            try:
                t_ref = _median(fast, repeat)[0]
            finally:
                C.USE_NUMBA = use
        else:
            t_ref = _median(ref, repeat)[0]
        kind = "numba" if use else "numpy (numba unavailable)"
        rows.append((f"{label}: {kind} / numpy reference (same run)",
                     f"{_ms(t_fast)} / {_ms(t_ref)} ({t_ref / t_fast:.0f}×)"))
    K = free_tangent(fem, x)
    B = np.random.default_rng(0).standard_normal((fem.n_free, 4))
    for method in solvers:
        s = SparseSolver(method)
        t = time.perf_counter()
        s.factorize(K)
        first = time.perf_counter() - t
        re_ = _median(lambda: s.factorize(K), repeat)[0]
        rows.append((f"{method} first factorization / re-factorization / 4-RHS solve",
                     f"{_ms(first)} / {_ms(re_)} / {_ms(_median(lambda: s.solve(B), repeat)[0])}"))
    default = SparseSolver("auto")
    default.factorize(K)
    H = force_actuator(fem, model.p_ext["on-centre"], radius=5e-3)
    f = H @ np.array([0.0, 5.0, 0.0])

    def newton_iteration():
        r = (internal_force(fem, x) - f)[fem.free_dofs]
        d = default.factorize(free_tangent(fem, x)).solve(-r)
        xt = x.copy()
        xt[fem.free_dofs] += d
        return internal_force(fem, xt)

    rows.append((f"one Newton iteration ({default.method})", _ms(_median(newton_iteration, repeat)[0])))
    t_sol, sol = _median(lambda: solve_static(fem, f, solver=default), 1)
    rows.append((f"5 N push, full static solve ({sol.iterations} iterations; max u_y "
                 f"{sol.u[:, 1].max() * 1e3:.1f} mm, residual {sol.residual_norm:.1e})", _ms(t_sol)))
    head = (f"{name}: {grouped(fem.n_nodes)} nodes, {grouped(len(fem.tets))} tets, {grouped(fem.n_free)} free DOF, "
            f"K_ff nnz {grouped(K.nnz)}")
    return head, rows, sol


def _busy() -> None:  # pragma: no cover - runs in the load process
    while True:
        pass


def bench_p1_p2(repeat):
    import dataclasses
    import multiprocessing as mp

    from softphantom.design import BIPDesign, MeshParams, build_model
    from softphantom.fem import (
        ContactPatch,
        NeoHookean,
        SparseSolver,
        fem_from_phantom,
        free_tangent,
        internal_force,
        solve_static,
    )
    from softphantom.fem.material import ECOFLEX_00_50

    nh = NeoHookean(ECOFLEX_00_50.E_Pa, ECOFLEX_00_50.nu, ECOFLEX_00_50.density_kg_m3)
    model = build_model(BIPDesign(mesh=dataclasses.replace(MeshParams(), element_order=2)))
    cases = [
        ("P1 co-rotational", fem_from_phantom(model, ECOFLEX_00_50, order=1)),
        ("P1 neo-Hookean", fem_from_phantom(model, nh, order=1)),
        ("P2 neo-Hookean", fem_from_phantom(model, nh, order=2)),
    ]
    rows, doc = [], []
    states = {}
    for label, fem in cases:
        c, s_ = np.cos(0.5), np.sin(0.5)
        Rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        noise = 2e-5 * np.random.default_rng(1).standard_normal(fem.nodes.shape)
        xd = ((fem.nodes + noise) @ Rz.T).reshape(-1)
        states[label] = (fem, xd)
        m = len(fem.tets)
        t_f = _median_cpu(lambda: internal_force(fem, xd), repeat)
        t_k = _median_cpu(lambda: free_tangent(fem, xd), repeat)
        K = free_tangent(fem, fem.x_rest)
        solver = SparseSolver("auto")
        solver.factorize(K)
        t_fac = _median_cpu(lambda: solver.factorize(K), repeat)
        H = ContactPatch(model.p_ext["on-centre"], 4e-3).load_matrix(fem)
        *t_sol, sol = _median_cpu(lambda: solve_static(fem, H @ np.array([0.0, 3.0, 0.0]), solver=solver), 1)
        head = f"{label}: {fem.n_nodes} nodes, {m} tets, {fem.n_free} free DOF, K_ff nnz {K.nnz}"
        doc.append((label, grouped(fem.n_free), _ms(t_f[1]), _ms(t_k[1]), _ms(t_fac[1]),
                    f"{t_sol[1]:.1f} s, {sol.iterations} it., y {sol.u[:, 1].max() * 1e3:.2f} mm"))
        rows.append((head, [
            ("internal force", *t_f[:2], m / t_f[0]),
            ("tangent K_ff assembly", *t_k[:2], m / t_k[0]),
            (f"re-factorization ({solver.method})", *t_fac[:2], None),
            (f"3 N push solve: {sol.iterations} it., y {sol.u[:, 1].max() * 1e3:.2f} mm", *t_sol, None),
        ]))
    load = mp.get_context("spawn").Process(target=_busy, daemon=True)
    load.start()
    try:
        busy = []
        for label, (fem, xd) in states.items():
            m = len(fem.tets)
            t_f = _median_cpu(lambda: internal_force(fem, xd), repeat)
            t_k = _median_cpu(lambda: free_tangent(fem, xd), repeat)
            busy.append((f"{label}: internal force (both cores busy)", *t_f[:2], m / t_f[0]))
            busy.append((f"{label}: tangent K_ff (both cores busy)", *t_k[:2], m / t_k[0]))
    finally:
        load.terminate()
        load.join()
    rows.append(("both cores busy (a busy-loop process started by the benchmark)", busy))
    return rows, doc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-fine", action="store_true", help="only the default mesh")
    ap.add_argument("--no-splu-fine", action="store_true", help="skip scipy splu on the fine mesh (slow)")
    ap.add_argument("--no-p2", action="store_true", help="skip the P1 vs P2 section")
    ap.add_argument("--only-p2", action="store_true", help="only the P1 vs P2 section")
    args = ap.parse_args()
    from softphantom.design import MeshParams
    from softphantom.fem import available_solvers

    print(f"# bench_fem  python {platform.python_version()}  {platform.machine()}  cpus={os.cpu_count()}")
    h0 = MeshParams().size_mm
    # element size / 4^(1/3) aims at 4x the tets; the design's fixed cavity/arm sizing gives ~2.7x
    cases = [("default", None)] + ([] if args.no_fine else [("fine (size / 4^(1/3))", h0 / 4 ** (1 / 3))])
    cases = [] if args.only_p2 else cases
    for name, size in cases:
        solvers = list(available_solvers())
        if size is not None and args.no_splu_fine:
            solvers = [s for s in solvers if s != "splu"]
        head, rows, sol = bench(name, size, args.repeat, solvers)
        table = markdown_table(("step", "ms"), rows, right=(1,))
        print(f"\n## {head}\n{table}")
        if size is None:                                     # the mesh's time is bench_design's figure
            write_result("fem_core", markdown_table(("step", "ms"), rows[1:], right=(1,)), caption=f"Co-rotational law on linear tets, default design, "
                                                    f"{head.split(': ', 1)[1]}; medians of {args.repeat}:")
    if not args.no_p2:
        print("\n## P1 vs P2 on the default design (one element_order = 2 mesh; P1 = its corner nodes)")
        sections, doc = bench_p1_p2(args.repeat)
        for head, rows in sections:
            print(f"\n### {head}\n| step | wall ms | CPU ms | elements/s (wall) |\n| --- | ---: | ---: | ---: |")
            for label, t, c, rate in rows:
                print(f"| {label} | {t * 1e3:.1f} | {c * 1e3:.1f} | {'' if rate is None else f'{rate:.3g}'} |")
        write_table("fem_p1_p2", ("model", "free DOF", "force", "tangent K_ff", "re-factor", "3 N push solve"),
                    doc, right=(1, 2, 3, 4), caption="CPU ms of the process (a load inflates it less than wall time):")


if __name__ == "__main__":
    main()
