"""Value objects of the estimation stage (see docs/architecture.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # pose is a leaf library; only the type is needed here
    from softphantom.pose import Pose6

ARM_NAMES: tuple[str, ...] = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
"""Arm cavity order used in every length-4 array (docs/architecture.md)."""


@dataclass(frozen=True)
class Estimate:
    """One estimate of the phantom's state at time ``t`` (SI units).

    ``force`` N (3,), ``p_urethra`` Pa, ``pose`` of the marker rigid body relative to rest,
    ``target_shift`` m per named target, ``volume_pred``/``volume_meas`` cavity volume changes
    m³ (4,), ``cond_W`` the condition number of the sensitivity matrix, ``qp_status`` the QP
    solver's status, ``step_time`` s spent on this step, ``skipped`` samples dropped since the
    previous estimate (estimation fell behind and took the newest one), ``in_envelope`` False
    when the loads lie outside the range the estimator's model covers (the atlas's envelope; the
    estimate is then clamped to it).
    """

    t: float
    force: np.ndarray
    p_urethra: float
    pose: "Pose6"
    target_shift: dict[str, np.ndarray]
    volume_pred: np.ndarray
    volume_meas: np.ndarray
    cond_W: float
    qp_status: str
    step_time: float
    skipped: int = 0
    status: str = "ok"
    in_envelope: bool = True
    extra: dict = field(default_factory=dict)


@runtime_checkable
class StateEstimator(Protocol):
    """The estimator interface: :class:`~softphantom.estimation.Estimator` (refreshed
    linearization) and :class:`~softphantom.estimation.atlas_estimator.AtlasEstimator` (precomputed atlas)
    implement it; the CLI, the live view and the demo only use this.

    ``step(measurement, skipped=0) → Estimate`` one sample; ``node_positions()`` (N,3) m of the
    last estimate; ``reset()`` back to rest; ``close()`` stops anything running in the background.
    """

    kind: str
    marker_names: tuple[str, ...]
    target_names: tuple[str, ...]

    def step(self, m, skipped: int = 0) -> Estimate: ...

    def node_positions(self) -> np.ndarray: ...

    def reset(self) -> None: ...

    def close(self) -> None: ...
