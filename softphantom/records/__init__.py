"""Records: the small value objects that cross stages, their flat forms and the session file.

The bottom of the stages (it imports only :mod:`softphantom.pose` and :mod:`softphantom.errors`),
so reading any file or message needs nothing of the FEM or the estimator:

- :mod:`~softphantom.records.names`: the BIP's arm and channel names, the pose, force, estimate
  and measurement column names, each defined once;
- :mod:`~softphantom.records.channels`: :class:`ChannelLayout`, a phantom's channels (arms,
  measured and actuated cavities), in every file's metadata;
- :mod:`~softphantom.records.estimate`: :class:`Estimate` and its one flat form (message = row);
- :mod:`~softphantom.records.measurement`: :class:`Measurement`, :class:`SourceEvent`;
- :mod:`~softphantom.records.track`: :class:`PoseTrack`;
- :mod:`~softphantom.records.session`: the ``# {json}`` + CSV session file, one writer, one reader.
"""

from softphantom.records.channels import BIP_LAYOUT, LAYOUT_KEY, ChannelLayout, read_layout
from softphantom.records.estimate import Estimate, estimate_row, estimate_to_message, message_to_estimate
from softphantom.records.measurement import Measurement, SourceEvent, measurement_to_message
from softphantom.records.names import (
    ARM_NAMES,
    BIP_CAVITIES,
    CHANNEL_NAMES,
    FORCE_COLUMNS,
    MEASUREMENT_COLUMNS,
    POSE_COLUMNS,
    arm_names_of,
    estimate_columns,
    measurement_columns,
    pressure_names_of,
)
from softphantom.records.session import (
    FILE_VERSION,
    SessionFile,
    SessionWriter,
    TruncatedRecordingWarning,
    read_session_file,
    write_session_file,
)
from softphantom.records.track import PoseTrack, make_track

__all__ = [
    "ARM_NAMES", "BIP_CAVITIES", "BIP_LAYOUT", "CHANNEL_NAMES", "ChannelLayout", "FILE_VERSION", "LAYOUT_KEY", "FORCE_COLUMNS", "MEASUREMENT_COLUMNS", "POSE_COLUMNS",
    "Estimate", "Measurement", "PoseTrack", "SessionFile", "SessionWriter", "SourceEvent",
    "TruncatedRecordingWarning", "arm_names_of", "estimate_columns", "estimate_row", "estimate_to_message", "make_track",
    "measurement_columns", "measurement_to_message", "message_to_estimate", "pressure_names_of", "read_layout", "read_session_file",
    "write_session_file",
]
