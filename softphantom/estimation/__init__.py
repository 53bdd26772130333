"""Estimation stage: real-time inverse problem from cavity volumes to force, pose and targets.

:class:`Estimator` (with :class:`EstimatorConfig`) turns each
:class:`~softphantom.sensing.Measurement` into an :class:`Estimate`; :func:`estimate_stream` runs it
over a sensor source and writes the estimate CSV (:class:`EstimateWriter`).
"""

from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.estimator import Estimator, NoiseBound, noise_bound
from softphantom.estimation.linearization import EquilibriumSolver, Linearization
from softphantom.estimation.qp import QP_SOLVERS, QPResult, solve_volume_qp
from softphantom.estimation.stream import (
    EstimateWriter,
    estimate_columns,
    estimate_row,
    estimate_stream,
    iter_samples,
    write_estimates,
)
from softphantom.estimation.types import ARM_NAMES, Estimate

__all__ = [
    "ARM_NAMES",
    "EquilibriumSolver",
    "Estimate",
    "EstimateWriter",
    "Estimator",
    "EstimatorConfig",
    "Linearization",
    "NoiseBound",
    "QPResult",
    "QP_SOLVERS",
    "estimate_columns",
    "estimate_row",
    "estimate_stream",
    "iter_samples",
    "noise_bound",
    "solve_volume_qp",
    "write_estimates",
]
