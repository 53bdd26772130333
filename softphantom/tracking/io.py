"""One registry of tracker readers (meshio style): the format comes from the content, then the
extension, or is named."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from softphantom.errors import FileFormatError
from softphantom.tracking.motive import read_motive_csv
from softphantom.tracking.rosbag import read_rosbag
from softphantom.tracking.track import PoseTrack

#: format name → reader(path, body=None, **options) -> PoseTrack
READERS: dict[str, Callable[..., PoseTrack]] = {
    "motive-csv": read_motive_csv,
    "ros1-bag": read_rosbag,
    "ros2-bag": read_rosbag,
    "mcap": read_rosbag,
}
_EXTENSIONS = {".csv": "motive-csv", ".bag": "ros1-bag", ".db3": "ros2-bag", ".mcap": "mcap"}
_MAGIC = ((b"#ROSBAG", "ros1-bag"), (b"\x89MCAP", "mcap"), (b"SQLite format 3\x00", "ros2-bag"))


def detect_format(path: str | Path) -> str:
    """The registry's name for the format of ``path`` (by content first, then by extension)."""
    path = Path(path)
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return "ros2-bag"
        raise FileFormatError(f"{path}: a directory without metadata.yaml is not a ROS 2 bag")
    try:
        with path.open("rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read ({exc.strerror})") from None
    for magic, name in _MAGIC:
        if head.startswith(magic):
            return name
    text = head.decode("utf-8", "replace").lstrip("\ufeff")
    if text.startswith("Format Version") or "Rigid Body" in text:
        return "motive-csv"
    if path.suffix.lower() in _EXTENSIONS:
        return _EXTENSIONS[path.suffix.lower()]
    raise FileFormatError(
        f"{path}: cannot tell the tracker format (byte 0: {head[:16]!r}); known: {', '.join(READERS)}"
    )


def read_track(path: str | Path, body: str | None = None, format: str | None = None, **options) -> PoseTrack:
    """Read a rigid body's track from any supported tracker file.

    ``format`` is one of :data:`READERS` (detected when left out); ``options`` go to the reader
    (e.g. ``clock="receive_time"`` for bags).
    """
    fmt = format or detect_format(path)
    if fmt not in READERS:
        raise FileFormatError(f"unknown tracker format {fmt!r}; known: {', '.join(READERS)}")
    return READERS[fmt](Path(path), body=body, **options)
