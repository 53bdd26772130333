"""CPU time of the FEM kernels per material law, P1 and P2, on a box mesh: one internal force with
its energy (the Newton line search's call) and one free-free tangent assembly per law.

    .venv/bin/python benchmarks/bench_fem_laws.py [--repeat 30]

Box 40 × 20 × 20 mm in 24 × 12 × 12 cubes of 6 tets (20 736 tets; P2: the same tets with mid-edge
nodes), left face clamped, a smooth deformed state (strains ≈ 0.2). Medians of ``--repeat`` calls
(P2 and tangents fewer) of this process's CPU time (``time.process_time``): on a shared machine
the steadier figure. Prints one JSON object, milliseconds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def _median_cpu_ms(fn, n: int) -> float:
    cs = []
    for _ in range(n):
        c = time.process_time()
        fn()
        cs.append(time.process_time() - c)
    return statistics.median(cs) * 1e3


def main() -> None:
    from softphantom.fem import Corotational, NeoHookean, Yeoh, build_fem, force_and_energy
    from softphantom.fem.corotational import tangent_data
    from softphantom.fem.meshes import box_mesh, quadratic_mesh

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=30)
    a = ap.parse_args()
    X, T = box_mesh((0.04, 0.02, 0.02), (24, 12, 12))
    meshes = {1: (X, T), 2: quadratic_mesh(X, T)}
    laws = {"corotational": Corotational(1.4e5, 0.45), "neo-hookean": NeoHookean(1.4e5, 0.45),
            "yeoh": Yeoh(17e3, -200.0, 23.0, 0.45)}
    out = {}
    for order, (Xo, To) in meshes.items():
        n = a.repeat if order == 1 else max(3, a.repeat // 4)
        for name, law in laws.items():
            fem = build_fem(Xo, To, law, fixed_nodes=np.flatnonzero(Xo[:, 0] < 1e-9))
            x = fem.nodes + 1e-3 * np.sin(150 * fem.nodes[:, [1, 2, 0]])
            out[f"P{order} {name} force+energy"] = _median_cpu_ms(lambda: force_and_energy(fem, x), n)
            out[f"P{order} {name} tangent K_ff"] = _median_cpu_ms(lambda: tangent_data(fem, x, True, free=True),
                                                                  max(3, n // 3))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
