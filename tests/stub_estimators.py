"""A stand-in estimator for tests of the sensing → estimate path: it keeps nothing between samples
and echoes each measurement's pressures and volume changes (zero force, rest pose), so the stream,
its marker rows and its memory are tested without a model."""

from __future__ import annotations

import numpy as np


class EchoEstimator:
    from softphantom.records import BIP_LAYOUT as layout

    target_names = ("apex",)

    def step(self, m, skipped=0):
        from softphantom.estimation import Estimate
        from softphantom.pose import Pose6

        z = np.zeros(3)
        return Estimate(m.t, z, 0.0, Pose6(z, z), {"apex": z}, m.dp, m.dV, 1.0, "optimal", 1e-4, skipped, m.status,
                        layout=self.layout)
