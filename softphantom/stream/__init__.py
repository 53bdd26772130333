"""Streaming and recording of estimates (see docs/stream.md).

- :mod:`~softphantom.stream.schema`: the flat, unit-named JSON message of one estimate;
- :mod:`~softphantom.stream.publisher`: ZeroMQ PUB/SUB on loopback, never blocking the estimator;
- :mod:`~softphantom.stream.recording`: the session recording (MCAP; Foxglove opens it) and its
  export to the estimate CSV that ``softphantom evaluate`` reads;
- :mod:`~softphantom.stream.foxglove`: the same scene as Foxglove's well-known messages, in the
  recording and live (``softphantom live --foxglove``).
"""

from softphantom.stream.foxglove import FoxgloveBridge, FoxgloveScene, FoxgloveServer
from softphantom.stream.publisher import DEFAULT_STREAM_PORT, EstimatePublisher, EstimateSubscriber, PublisherStats
from softphantom.stream.recording import (
    Recording,
    SessionRecorder,
    export_estimate_csv,
    json_schemas,
    measurement_to_message,
    read_estimate_csv,
    read_recording,
    tracker_message,
    write_estimate_csv,
)
from softphantom.stream.schema import (
    ESTIMATE_JSON_SCHEMA,
    csv_columns,
    estimate_json_schema,
    estimate_to_message,
    message_to_estimate,
)

__all__ = [
    "DEFAULT_STREAM_PORT", "ESTIMATE_JSON_SCHEMA", "EstimatePublisher", "EstimateSubscriber", "FoxgloveBridge",
    "FoxgloveScene", "FoxgloveServer", "PublisherStats",
    "Recording", "SessionRecorder", "csv_columns", "estimate_json_schema", "estimate_to_message",
    "export_estimate_csv", "json_schemas", "measurement_to_message", "message_to_estimate", "read_estimate_csv", "read_recording", "tracker_message",
    "write_estimate_csv",
]
