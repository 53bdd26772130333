"""Live view: a local web page (3-D surface, force arrow, targets, scrolling plots, status) fed
by an estimate source, plus the network stream and the session recording.

Sources implement :class:`~softphantom.viz.live.source.EstimateSource`; the estimator over a sensor source is
:class:`~softphantom.viz.live.source.EstimatorSource`. Run with :class:`LiveSession` or
``softphantom live``.
"""

from softphantom.viz.live.server import LiveConfig, LiveSession, LiveState
from softphantom.viz.live.source import (
    EstimateSource,
    LiveGeometry,
    EstimateReplay,
    SyntheticSource,
    ellipsoid_geometry,
    EstimatorSource,
)

__all__ = [
    "EstimateSource", "LiveConfig", "LiveGeometry", "LiveSession", "LiveState", "EstimateReplay",
    "EstimatorSource", "SyntheticSource", "ellipsoid_geometry",
]
