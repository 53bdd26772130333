"""BLAS threads per process: one (softphantom's default, ``softphantom/__init__.py``) against the
library default of one per core, on the work the demo, the atlas build and the truth do.

Work: one atlas plane (:func:`softphantom.estimation.atlas.solves._sweep`: 20 converged forward solves of
the default 6 mm model, warm-started from their neighbours, the on-centre contact) in a fresh
process, once with ``OPENBLAS_NUM_THREADS=1`` and once with it set to the number of cores (the peer:
what numpy's OpenBLAS does when nothing is set). Wall and CPU seconds of the plane; idle, and again
with both cores busy (two spinning processes started here, as a user's machine is).

    .venv/bin/python benchmarks/bench_threads.py [--mesh-size-mm 6]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from _results import write_table

WORK = """
import json, sys, time
from softphantom.design import BIPDesign, build_model
from softphantom.estimation import AtlasConfig, EstimatorConfig
from softphantom.estimation.atlas.build import _sweep
model = build_model(BIPDesign(), float(sys.argv[1]))
acfg = AtlasConfig(force_min_N=(-1.1, -0.8, -1.1), force_max_N=(1.1, 3.8, 1.1), p_min_kPa=-2, p_max_kPa=2,
                   n_force=(4, 5, 4), n_pressure=2)
cfg = EstimatorConfig(contact="on-centre", mode="sync")
_sweep(model, cfg, acfg, 0, 0)  # warm: numba compile, caches
t, c = time.perf_counter(), time.process_time()
r = _sweep(model, cfg, acfg, 1, 0)
print(json.dumps({"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c, "solved": int(r[5].sum())}))
"""


def plane(threads: int, mesh_mm: float) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    with tempfile.TemporaryDirectory() as d:
        out = subprocess.run([sys.executable, "-c", WORK, str(mesh_mm)], env=env, cwd=d, capture_output=True,
                             text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size-mm", type=float, default=6.0)
    a = ap.parse_args()
    sys.path.insert(0, os.path.dirname(__file__))
    from bench_estimate import start_load, stop_load

    cores = os.cpu_count() or 2
    print(f"one atlas plane (20 forward solves), {a.mesh_size_mm:g} mm model, {cores} cores; load "
          f"{os.getloadavg()[0]:.1f} at start")
    rows = []
    for busy in (False, True):
        load = start_load(cores) if busy else []
        try:
            one, peer = plane(1, a.mesh_size_mm), plane(cores, a.mesh_size_mm)
        finally:
            stop_load(load)
        tag = "both cores busy" if busy else "idle"
        for name, r in (("1 BLAS thread (softphantom)", one), (f"{cores} BLAS threads (library default)", peer)):
            print(f"  {tag:16s} {name:36s} {r['wall_s']:6.1f} s wall {r['cpu_s']:6.1f} CPU-s ({r['solved']} solved)")
        print(f"  {tag:16s} ratio default/softphantom: wall {peer['wall_s'] / one['wall_s']:.2f}x, "
              f"CPU {peer['cpu_s'] / one['cpu_s']:.2f}x")
        rows.append((tag, f"{one['wall_s']:.1f} / {one['cpu_s']:.1f}", f"{peer['wall_s']:.1f} / {peer['cpu_s']:.1f}",
                     f"{peer['wall_s'] / one['wall_s']:.2f}× / {peer['cpu_s'] / one['cpu_s']:.2f}×"))
    write_table("threads", ("machine", "1 BLAS thread (softphantom): wall s / CPU-s",
                            f"{cores} BLAS threads (library default): wall s / CPU-s", "ratio wall / CPU"), rows,
                caption=f"One atlas plane (20 warm-started forward solves) of the {a.mesh_size_mm:g} mm model in a "
                        "fresh process:")


if __name__ == "__main__":
    main()
