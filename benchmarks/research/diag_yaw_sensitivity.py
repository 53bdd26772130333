"""How strongly f_x moves the pose and the arm volumes about f_x = 0, by central differences of
converged solves: the figure that says how well the volumes must be interpolated for an angle goal.

    .venv/bin/python benchmarks/research/diag_yaw_sensitivity.py MODEL_DIR [--f-y-N 0,1.5,3] [--h-N 0.05]

Prints, per f_y, d pose/d f_x (mm/N, deg/N), d V/d f_x per arm (mm³/N) and the yaw per mm³ of the
back pair's volume difference (docs/estimation.md, Known limits).
"""

from __future__ import annotations

import argparse

import numpy as np

from softphantom.design import load_model
from softphantom.estimation import EstimatorConfig
from softphantom.estimation.forward import ForwardModel
from softphantom.pose import Pose6, rigid_fit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="model directory")
    ap.add_argument("--f-y-N", default="0,1.5,3", help="pushes along +y (N), comma-separated")
    ap.add_argument("--h-N", type=float, default=0.05, help="half step of the central difference in f_x (N)")
    ap.add_argument("--contact-radius-mm", type=float, default=4.0)
    a = ap.parse_args()
    fwd = ForwardModel(load_model(a.model), EstimatorConfig(contact_radius_m=a.contact_radius_mm * 1e-3),
                       exact_sensitivities=False)
    nm = fwd.n_markers
    rest = fwd.rest.sub_x[:nm]
    for fy in (float(v) for v in a.f_y_N.split(",")):
        pose, vol = [], []
        for fx in (-a.h_N, a.h_N):
            lin = fwd.solve([fx, fy, 0.0, 0.0])
            pose.append(Pose6.from_transform(rigid_fit(rest, lin.sub_x[:nm])).to_mm_deg())
            vol.append(lin.V * 1e9)
        dp = (pose[1] - pose[0]) / (2 * a.h_N)
        dv = (vol[1] - vol[0]) / (2 * a.h_N)
        back = dv[2] - dv[3]  # back_xpos − back_xneg (ARM_NAMES order)
        print(f"f_y {fy:g} N: d pose/d f_x {np.round(dp, 3).tolist()} (mm/N, deg/N); d V/d f_x "
              f"{np.round(dv, 2).tolist()} mm³/N; yaw per mm³ of the back pair's difference "
              f"{abs(dp[3] / back):.2f} deg")


if __name__ == "__main__":
    main()
