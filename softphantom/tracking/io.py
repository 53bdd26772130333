"""One registry of tracker readers (meshio style): each format is a small reader with a content
test; the format comes from the content, then the extension, or is named. The CLI and the Python
API both go through :func:`read_track`."""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from softphantom.errors import FileFormatError
from softphantom.tracking import motive
from softphantom.tracking.track import PoseTrack


def _lazy(module: str, name: str) -> Callable[..., PoseTrack]:
    def reader(path, body=None, **options):
        import importlib

        return getattr(importlib.import_module(module), name)(path, body=body, **options)

    reader.__name__ = name
    return reader


@dataclass(frozen=True)
class TrackerFormat:
    """A registry entry: ``name``; ``reader(path, body=None, **options) -> PoseTrack``; the
    ``options`` it understands; the file ``extensions`` it claims when the content says nothing."""

    name: str
    reader: Callable[..., PoseTrack]
    options: tuple[str, ...] = ()
    extensions: tuple[str, ...] = ()
    description: str = ""


_FORMATS = (
    TrackerFormat("motive-csv", motive.read_motive_csv, ("length_unit", "rotation_order"), (),
                  "OptiTrack Motive CSV export, Format Version 1.1x-1.25"),
    TrackerFormat("optitrack-legacy-csv", motive.read_optitrack_legacy, (), (),
                  "pre-1.2 'OptiTrack Export Data' (recognised to be refused)"),
    TrackerFormat("ros1-bag", _lazy("softphantom.tracking.rosbag", "read_rosbag"), ("clock",), (".bag",),
                  "ROS 1 bag (PoseStamped / TransformStamped)"),
    TrackerFormat("ros2-bag", _lazy("softphantom.tracking.rosbag", "read_rosbag"), ("clock",), (".db3",),
                  "ROS 2 bag directory or its sqlite3 file"),
    TrackerFormat("mcap", _lazy("softphantom.tracking.rosbag", "read_rosbag"), ("clock",), (".mcap",),
                  "ROS 2 mcap file"),
    TrackerFormat("softphantom-mcap", _lazy("softphantom.tracking.recorded", "read_recorded_tracker"), (), (),
                  "softphantom session recording (/tracker channel)"),
    TrackerFormat("natnet-pcap", _lazy("softphantom.tracking.capture", "read_natnet_capture"),
                  ("natnet_version",), (".pcap", ".pcapng"), "pcap/pcapng capture of a NatNet 3.x/4.x stream"),
)
FORMATS: dict[str, TrackerFormat] = {f.name: f for f in _FORMATS}

#: format name → reader(path, body=None, **options) -> PoseTrack
READERS: dict[str, Callable[..., PoseTrack]] = {f.name: f.reader for f in _FORMATS}



_PCAP_MAGIC = (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d", b"\x0a\x0d\x0d\x0a")


def _mcap_library(head: bytes) -> str:
    """The ``library`` string of an MCAP header record ('' when unreadable)."""
    try:
        off = 8 + 1 + 8  # magic, opcode, record length
        (n,) = struct.unpack_from("<I", head, off)
        off += 4 + n  # profile
        (m,) = struct.unpack_from("<I", head, off)
        return head[off + 4: off + 4 + m].decode("utf-8", "replace")
    except struct.error:
        return ""


def sniff_bytes(head: bytes) -> str | None:
    """The format name from the first bytes of a file (None when they say nothing known).

    >>> sniff_bytes(b"#ROSBAG V2.0\\n"), sniff_bytes(b"Format Version,1.25,Take Name,x\\n")
    ('ros1-bag', 'motive-csv')
    """
    if head.startswith(b"#ROSBAG V2.0"):
        return "ros1-bag"
    if head.startswith(b"\x89MCAP"):
        return "softphantom-mcap" if _mcap_library(head).startswith("softphantom") else "mcap"
    if head.startswith(b"SQLite format 3\x00"):
        return "ros2-bag"
    if head[:4] in _PCAP_MAGIC:
        return "natnet-pcap"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not just a character cut at the end of the block
            return None
        text = head[: exc.start].decode("utf-8")
    return motive.sniff(text)


def detect_format(path: str | Path) -> str:
    """The registry's name for the format of ``path`` (by content first, then by extension)."""
    path = Path(path)
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return "ros2-bag"
        raise FileFormatError(f"{path}: a directory without metadata.yaml is not a ROS 2 bag")
    try:
        with path.open("rb") as fh:
            head = fh.read(8192)
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read ({exc.strerror})") from None
    if not head:
        raise FileFormatError(f"{path}: empty file (0 bytes)")
    name = sniff_bytes(head)
    if name is not None:
        return name
    for f in _FORMATS:
        if path.suffix.lower() in f.extensions and not head.strip() == b"":
            return f.name
    raise FileFormatError(
        f"{path}: cannot tell the tracker format (byte 0: {head[:16]!r}); known: {', '.join(FORMATS)}"
    )


def read_track(path: str | Path, body: str | None = None, format: str | None = None, **options) -> PoseTrack:
    """Read a rigid body's track from any supported tracker file.

    ``format`` is one of :data:`FORMATS` (detected when left out); ``options`` go to the reader
    (``clock=`` for bags, ``length_unit=``/``rotation_order=`` for Motive CSV, ``natnet_version=``
    for captures); an option the format has no use for is refused, naming the format.
    """
    fmt = format or detect_format(path)
    if fmt not in FORMATS:
        raise FileFormatError(f"unknown tracker format {fmt!r}; known: {', '.join(FORMATS)}")
    f = FORMATS[fmt]
    extra = [k for k, v in options.items() if v is not None and k not in f.options]
    if extra:
        raise FileFormatError(
            f"{path} ({fmt}): option(s) {', '.join(extra)} do not apply to this format"
            + (f" (it takes: {', '.join(f.options)})" if f.options else "")
        )
    return f.reader(Path(path), body=body, **{k: v for k, v in options.items() if v is not None})
