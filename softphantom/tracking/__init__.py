"""Ground truth from a tracker: readers (Motive CSV, ROS 1/2 bags, mcap) → :class:`PoseTrack`,
registration into the model frame, and time alignment by cross-correlation."""

from softphantom.tracking.io import READERS, detect_format, read_track
from softphantom.tracking.motive import read_motive_csv, rigid_bodies
from softphantom.tracking.registration import (
    pose_columns,
    register_track,
    registration_from_markers,
    rest_pose,
    rest_window,
    track_pose6,
)
from softphantom.tracking.rosbag import pose_topics, read_rosbag
from softphantom.tracking.timing import LagResult, estimate_lag, shift_to_common_start
from softphantom.tracking.track import PoseTrack, make_track

__all__ = [
    "LagResult",
    "PoseTrack",
    "READERS",
    "detect_format",
    "estimate_lag",
    "make_track",
    "pose_columns",
    "pose_topics",
    "read_motive_csv",
    "read_rosbag",
    "read_track",
    "register_track",
    "registration_from_markers",
    "rest_pose",
    "rest_window",
    "rigid_bodies",
    "shift_to_common_start",
    "track_pose6",
]
