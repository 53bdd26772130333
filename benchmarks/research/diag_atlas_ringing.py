"""Does a cached atlas's global f_y polynomial ring below a fold? Along a push on +y (f_x = f_z = 0,
urethra at 0 Pa) the arm volumes from the atlas's own polynomial and from a polynomial in f_y
through only the atlas's f_y nodes below ``--split-f-y-N`` (the other axes as the atlas has them),
both against converged solves. If the second is much closer, the fold's shape is carried down by
the global polynomial and a piecewise f_y axis would remove it (docs/estimation.md, Known limits).

    .venv/bin/python benchmarks/research/diag_atlas_ringing.py --model DIR --atlas-cache DIR \\
        --atlas-grid 11,9,4,3 --x-control displacement --split-f-y-N 3.4
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.interpolate import BarycentricInterpolator

from softphantom.design import load_model
from softphantom.estimation import EstimatorConfig
from softphantom.estimation.atlas import X_CONTROLS, load_or_build
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.select import atlas_config_from_options


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--atlas-cache", required=True, help="model directory holding the atlas (built if missing)")
    ap.add_argument("--atlas-grid", default=None)
    ap.add_argument("--envelope", default=None)
    ap.add_argument("--x-control", choices=X_CONTROLS, default="force")
    ap.add_argument("--contact-radius-mm", type=float, default=4.0)
    ap.add_argument("--split-f-y-N", type=float, default=3.4, help="keep the f_y nodes below this (N)")
    ap.add_argument("--f-y-N", default="0.5,1,1.5,2,2.5,3", help="pushes to compare at (N)")
    a = ap.parse_args()
    model = load_model(a.model)
    cfg = EstimatorConfig(contact_radius_m=a.contact_radius_mm * 1e-3)
    acfg = atlas_config_from_options(a.atlas_grid, a.envelope, a.x_control)
    atlas = load_or_build(model, cfg, acfg, cache_dir=a.atlas_cache, n_workers=1)
    ny = acfg.axes()[1]
    below = ny[ny < a.split_f_y_N]
    print(f"f_y nodes {np.round(ny, 3).tolist()} N; {len(below)} below {a.split_f_y_N:g} N")
    fwd = ForwardModel(model, cfg, exact_sensitivities=False)
    for fy in (float(v) for v in a.f_y_N.split(",")):
        c = atlas.coords(np.array([0.0, fy, 0.0]), 0.0)
        glob = atlas.volumes(c)[0]
        vals = np.array([atlas.volumes(np.array([c[0], y, c[2], c[3]]))[0] for y in below])
        loc = BarycentricInterpolator(below, vals)(fy)  # the polynomial through the nodes below the split
        truth = fwd.solve([0.0, fy, 0.0, 0.0]).V
        back = lambda v: (v[2] - v[3]) * 1e9  # noqa: E731  back_xpos − back_xneg, mm³
        print(f"f_y {fy:g} N: volumes max error global {np.abs(glob - truth).max() * 1e9:.3f} mm³, "
              f"below the split {np.abs(loc - truth).max() * 1e9:.3f} mm³; back pair's difference error "
              f"global {back(glob) - back(truth):+.3f}, below the split {back(loc) - back(truth):+.3f} mm³")


if __name__ == "__main__":
    main()
