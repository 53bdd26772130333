"""Virtual phantom: truth solve time per bundled scenario, frame and tracker generation rates.

Run: ``.venv/bin/python benchmarks/bench_virtual.py [--mesh-size-mm H] [--truth-mesh-scale S]
[--truth-order 1|2] [--scenarios ...]``

For each scenario: the truth mesh size and nodes, keyframes, Newton iterations, solve wall time,
the peak marker motion, and (inflation) the pressure and bulb growth reached; then how fast the
board's frames (through the whole chain and the encoder) and the tracker stream are generated,
and the decoder round trip. Default: the estimator's default mesh → the truth's default (TruthConfig:
hyperelastic, quadratic, 0.75 × the model's mesh size). Prints the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

from softphantom.design import BIPDesign, build_model
from softphantom.virtual import BUNDLED, TruthConfig, VirtualConfig, simulate, simulate_tracker, truth_model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size-mm", type=float, default=None)
    ap.add_argument("--truth-mesh-scale", type=float, default=TruthConfig.mesh_scale)
    ap.add_argument("--truth-order", type=int, default=TruthConfig.order)
    ap.add_argument("--scenarios", nargs="*", default=list(BUNDLED))
    ap.add_argument("--osr", type=int, default=25)
    a = ap.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, python {platform.python_version()}, "
          f"load average {os.getloadavg()[0]:.1f}")
    t = time.perf_counter()
    model = build_model(BIPDesign(), a.mesh_size_mm)
    cfg = VirtualConfig.seeded(seed=0, osr=a.osr, mesh_scale=a.truth_mesh_scale, order=a.truth_order)
    tm = truth_model(model, cfg.truth)
    print(f"model {len(model.nodes)} nodes ({model.design.mesh.size_mm:g} mm, P{model.element_order}); truth "
          f"{len(tm.nodes)} nodes ({tm.design.mesh.size_mm:g} mm, P{tm.element_order}); meshing both "
          f"{time.perf_counter() - t:.1f} s")
    print(f"{'scenario':20s} {'keyfr':>5s} {'Newton':>6s} {'solve s':>8s} {'peak mm':>8s} {'frames/s':>9s} "
          f"{'tracker/s':>9s} {'decode/s':>9s}  note")
    total = 0.0
    for name in a.scenarios:
        run = simulate(name, model, cfg, truth_mesh=tm)
        s = run.truth.summary()
        total += s["solve_s"]
        kf = sum(e["keyframes"] for e in s["events"])
        its = sum(e["newton_iterations"] for e in s["events"])
        peak = max(e["peak_marker_shift_mm"] for e in s["events"])
        t0 = time.perf_counter()
        data = run.frame_bytes()
        t_frames = time.perf_counter() - t0
        n_frames = data.count(b"\x00") - 1
        t0 = time.perf_counter()
        n_dec = sum(1 for _ in run.source())
        t_dec = time.perf_counter() - t0
        t0 = time.perf_counter()
        st = simulate_tracker(run.truth, cfg.tracker)
        t_trk = time.perf_counter() - t0
        note = "; ".join(f"{e['p_urethra_kPa']:.1f} kPa, near_urethra {e.get('near_urethra_shift_mm', float('nan')):.2f} mm, "
                         f"growth {e['bulb_growth_percent']:.2f} %"
                         + (f" ({e['note']})" if e.get("note") else "")
                         for e in s["events"] if e["kind"] == "inflate")
        print(f"{name:20s} {kf:5d} {its:6d} {s['solve_s']:8.1f} {peak:8.2f} {n_frames / t_frames:9.0f} "
              f"{len(st.t_take) / t_trk:9.0f} {n_dec / t_dec:9.0f}  {note}")
    print(f"truth solves, all scenarios: {total:.1f} s; load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
