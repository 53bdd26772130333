"""Offline atlas build of the default model: wall, CPU seconds a point, size.

Builds ``AtlasConfig()`` (11 × 9 × 4 × 3 = 1 188 forward solves) of the default design at
``--mesh-size-mm`` (6: the default estimator model) with the default :class:`EstimatorConfig`, on a
local Dask cluster of ``--workers`` processes, and prints wall seconds, CPU seconds of the solves
(summed over the workers) per grid point, the atlas size and the peak RSS of this process.
``--save FILE`` keeps the grid values (volumes, tracked points, field) to compare two builds with
``--compare FILE`` (max deviation relative to each output's span over the grid: the check that a
faster build reaches the same converged equilibria). ``--cache DIR`` writes the atlas where
``load_or_build`` (and ``bench_estimate.py --atlas-cache DIR --contact-radius-mm 4``) finds it.

Same run, after the build: the **peer** — ``--peer-points`` grid points (seeded) each solved on its
own from rest (``ForwardModel.solve``: continuation in ≤ 1 N steps, a new factor where the chord
stalls; what every grid point would cost without the build's walk), CPU seconds a point and their
ratio to the build's; and **one plane** of the build (``_sweep``, f_x index 2, lowest pressure:
f_y × f_z points) in this process, alone and then with 2 busy processes started by the benchmark (both
cores busy): wall and CPU seconds.

    nice -n 10 .venv/bin/python benchmarks/bench_atlas_build.py --workers 2 [--save grid.npz] [--cache DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import add_results_option, grouped, write_table  # noqa: E402

import softphantom  # noqa: E402,F401 - one BLAS thread before numpy loads
import numpy as np  # noqa: E402

from softphantom.design import BIPDesign, build_model, load_model  # noqa: E402
from softphantom.estimation import AtlasConfig, EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas import X_CONTROLS, atlas_key, atlas_path, build_atlas, save_atlas  # noqa: E402
from softphantom.estimation.atlas.build import _sweep  # noqa: E402
from softphantom.estimation.atlas.store import AXIS_NAMES  # noqa: E402
from softphantom.estimation.select import atlas_config_from_options  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from bench_estimate import start_load, stop_load  # noqa: E402 - the benchmarks' busy processes


def peer_cpu_per_point(model, cfg, acfg, n: int, seed: int = 0) -> float:
    """CPU seconds a grid point solved on its own from rest (a fresh ForwardModel each: the
    naive build), over ``n`` seeded grid points."""
    rng = np.random.default_rng(seed)
    axes = acfg.axes()
    cpu = []
    for _ in range(n):
        lam = np.array([ax[rng.integers(len(ax))] for ax in axes])
        t = time.process_time()
        ForwardModel(model, cfg).solve(lam)
        cpu.append(time.process_time() - t)
        print(f"  peer: {np.round(lam[:3], 2).tolist()} N, {lam[3] * 1e-3:.1f} kPa from rest: {cpu[-1]:.2f} CPU-s")
    return float(np.mean(cpu))


def plane(model, cfg, acfg, busy: bool) -> tuple[float, float]:
    """(wall s, CPU s) of one plane of the build in this process (``busy``: 2 busy processes beside)."""
    procs = start_load(2) if busy else []
    try:
        t, c = time.perf_counter(), time.process_time()
        _sweep(model, cfg, acfg, 2, 0)
        return time.perf_counter() - t, time.process_time() - c
    finally:
        stop_load(procs)


def grid_values(at) -> dict[str, np.ndarray]:
    """The atlas's polynomials at its own grid points (exact there): volumes, points, field."""
    axes = at.config.axes()
    lams = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)
    V = np.array([at.volumes(lam)[0] for lam in lams])
    P = np.array([at.points(lam) for lam in lams])
    F = np.array([at.nodes(lam) for lam in lams])
    return {"V": V, "P": P, "F": F, "solved": at.solved.reshape(-1)}


