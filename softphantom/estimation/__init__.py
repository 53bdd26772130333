"""Estimation stage: real-time inverse problem from cavity volumes to force, pose and targets.

Two estimators behind one interface (:class:`StateEstimator`: ``step(measurement) → Estimate``),
picked by :func:`open_estimator`: :class:`AtlasEstimator` inverts a precomputed atlas of converged
equilibria (the default: no background work, exact to interpolation error inside its envelope) and
:class:`Estimator` refreshes a linearization (sync or async). Both use :class:`ForwardModel`, the
converged equilibrium at given loads. :func:`estimate_stream` runs one over a sensor source and
writes the estimate CSV (:class:`EstimateWriter`).
"""

from softphantom.estimation.atlas.build import build_atlas
from softphantom.estimation.atlas.catalogue import load_or_build
from softphantom.estimation.atlas.config import AtlasConfig
from softphantom.estimation.atlas.estimator import AtlasEstimator
from softphantom.estimation.atlas.map import Atlas
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.estimator import Estimator, NoiseBound, noise_bound
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.linearization import EquilibriumSolver, Linearization
from softphantom.estimation.select import ESTIMATORS, open_estimator
from softphantom.estimation.qp import QP_SOLVERS, QPResult, solve_volume_qp
from softphantom.estimation.stream import (
    EstimateWriter,
    estimate_columns,
    estimate_row,
    estimate_stream,
    iter_samples,
    write_estimates,
)
from softphantom.estimation.types import ARM_NAMES, Estimate, StateEstimator

__all__ = [
    "ARM_NAMES",
    "ESTIMATORS",
    "Atlas",
    "AtlasConfig",
    "AtlasEstimator",
    "ForwardModel",
    "StateEstimator",
    "build_atlas",
    "load_or_build",
    "open_estimator",
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
