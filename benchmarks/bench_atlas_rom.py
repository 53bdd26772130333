"""The atlas's reduced-order offline stage against the full one (docs/offline.md).

Builds the model's atlas with ``offline="rom"`` (fresh, not cached) and prints, in one run: the
build's CPU seconds and wall per stage (snapshots, training, reduced grid solves, checks), the full
path's CPU seconds a grid point measured on a sample (one or more of the full build's own plane
tasks, ``--full-planes``; the full atlas is not rebuilt: the ratio is full per point × points / ROM
total), peak memory, and the ROM-built atlas's accuracy at seeded held-out loads against converged
full solves (volumes mm³, tracked points mm, the inverse's force N / pose mm / yaw deg, as
bench_estimate.py), including loads in the arm pair's step core (|f_x| < 0.1 N, f_y > 3.5 N) and
near the envelope's corners.

    python benchmarks/bench_atlas_rom.py --model /path/to/p2model [--held-out 30] [--full-planes 1]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import sys
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from bench_estimate import held_out  # noqa: E402
from softphantom.progress import message_handler  # noqa: E402
from softphantom.design import load_model  # noqa: E402
from softphantom.estimation import AtlasEstimator, EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas.build import _sweep, build_atlas  # noqa: E402
from softphantom.estimation.atlas.config import default_atlas_config  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from softphantom.estimation.select import atlas_config_from_options  # noqa: E402


def full_per_point(model, cfg, acfg, planes: int) -> tuple[float, int]:
    """CPU-s a grid point of the full build: ``planes`` of its force-controlled plane tasks (the
    first piece, f_x indices from the middle outwards, lowest pressure), run here."""
    piece = acfg.patches()[0]
    n1 = piece.shape[0]
    cpu, pts = 0.0, 0
    for i in [n1 // 2, n1 // 2 + 1, 0][:planes]:
        r = _sweep(model, cfg, piece, i, 0)
        cpu += r[7]
        pts += int(r[5].sum())
    return cpu / max(pts, 1), pts


def corner_loads(lo, hi, frac=0.03):
    c = np.array(np.meshgrid(*[[frac, 1 - frac]] * 4, indexing="ij")).reshape(4, -1).T
    return lo + (hi - lo) * c


def core_loads(lo, hi, n, seed=11):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        lam = lo + (hi - lo) * rng.uniform(0.02, 0.98, 4)
        lam[0] = rng.uniform(-0.1, 0.1)
        lam[1] = rng.uniform(max(3.5, lo[1]), hi[1])
        out.append(lam)
    return np.array(out)


def main() -> None:
    logging.getLogger("softphantom").addHandler(message_handler())  # the library's messages, not its progress
    logging.getLogger("softphantom").setLevel(logging.INFO)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="model directory")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--atlas-grid", help="NX,NY,NZ,NP (default: the model's)")
    ap.add_argument("--envelope", help="FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX (N, kPa)")
    ap.add_argument("--x-control", default=None, help="force | displacement (default: the model's)")
    ap.add_argument("--atlas-f-y-split-N", default=None)
    ap.add_argument("--held-out", type=int, default=30, help="seeded random held-out loads")
    ap.add_argument("--held-out-core", type=int, default=10, help="held-out loads in the step's core")
    ap.add_argument("--corners", action="store_true", help="also the 16 loads 3 %% inside the box's corners")
    ap.add_argument("--full-planes", type=int, default=1, help="full plane tasks to time (0: skip)")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--snapshot-cache", help="keep the snapshot solves under this path prefix and reuse them")
    a = ap.parse_args()
    if a.snapshot_cache:
        from softphantom.estimation import offline

        offline.SNAPSHOT_CACHE = a.snapshot_cache

    model = load_model(a.model)
    cfg = EstimatorConfig(contact="on-centre")
    acfg = atlas_config_from_options(a.atlas_grid, a.envelope, a.x_control, a.atlas_f_y_split_N,
                                     base=default_atlas_config(model.element_order))
    acfg = replace(acfg, offline="rom")
    out: dict = {"model": a.model, "grid": list(acfg.shape), "pieces": len(acfg.patches()),
                 "points": acfg.n_solves, "x_control": acfg.x_control}
    t0 = time.perf_counter()
    at = build_atlas(model, cfg, acfg, n_workers=a.workers)
    out["rom_wall_s"] = time.perf_counter() - t0
    pieces = getattr(at, "patches", (at,))
    offl = [p.provenance["offline"] for p in pieces]
    stages = {}
    for k in ("snapshot", "train", "grid", "check"):
        stages[k + "_cpu_s"] = sum(o[k + "_cpu_s"] if k == "snapshot" else sum(r[k + "_cpu_s"] for r in o["rounds"])
                                   for o in offl)
        stages[k + "_wall_s"] = sum(o[k + "_wall_s"] if k == "snapshot" else sum(r[k + "_wall_s"] for r in o["rounds"])
                                    for o in offl)
    out.update(stages)
    out["rom_cpu_s"] = sum(stages[k + "_cpu_s"] for k in ("snapshot", "train", "grid", "check"))
    out["offline"] = offl
    out["peak_rss_main_MB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["peak_rss_workers_MB"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(f"ROM build: {out['rom_wall_s']:.0f} s wall, {out['rom_cpu_s']:.0f} CPU-s "
          f"({acfg.n_solves} grid points, {len(pieces)} piece(s))")
    for k in ("snapshot", "train", "grid", "check"):
        print(f"  {k:9s} {stages[k + '_cpu_s']:8.1f} CPU-s  {stages[k + '_wall_s']:7.1f} s wall")
    for i, o in enumerate(offl):
        for j, r in enumerate(o["rounds"]):
            print(f"  piece {i} round {j + 1}: {o['snapshots']} snapshots, basis {r['basis']}, {r['elements']} "
                  f"elements (ECSW error {r['ecsw_error']:.1e}), {r['grid_cpu_s'] / acfg.patches()[i].n_solves * 1e3:.0f} "
                  f"CPU-ms a reduced point; checks ({r['checks']}): dV {r['check_max_dV_mm3']:.4f} mm3, points "
                  f"{r['check_max_points_mm']:.4f} mm, f_x {r['check_max_fx_N']:.4f} N")
    print(f"  peak RSS: main {out['peak_rss_main_MB']:.0f} MB, a worker {out['peak_rss_workers_MB']:.0f} MB")
    if a.full_planes:
        per, n = full_per_point(model, cfg, acfg, a.full_planes)
        out["full_cpu_s_per_point"], out["full_sample_points"] = per, n
        out["ratio"] = per * acfg.n_solves / out["rom_cpu_s"]
        print(f"full path: {per:.2f} CPU-s a point ({n} points sampled) -> {per * acfg.n_solves:.0f} CPU-s for the grid; "
              f"ratio {out['ratio']:.1f}x")
    est = AtlasEstimator(model, cfg, at)
    fwd = ForwardModel(model, cfg, exact_sensitivities=False)
    lo, hi = acfg.lower, acfg.upper
    rows = {"held_out": held_out(est, fwd, a.held_out)}
    if a.held_out_core and hi[1] > 3.5:
        rows["core"] = held_out(est, fwd, 0, loads_in=core_loads(lo, hi, a.held_out_core))
    if a.corners:
        rows["corners"] = held_out(est, fwd, 0, loads_in=corner_loads(lo, hi))
    for name, r in rows.items():
        print(f"{name:9s} dV {r['dV_mm3']:.4f} mm3, points {r['points_mm']:.4f} mm; inverse: force {r['force_N']:.4f} N, "
              f"pose {r['pos_mm']:.4f} mm / {r['ang_deg']:.3f} deg (worst at {r['worst_force_load']})")
    out["accuracy"] = rows
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1, default=float)


if __name__ == "__main__":
    main()