def compare(a: dict, b: dict) -> dict[str, float]:
    """Max |a − b| over the solved grid points, relative to the span of ``a`` over the grid."""
    ok = a["solved"] & b["solved"]
    out = {"solved_a": int(a["solved"].sum()), "solved_b": int(b["solved"].sum())}
    for k in ("V", "P", "F"):
        x, y = a[k][ok].reshape(ok.sum(), -1), b[k][ok].reshape(ok.sum(), -1)
        span = float(np.max(np.ptp(x, axis=0)))
        out[k] = float(np.max(np.abs(x - y))) / span
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size-mm", type=float, default=6.0)
    ap.add_argument("--model", help="a saved model directory instead of meshing the default design")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--save", help="write the grid values here (npz)")
    ap.add_argument("--compare", help="compare the grid values with this file (npz from --save)")
    ap.add_argument("--cache", help="model directory to write the atlas into (MODEL/atlas/<key>.npz)")
    ap.add_argument("--peer-points", type=int, default=3, help="grid points solved on their own from rest (0: none)")
    ap.add_argument("--no-busy", action="store_true", help="skip the one-plane quiet/busy figure")
    ap.add_argument("--atlas-grid", help="points per axis NX,NY,NZ,NP (default: AtlasConfig's)")
    ap.add_argument("--x-control", choices=X_CONTROLS, default=AtlasConfig.x_control,
                    help="the first axis: f_x (default) or the patch displacement (AtlasConfig.x_control)")
    add_results_option(ap, "atlas_build")
    ap.add_argument("--atlas-hermite-axis", choices=AXIS_NAMES, default=None,
                    help="interpolate this axis by Hermite from the exact derivatives of every grid point "
                    "(AtlasConfig.hermite_axis; its NX/NY/NZ/NP points then give a polynomial of twice as many terms)")
    a = ap.parse_args()
    model = load_model(a.model) if a.model else build_model(BIPDesign(), a.mesh_size_mm)
    acfg = atlas_config_from_options(a.atlas_grid, x_axis=a.x_control)
    if a.atlas_hermite_axis is not None:
        acfg = dataclasses.replace(acfg, hermite_axis=AXIS_NAMES.index(a.atlas_hermite_axis))
    cfg = EstimatorConfig()
    load0 = os.getloadavg()
    t = time.perf_counter()
    at = build_atlas(model, cfg, acfg, n_workers=a.workers)
    wall = time.perf_counter() - t
    load1 = os.getloadavg()
    n = at.solved.size
    print(f"atlas {'x'.join(map(str, acfg.shape))} = {n} points, {a.workers} workers: {wall:.1f} s wall, "
          f"{at.build_cpu_s:.0f} CPU-s in the solves ({at.build_cpu_s / n:.3f} CPU-s a point), "
          f"{at.solves} converged, {at.nbytes / 1e6:.1f} MB ({at.modes.shape[1]} field modes); "
          f"peak RSS of this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3:.0f} MB; "
          f"load average {load0[0]:.1f} at start, {load1[0]:.1f} at end")
    write_table(a.results_name, ("model, atlas", "wall", "CPU-s in the solves (a solve)", "size", "load"), [(
        f"{grouped(len(model.nodes))} nodes, {' × '.join(map(str, acfg.shape))} = {grouped(n)} points, "
        f"{a.workers} workers", f"{wall:.0f} s", f"{at.build_cpu_s:.0f} ({at.build_cpu_s / n:.2f}), {at.solves} converged",
        f"{at.nbytes / 1e6:.1f} MB, {at.modes.shape[1]} field modes; peak RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3:.0f} MB", f"{load0[0]:.0f}–{load1[0]:.0f}")])
    if a.cache:
        path = save_atlas(at, atlas_path(a.cache, atlas_key(model, cfg, acfg)))
        print(f"atlas written to {path}")
    n_pts = at.build_cpu_s / n
    if a.peer_points:
        peer = peer_cpu_per_point(model, cfg, acfg, a.peer_points)
        print(f"peer (each point from rest, same run, load average {os.getloadavg()[0]:.1f}): {peer:.2f} CPU-s a "
              f"point; the build's walk {peer / n_pts:.1f}x cheaper a point")
    if not a.no_busy:
        for busy in (False, True):
            wall, cpu = plane(model, cfg, acfg, busy)
            print(f"one plane ({acfg.n_force[1] * acfg.n_force[2]} points) in this process{', 2 busy processes beside' if busy else ', alone'}: "
                  f"{wall:.1f} s wall, {cpu:.1f} CPU-s (load average {os.getloadavg()[0]:.1f})")
    g = grid_values(at)
    if a.save:
        np.savez(a.save, **g)
    if a.compare:
        with np.load(a.compare) as z:
            ref = {k: z[k] for k in z.files}
        c = compare(ref, g)
        print(f"vs {a.compare}: solved {c['solved_a']} / {c['solved_b']}; max deviation / span: volumes "
              f"{c['V']:.2e}, points {c['P']:.2e}, field {c['F']:.2e}")


if __name__ == "__main__":
    main()
