"""The estimator interface; its record, :class:`Estimate`, lives in :mod:`softphantom.records`."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from softphantom.records.channels import ChannelLayout
from softphantom.records.estimate import Estimate
from softphantom.records.names import ARM_NAMES

__all__ = ["ARM_NAMES", "Estimate", "StateEstimator"]


@runtime_checkable
class StateEstimator(Protocol):
    """The estimator interface: :class:`~softphantom.estimation.Estimator` (refreshed
    linearization) and :class:`~softphantom.estimation.atlas.estimator.AtlasEstimator` (precomputed atlas)
    implement it; the CLI, the live view and the demo only use this.

    ``step(measurement, skipped=0) → Estimate`` one sample; ``node_positions()`` (N,3) m of the
    last estimate; ``reset()`` back to rest; ``close()`` stops anything running in the background.
    """

    kind: str
    layout: ChannelLayout  # the phantom's channels: its estimates' volumes and pressures
    marker_names: tuple[str, ...]
    target_names: tuple[str, ...]

    def step(self, m, skipped: int = 0) -> Estimate: ...

    def node_positions(self) -> np.ndarray: ...

    def reset(self) -> None: ...

    def close(self) -> None: ...
