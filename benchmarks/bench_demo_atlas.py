"""The demo's push atlases against the model's exact inverse.

Replays a demo scenario's recording (``softphantom demo --out DIR``) through the atlas estimator with
the demo's box for that contact and a given grid, and through the refresh estimator in sync mode;
at the ``--samples`` samples where the two differ most in yaw, settles the refresh estimator
(``Estimator.settle``: Gauss–Newton on the forward model to 1e-7 N, the exact inverse) and prints
each estimator's largest error against it (force N, y mm, yaw and pitch °), plus the atlas's build
cost. The atlas is cached in DIR/model/atlas, so the demo's own grid costs nothing.

    python benchmarks/bench_demo_atlas.py --demo out/demo --scenario push-on-centre
    python benchmarks/bench_demo_atlas.py --demo out/demo --scenario push-off-centre --grid 7,5,5,2 --cluster-N 0.1,0,0

Figures are in docs/performance/tools.md ("push atlases checked against exact inverses").
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np


def _estimates(est, source) -> list:
    out = []
    for m in source:
        out.append((m, est.step(m)))
    return out


def _row(e) -> np.ndarray:
    p = e.pose.to_mm_deg()
    return np.array([*e.force, p[1], p[3], p[4]])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, default=Path("out/demo"), help="softphantom demo --out directory (make demo's)")
    ap.add_argument("--scenario", default="push-on-centre")
    ap.add_argument("--grid", default=None, help="NX,NY,NZ,NP (default: the demo's for the contact)")
    ap.add_argument("--cluster-N", default=None, help="force_cluster_N FX,FY,FZ (N; default: the demo's)")
    ap.add_argument("--samples", type=int, default=10, help="samples settled (where atlas and sync differ most)")
    a = ap.parse_args(argv)
    if not (a.demo / "model" / "model.npz").is_file():
        print(f"skipped: no demo output in {a.demo} (run make demo, or give --demo DIR)")
        return 0

    from softphantom.virtual.demo import push_only, shared_atlases
    from softphantom.cli.estimation import open_sensor_source
    from softphantom.design import load_model
    from softphantom.estimation import EstimatorConfig, open_estimator
    from softphantom.estimation.atlas import load_or_build
    from softphantom.estimation.estimator import Estimator
    from softphantom.virtual import BUNDLED, load_scenario

    model = load_model(a.demo / "model")
    sc = load_scenario(a.scenario)
    contact = push_only(sc)
    if contact is None:
        sys.exit(f"--scenario {a.scenario}: not a push at one contact point")
    grid = tuple(int(v) for v in a.grid.split(",")) if a.grid else None
    # the demo's atlas for this contact (its box over the bundled scenarios pushing there)
    acfg = shared_atlases([load_scenario(n) for n in BUNDLED], grid)[contact]
    if a.cluster_N:
        acfg = dataclasses.replace(acfg, force_cluster_N=tuple(float(v) for v in a.cluster_N.split(",")))
    cfg = EstimatorConfig(contact=contact, mode="sync")
    rec = a.demo / a.scenario / "recording.csv"
    c0 = time.process_time()
    at = load_or_build(model, cfg, acfg, cache_dir=a.demo / "model")
    print(f"atlas {'x'.join(map(str, acfg.shape))}, f_x cluster {acfg.cluster_N[0]:g} N, box "
          f"{np.round(acfg.force_min_N, 2).tolist()}..{np.round(acfg.force_max_N, 2).tolist()} N: "
          f"{acfg.n_solves} solves, built in {at.build_s:.0f} s, {at.build_cpu_s:.0f} CPU-s (this call "
          f"{time.process_time() - c0:.0f} CPU-s)")
    with open_estimator("atlas", model, cfg, atlas=at) as est:
        atl = _estimates(est, open_sensor_source(f"replay:{rec}", model).source)
    with Estimator(model, cfg) as est:
        syn = _estimates(est, open_sensor_source(f"replay:{rec}", model).source)
    A = np.array([_row(e) for _, e in atl])
    S = np.array([_row(e) for _, e in syn])
    d = np.abs(A - S)
    print(f"atlas vs sync over {len(A)} samples, max: F {d[:, :3].max():.3f} N, y {d[:, 3].max():.3f} mm, "
          f"yaw {d[:, 4].max():.3f}°, pitch {d[:, 5].max():.3f}°")
    pick = sorted(np.argsort(-d[:, 4])[: a.samples].tolist())
    exact = Estimator(model, cfg)
    err = {"atlas": [], "sync": []}
    for i in pick:
        x = _row(exact.settle(atl[i][0]))
        err["atlas"].append(np.abs(A[i] - x))
        err["sync"].append(np.abs(S[i] - x))
    exact.close()
    for k, v in err.items():
        v = np.array(v)
        print(f"{k} vs exact inverse at {len(pick)} samples, max: F {v[:, :3].max():.3f} N, y {v[:, 3].max():.3f} mm, "
              f"yaw {v[:, 4].max():.3f}°, pitch {v[:, 5].max():.3f}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
