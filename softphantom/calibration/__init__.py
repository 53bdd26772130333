"""Calibration of the model and the sensors to a cast phantom on the bench (``softphantom
calibrate``): least squares over forward FEM solves (on Dask) of the material stiffness per region
group (and a Yeoh group's shape), the transducers' gains, offsets and each session's drift, the
tube volume, the tracker registration and lag, with confidence intervals, correlations and an
identifiability check. See docs/calibration.md.

Data flow: after evaluation (it reads recordings, takes and the model; it writes a model directory
that every earlier stage reads as any other).
"""

from softphantom.calibration.fit import FitOptions, FitResult, Parameter, parameter_set
from softphantom.calibration.output import write_calibration
from softphantom.calibration.run import (
    Calibration, HeldOut, SessionSpec, calibrate, check_held_out, rmse_ratio, rmse_ratio_interval,
)
from softphantom.calibration.session import CalibrationInputError, Session, load_session, select_keyframes

__all__ = [
    "Calibration",
    "CalibrationInputError",
    "FitOptions",
    "FitResult",
    "HeldOut",
    "Parameter",
    "Session",
    "SessionSpec",
    "calibrate",
    "check_held_out",
    "load_session",
    "parameter_set",
    "rmse_ratio",
    "rmse_ratio_interval",
    "select_keyframes",
    "write_calibration",
]
