"""Fill of the sparse factorizations of the P2 tangent (docs/performance/design-fem.md, "Memory of
the P2 solves"): CHOLMOD's supernodal LLᵀ (the Newton default), its simplicial LDLᵀ (the fallback for
an indefinite tangent) and SuperLU with scipy's COLAMD ordering and with softphantom's symmetric one,
on the default design's neo-Hookean P2 tangent with 30 kPa in the urethra (its pressure stiffness
included), at rest.

    .venv/bin/python benchmarks/bench_factor_memory.py [--mesh-size-mm 12 9] [--no-colamd]

Prints per mesh: free DOF, entries of K_ff and of each factor, CPU seconds and the process's peak RSS
after each (the peak only grows: run the big ones last). Needs scikit-sparse and the test extra.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "reference"))

import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402
from felupe_bip import bip_tet10  # noqa: E402

from softphantom.design import BIPDesign  # noqa: E402
from softphantom.fem import ECOFLEX_00_50, NeoHookean, build_fem  # noqa: E402
from softphantom.fem.solve import SparseSolver, free_tangent  # noqa: E402


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size-mm", type=float, nargs="+", default=[12.0, 9.0])
    ap.add_argument("--no-colamd", action="store_true", help="skip SuperLU with COLAMD (the largest)")
    a = ap.parse_args(argv)
    from sksparse.cholmod import analyze

    for h in a.mesh_size_mm:
        mesh = bip_tet10(BIPDesign(), h, order=2)
        fem = build_fem(mesh.nodes, mesh.tets, NeoHookean(ECOFLEX_00_50.E_Pa, 0.45), mesh.fixed_nodes,
                        cavities=mesh.cavities)
        K = sp.csc_matrix(free_tangent(fem, fem.x_rest, {"urethra": 30e3}))
        K.sort_indices()
        print(f"P2 {h:g} mm: {K.shape[0]} free DOF, K_ff {K.nnz / 1e6:.2f} M entries", flush=True)
        for name, mode in (("CHOLMOD LLᵀ supernodal", "supernodal"), ("CHOLMOD LDLᵀ simplicial", "simplicial")):
            c0 = time.process_time()
            f = analyze(K, mode=mode)
            f.cholesky_inplace(K)
            nnz = (f.L() if mode == "supernodal" else f.L_D()[0]).nnz
            print(f"  {name}: L {nnz / 1e6:.1f} M, {time.process_time() - c0:.1f} CPU-s, peak RSS {_peak_gb():.2f} GB",
                  flush=True)
        runs = [("SuperLU, symmetric ordering (softphantom)", lambda: SparseSolver("splu").factorize(K)._factor)]
        if not a.no_colamd:
            runs.append(("SuperLU, COLAMD (scipy's default)", lambda: spla.splu(K)))
        for name, fn in runs:
            c0 = time.process_time()
            lu = fn()
            print(f"  {name}: L+U {(lu.L.nnz + lu.U.nnz) / 1e6:.1f} M, {time.process_time() - c0:.1f} CPU-s, "
                  f"peak RSS {_peak_gb():.2f} GB", flush=True)
            del lu
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
