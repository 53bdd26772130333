"""ROS 1 bags, ROS 2 bags (sqlite3 or mcap storage) and bare ``.mcap``/``.db3`` files, read with
``rosbags`` (its ``AnyReader`` reads all of them).

Pose topics are found by message type: ``geometry_msgs/msg/PoseStamped`` (vrpn_client_ros:
``/vrpn_client_node/<body>/pose``) and ``geometry_msgs/msg/TransformStamped`` (e.g. a Vicon bridge).
The body of a topic is its last segment, or the one before a final ``pose``.

Two clocks: the header stamp (when the tracker says the pose was captured; the default) and the
receive time (when the recorder got the message). The reader keeps the median of
``receive − stamp`` in ``meta["receive_minus_stamp_s"]``: a large value is transport latency or a
clock offset.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.tracking.track import PoseTrack, make_track

POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped")
CLOCKS = ("header_stamp", "receive_time")


def _body_of_topic(topic: str) -> str:
    parts = [p for p in topic.split("/") if p]
    if len(parts) >= 2 and parts[-1] in ("pose", "transform"):
        return parts[-2]
    return parts[-1] if parts else topic


def _diagnose(path: Path) -> str:
    """Why a file rosbags refused is broken, with a byte offset where one can be named."""
    if path.is_dir():
        return "" if (path / "metadata.yaml").exists() else " (a ROS 2 bag directory needs its metadata.yaml)"
    try:
        size = path.stat().st_size
        with path.open("rb") as fh:
            head = fh.read(4096)
            fh.seek(max(0, size - 8))
            tail = fh.read(8)
    except OSError:
        return ""
    if head.startswith(b"#ROSBAG V2.0\n"):
        # bag header record: uint32 header length, then fields "name=value" with uint32 lengths
        try:
            hlen = struct.unpack_from("<I", head, 13)[0]
            fields, off = {}, 17
            while off < 17 + hlen:
                flen = struct.unpack_from("<I", head, off)[0]
                key, _, val = head[off + 4 : off + 4 + flen].partition(b"=")
                fields[key] = val
                off += 4 + flen
            index_pos = struct.unpack("<Q", fields[b"index_pos"])[0]
        except (struct.error, KeyError):
            return f" (the ROS 1 bag header record at byte 13 is unreadable; file is {size} bytes)"
        if index_pos == 0:
            return " (the bag header has index_pos 0: the recording was not closed; `rosbag reindex` it)"
        if index_pos >= size:
            return (f" (truncated: the bag header puts the index at byte {index_pos}, the file ends at byte {size};"
                    " `rosbag reindex` recovers the messages before the cut)")
        return (f" (the index, from byte {index_pos} to the end at byte {size}, is damaged or cut short;"
                " `rosbag reindex` rebuilds it)")
    if head.startswith(b"\x89MCAP"):
        if tail != head[:8]:
            return (f" (truncated: no MCAP end magic at byte {size - 8}; the file ends at byte {size};"
                    " `mcap recover` rebuilds what is before the cut)")
        return ""
    if head.startswith(b"SQLite format 3\x00") and len(head) >= 32:
        page = struct.unpack(">H", head[16:18])[0]
        page = 65536 if page == 1 else page
        pages = struct.unpack(">I", head[28:32])[0]
        if page * pages > size:
            return f" (truncated: the SQLite header announces {page * pages} bytes, the file ends at byte {size})"
        return ""
    return f" (unknown magic {head[:8]!r} at byte 0)"


def pose_topics(path: str | Path) -> dict[str, str]:
    """Pose topics of a bag: ``{topic: message type}``."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    try:
        with AnyReader([path]) as reader:
            return {c.topic: c.msgtype for c in reader.connections if c.msgtype in POSE_TYPES}
    except Exception as exc:  # rosbags raises several types for a broken file
        raise FileFormatError(f"{path}: not a readable ROS bag: {exc}{_diagnose(path)}") from None


def read_rosbag(path: str | Path, body: str | None = None, clock: str = "header_stamp") -> PoseTrack:
    """Read one tracked body's poses from a ROS 1/ROS 2 bag or mcap file into a :class:`PoseTrack`.

    ``body`` is a body name (as in ``/vrpn_client_node/<body>/pose``) or a full topic; it may be left out when the bag has one pose topic.
    ``clock`` is ``"header_stamp"`` or ``"receive_time"``.
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if clock not in CLOCKS:
        raise FileFormatError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
    if not path.exists():
        raise FileFormatError(f"{path}: no such file or directory")
    try:
        with AnyReader([path]) as reader:
            conns = [c for c in reader.connections if c.msgtype in POSE_TYPES]
            if not conns:
                have = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in reader.connections)) or "none"
                raise FileFormatError(
                    f"{path}: no pose topic (geometry_msgs PoseStamped or TransformStamped); topics: {have}"
                )
            chosen = _choose(path, conns, body)
            t_stamp, t_recv, pos, quat, frames = [], [], [], [], set()
            for con, ts, raw in reader.messages(connections=[chosen]):
                msg = reader.deserialize(raw, con.msgtype)
                if con.msgtype.endswith("PoseStamped"):
                    p, q = msg.pose.position, msg.pose.orientation
                else:
                    p, q = msg.transform.translation, msg.transform.rotation
                t_stamp.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
                t_recv.append(ts * 1e-9)
                pos.append((p.x, p.y, p.z))
                quat.append((q.x, q.y, q.z, q.w))
                frames.add(msg.header.frame_id)
            fmt = _format_name(path, reader)
    except FileFormatError:
        raise
    except Exception as exc:  # rosbags raises several types for a broken file
        raise FileFormatError(f"{path}: not a readable ROS bag: {exc}{_diagnose(path)}") from None
    if not t_stamp:
        raise FileFormatError(f"{path}: topic {chosen.topic} has no messages")
    t_stamp, t_recv = np.array(t_stamp), np.array(t_recv)
    offset = float(np.median(t_recv - t_stamp))
    meta = {
        "format": fmt,
        "topic": chosen.topic,
        "msgtype": chosen.msgtype,
        "frame_id": ", ".join(sorted(frames)),
        "receive_minus_stamp_s": offset,
        "other_clock_t0_s": float((t_recv if clock == "header_stamp" else t_stamp)[0]),
    }
    t = t_stamp if clock == "header_stamp" else t_recv
    name = body if body is not None and not body.startswith("/") else _body_of_topic(chosen.topic)
    return make_track(t, np.array(pos), np.array(quat), clock=clock, source=f"{path} ({fmt})", name=name, meta=meta)


def _choose(path: Path, conns, body):
    by_topic = {c.topic: c for c in conns}
    if body is None:
        if len(by_topic) > 1:
            raise FileFormatError(f"{path}: {len(by_topic)} pose topics, choose a body: {', '.join(sorted(by_topic))}")
        return conns[0]
    if body in by_topic:
        return by_topic[body]
    match = [c for c in conns if _body_of_topic(c.topic) == body.strip("/")]
    if len(match) == 1:
        return match[0]
    raise FileFormatError(f"{path}: no pose topic for body {body!r}; pose topics: {', '.join(sorted(by_topic))}")


def _format_name(path: Path, reader) -> str:
    if path.suffix == ".bag" or getattr(reader, "is2", True) is False:
        return "ros1-bag"
    if path.suffix == ".mcap" or any(p.suffix == ".mcap" for p in (path.iterdir() if path.is_dir() else [])):
        return "ros2-bag (mcap)"
    return "ros2-bag (sqlite3)"
