"""Session recording: one MCAP file with JSON channels, opened directly by Foxglove.

Channels (JSON-schema'd, ``json`` message encoding; keys carry their units):

- ``/estimate``: every estimate message (:mod:`softphantom.stream.schema`),
- ``/sensors``: every sensor sample (``Measurement``: ``t_s, seq, t_board_s, raw_*, osr,
  dp_<arm>_kPa, dV_<arm>_mm3, p_<cavity>_kPa, status``),
- ``/tracker``: tracker poses when a tracker is present (``t_s, x_mm … roll_deg, valid``),
- ``/live/geometry`` (once) and ``/live/surface`` (10 Hz): the phantom's surface at rest
  and deformed, so a replay shows the deformation without re-running the estimator;
- ``/foxglove/surface``, ``/foxglove/overlay``, ``/foxglove/tf``: the same scene as Foxglove's
  well-known messages (protobuf), which its 3D panel draws (:mod:`softphantom.stream.foxglove`).

The channels are the phantom's (its :class:`~softphantom.records.channels.ChannelLayout`): the
``/estimate`` and ``/sensors`` schemas list each volume channel's and each actuated cavity's keys,
and the metadata names them (``channels``: the layout as JSON). :attr:`Recording.layout` reads
them back; a recording of an older release without the key has its metadata's ``arm_names`` and
``cavity_names`` (JSON lists, written when not the BIP's), else the arms its messages' keys name.

Crash safety: the writer closes its chunk and flushes it to the operating system every
``flush_interval_s`` (default 1 s) and at every chunk-size limit. A session killed at any moment
(``SIGKILL``, a crash) leaves a file whose complete chunks :func:`read_recording` reads: at most the
last ``flush_interval_s`` of data is lost (``fsync=True`` also survives a power loss, at a cost).
A cleanly closed file has MCAP's summary and index, so Foxglove seeks in it; a killed one has
neither and is read sequentially (``mcap recover`` rebuilds the index).

>>> import tempfile, os
>>> path = os.path.join(tempfile.mkdtemp(), "s.mcap")
>>> from softphantom.records.channels import BIP_LAYOUT
>>> with SessionRecorder(path, layout=BIP_LAYOUT) as rec:
...     rec.write_estimate({"seq": 0, "t_s": 0.0, "force_y_N": 1.0})
>>> r = read_recording(path)
>>> r.complete, len(r.estimates), r.estimates[0]["force_y_N"], r.layout == BIP_LAYOUT
(True, 1, 1.0, True)
"""

from __future__ import annotations

import json
import os
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from softphantom.errors import FileFormatError, UserError
from softphantom.records.measurement import measurement_to_message  # noqa: F401  (re-exported)
from softphantom.records.channels import BIP_LAYOUT, LAYOUT_KEY, ChannelLayout, ChannelNames, read_layout
from softphantom.records.names import (
    POSE_COLUMNS,
    arm_names_of,
    estimate_columns,
    pressure_names_of,
    target_names,
)
from softphantom.records.session import SessionWriter, read_session_file
from softphantom.stream.foxglove import foxglove_schemas
from softphantom.stream.schema import TRACKER_JSON_SCHEMA, encode, estimate_json_schema

TOPIC_ESTIMATE = "/estimate"
TOPIC_SENSORS = "/sensors"
TOPIC_TRACKER = "/tracker"
TOPIC_GEOMETRY = "/live/geometry"
TOPIC_SURFACE = "/live/surface"


def _obj_schema(title: str, desc: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "description": desc, "type": "object", "properties": props}


_NUM = {"type": ["number", "null"]}


def sensors_json_schema(layout: ChannelLayout) -> dict[str, Any]:
    """The JSON schema of the ``/sensors`` message of a board of ``layout``: its volume channels,
    then a pressure channel per actuated cavity (the BIP's: the urethra).

    >>> abc = ChannelLayout(("a", "b", "c"), actuated=("urethra",))
    >>> [k for k in sensors_json_schema(abc)["properties"] if k.startswith("raw_")]
    ['raw_a', 'raw_b', 'raw_c', 'raw_urethra']
    >>> [k for k in sensors_json_schema(ChannelLayout(("a", "b", "c")))["properties"] if k.startswith(("raw_", "p_"))]
    ['raw_a', 'raw_b', 'raw_c']
    """
    arms, cav = layout.sensing, layout.actuated
    return _obj_schema(
        "softphantom.Measurement", "one sensor sample (sensing stage), gauge pressures tared",
        {"t_s": _NUM, "seq": {"type": "integer"}, "t_board_s": _NUM, "osr": {"type": "integer"},
         **{f"raw_{n}": {"type": "integer"} for n in (*arms, *cav)},
         **{f"dp_{a}_kPa": _NUM for a in arms}, **{f"dV_{a}_mm3": _NUM for a in arms},
         **{f"p_{c}_kPa": _NUM for c in cav}, "status": {"type": "string"}})


SENSORS_JSON_SCHEMA = sensors_json_schema(BIP_LAYOUT)
"""The BIP's ``/sensors`` schema (:func:`sensors_json_schema` of its four arms)."""
GEOMETRY_JSON_SCHEMA = _obj_schema(
    "softphantom.LiveGeometry", "phantom outer surface at rest (see softphantom.viz.live)",
    {"nodes_mm": {"type": "array"}, "faces": {"type": "array"}, "targets_mm": {"type": "object"},
     "p_ext_mm": {"type": "array"}, "contact_radius_mm": {"type": "number"}})
SURFACE_JSON_SCHEMA = _obj_schema(
    "softphantom.LiveSurface", "deformed surface node positions, float32 little-endian base64, mm",
    {"t_s": _NUM, "seq": {"type": "integer"}, "positions_mm_f32_b64": {"type": "string"}})

LEGACY_ARM_NAMES_KEY = "arm_names"
"""The metadata key of an older release's recording naming its arms (a JSON list; written when not the BIP's)."""
LEGACY_CAVITY_NAMES_KEY = "cavity_names"
"""The metadata key of an older release's recording naming its internal cavities (when not the BIP's urethra)."""


def json_schemas(layout: ChannelLayout | None) -> dict[str, dict[str, Any]]:
    """Topic → JSON schema of each JSON channel, for a phantom of ``layout`` (None: a recording
    of no phantom, a tracker's: no ``/estimate`` and ``/sensors``)."""
    phantom = {} if layout is None else {TOPIC_ESTIMATE: estimate_json_schema(layout),
                                         TOPIC_SENSORS: sensors_json_schema(layout)}
    return {**phantom, TOPIC_TRACKER: TRACKER_JSON_SCHEMA, TOPIC_GEOMETRY: GEOMETRY_JSON_SCHEMA,
            TOPIC_SURFACE: SURFACE_JSON_SCHEMA}


def tracker_message(t: float, pose: Any, valid: bool = True, name: str = "") -> dict[str, Any]:
    """The ``/tracker`` message of a ``Pose6`` (``xyz`` m, ``ypr`` rad) at time ``t`` s."""
    v = np.concatenate([np.asarray(pose.xyz, float) * 1e3, np.degrees(np.asarray(pose.ypr, float))])
    return {"t_s": float(t), **{k: float(x) for k, x in zip(POSE_COLUMNS, v)}, "valid": bool(valid), "name": name}


class SessionRecorder:
    """Write a session to an MCAP file (see the module docstring for channels and guarantees).

    Not thread-safe: write from one thread. ``metadata`` (strings) goes in an MCAP metadata record
    named ``softphantom``, with ``layout`` (the phantom's
    :class:`~softphantom.records.channels.ChannelLayout`, for the schemas and the metadata; None:
    a recording of no phantom, a tracker's alone).
    """

    def __init__(self, path: str | os.PathLike, *, layout: ChannelLayout | None, flush_interval_s: float = 1.0,
                 fsync: bool = False, metadata: Mapping[str, str] | None = None, chunk_size_bytes: int = 256 * 1024):
        from softphantom import __version__

        self.layout = layout

        self.path = Path(path)
        try:
            self._fh = open(self.path, "wb")
        except OSError as exc:
            raise UserError(f"cannot write the recording {self.path}: {exc.strerror}") from None
        self._w = Writer(self._fh, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        self._w.start(profile="", library=f"softphantom {__version__}")
        meta = {"softphantom": __version__, "created_unix_s": f"{time.time():.3f}"}
        meta.update({str(k): str(v) for k, v in (metadata or {}).items()})
        if layout is not None:
            meta.update(layout.to_meta_str())
        self._w.add_metadata("softphantom", meta)
        self._meta = meta
        self._channels: dict[str, int] = {}
        for topic, schema in json_schemas(layout).items():
            sid = self._w.register_schema(schema["title"], "jsonschema", json.dumps(schema).encode())
            self._channels[topic] = self._w.register_channel(topic, "json", sid)
        sids: dict[str, int] = {}  # Foxglove's well-known messages (softphantom.stream.foxglove)
        for topic, fs in foxglove_schemas().items():
            if fs.name not in sids:
                sids[fs.name] = self._w.register_schema(fs.name, fs.encoding, bytes(fs.data))
            self._channels[topic] = self._w.register_channel(topic, fs.encoding, sids[fs.name])
        self._seq = {t: 0 for t in self._channels}
        self._flush_interval = float(flush_interval_s)
        self._fsync = fsync
        self._last_flush = time.monotonic()
        self.messages_written = 0
        self._closed = False
        self.flush()  # header, schemas and channels reach the disk first

    def write(self, topic: str, message: Mapping[str, Any] | bytes, log_time_ns: int | None = None) -> None:
        """Write one message on ``topic`` (one of the channels above): a dict (JSON-encoded here)
        or its encoded bytes (JSON, or protobuf on the Foxglove channels)."""
        if topic not in self._channels:
            raise UserError(f"unknown recording channel {topic!r}; known: {', '.join(self._channels)}")
        now = time.time_ns() if log_time_ns is None else int(log_time_ns)
        data = message if isinstance(message, bytes) else encode(message)
        self._w.add_message(self._channels[topic], log_time=now, data=data, publish_time=now,
                            sequence=self._seq[topic] & 0xFFFFFFFF)
        self._seq[topic] += 1
        self.messages_written += 1
        if time.monotonic() - self._last_flush >= self._flush_interval:
            self.flush()

    def write_estimate(self, message: Mapping[str, Any] | bytes, log_time_ns: int | None = None) -> None:
        self.write(TOPIC_ESTIMATE, message, log_time_ns)

    def write_sensors(self, message: Mapping[str, Any], log_time_ns: int | None = None) -> None:
        self.write(TOPIC_SENSORS, message, log_time_ns)

    def write_tracker(self, message: Mapping[str, Any], log_time_ns: int | None = None) -> None:
        self.write(TOPIC_TRACKER, message, log_time_ns)

    def flush(self) -> None:
        """Close the chunk in progress and hand everything to the OS (``fsync`` if asked)."""
        self._w.flush()
        if self._fsync:
            os.fsync(self._fh.fileno())
        self._last_flush = time.monotonic()

    def close(self, metadata: Mapping[str, str] | None = None) -> None:
        """Finish the file (summary, index, footer). Idempotent. ``metadata``: what is known only
        at the end (counts), added in a last ``softphantom`` metadata record (readers take the last)."""
        if self._closed:
            return
        self._closed = True
        if metadata:
            self._w.flush()
            self._w.add_metadata("softphantom", {**self._meta, **{str(k): str(v) for k, v in metadata.items()}})
        self._w.finish()
        self._fh.close()

    def abort(self) -> None:
        """Close without the summary and footer, for a session that failed: the file then reads as a
        killed one's (``complete`` False, every flushed chunk kept)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._w.flush()
        except Exception:  # the writer may be what failed: keep what already reached the file
            pass
        finally:
            self._fh.close()

    def __enter__(self) -> "SessionRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class Recording(ChannelNames):
    """What :func:`read_recording` found: messages per channel (decoded JSON dicts, in file order),
    the ``metadata`` record, ``complete`` (the file was closed cleanly), ``bytes_read`` (where a
    truncated file's last complete record ended), ``layout`` the phantom's channels (the module
    docstring)."""

    estimates: list[dict[str, Any]]
    sensors: list[dict[str, Any]]
    tracker: list[dict[str, Any]]
    geometry: dict[str, Any] | None
    surface: list[dict[str, Any]]
    metadata: dict[str, str]
    complete: bool
    bytes_read: int = 0
    other: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    layout: ChannelLayout = BIP_LAYOUT


def iter_records(path: str | os.PathLike) -> Iterator[tuple[str, Any]]:
    """Yield ``(topic, decoded message)`` (the bytes on a channel not in JSON) and
    ``("#metadata", dict)``; a final ``("#end", info)``
    says whether the file was complete and how many bytes were read (a truncated file stops at its
    last complete chunk; that is not an error)."""
    path = Path(path)
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise UserError(f"cannot read the recording {path}: {exc.strerror}") from None
    with fh:
        head = fh.read(8)
        if head[:5] != b"\x89MCAP":
            raise FileFormatError(f"{path}: not an MCAP file (byte 0: magic {head[:8]!r})")
        fh.seek(0)
        reader = StreamReader(fh, record_size_limit=1 << 30)
        channels: dict[int, str] = {}
        binary: set[int] = set()  # channels not in JSON (Foxglove's protobuf messages): not decoded here
        complete = False
        good = 8
        try:
            for rec in reader.records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                    if rec.message_encoding != "json":
                        binary.add(rec.id)
                elif isinstance(rec, Message):
                    topic = channels.get(rec.channel_id)
                    if topic is None:
                        raise FileFormatError(f"{path}: message on unknown channel {rec.channel_id} "
                                              f"near byte {fh.tell()}")
                    if rec.channel_id in binary:
                        yield topic, rec.data
                        good = fh.tell()
                        continue
                    try:
                        yield topic, json.loads(rec.data)
                    except ValueError:
                        raise FileFormatError(f"{path}: message on {topic} near byte {fh.tell()} "
                                              "is not JSON") from None
                elif isinstance(rec, Metadata) and rec.name == "softphantom":
                    yield "#metadata", dict(rec.metadata)
                elif isinstance(rec, Footer):
                    complete = True
                good = fh.tell()
        except FileFormatError:
            raise
        except (McapError, ValueError, EOFError, OSError, struct.error, zstandard.ZstdError):
            pass  # truncated by a crash: keep every complete record before the cut
        yield "#end", {"complete": complete, "bytes_read": good if not complete else path.stat().st_size}


def read_recording(path: str | os.PathLike) -> Recording:
    """Read a whole recording (complete, or truncated by a crash: see the module docstring)."""
    per: dict[str, list[dict[str, Any]]] = {}
    meta: dict[str, str] = {}
    end = {"complete": False, "bytes_read": 0}
    for topic, msg in iter_records(path):
        if topic == "#metadata":
            meta = msg
        elif topic == "#end":
            end = msg
        elif isinstance(msg, bytes):
            continue  # Foxglove's messages: the same scene as the JSON channels (read them with mcap)
        else:
            per.setdefault(topic, []).append(msg)
    known = {TOPIC_ESTIMATE, TOPIC_SENSORS, TOPIC_TRACKER, TOPIC_GEOMETRY, TOPIC_SURFACE}
    geo = per.get(TOPIC_GEOMETRY, [])
    layout = _recorded_layout(path, meta, per.get(TOPIC_ESTIMATE, []), per.get(TOPIC_SENSORS, []))
    return Recording(
        estimates=per.get(TOPIC_ESTIMATE, []), sensors=per.get(TOPIC_SENSORS, []),
        tracker=per.get(TOPIC_TRACKER, []), geometry=geo[0] if geo else None,
        surface=per.get(TOPIC_SURFACE, []), metadata=meta, complete=bool(end["complete"]),
        bytes_read=int(end["bytes_read"]), other={k: v for k, v in per.items() if k not in known},
        layout=layout,
    )


def _names_in_meta(path, meta: Mapping[str, str], key: str, empty: bool) -> tuple[str, ...] | None:
    if key not in meta:
        return None
    try:
        names = json.loads(meta[key])
    except ValueError:
        names = None
    if not (isinstance(names, list) and (names or empty) and all(isinstance(n, str) and n for n in names)):
        raise FileFormatError(f"{path}: metadata {key} is not a JSON list of names: {meta[key]!r}")
    return tuple(names)


def _recorded_layout(path, meta: Mapping[str, str], estimates: list, sensors: list) -> ChannelLayout:
    """A recording's layout: its metadata's ``channels``; an older release's recording: its
    metadata's ``arm_names`` (else the arms its first estimate or sensor message names) and
    ``cavity_names`` (:func:`~softphantom.records.channels.read_layout`)."""
    arms = _names_in_meta(path, meta, LEGACY_ARM_NAMES_KEY, empty=False)
    for msgs, prefix in ((estimates, "dVmeas_"), (sensors, "dV_")):
        if arms is None and msgs and (names := arm_names_of(msgs[0], prefix)):
            arms = names
    cavities = _names_in_meta(path, meta, LEGACY_CAVITY_NAMES_KEY, empty=True)
    return read_layout(meta, f"{path}: metadata", sensing=arms, actuated=cavities)


def write_estimate_csv(messages: list[Mapping[str, Any]], out: str | os.PathLike,
                       metadata: Mapping[str, Any] | None, layout: ChannelLayout) -> Path:
    """Write estimate messages of a phantom of ``layout`` as the estimate file of
    docs/architecture.md (empty for missing; the layout in its metadata)."""
    from softphantom import __version__

    first = messages[0] if messages else {}
    cols = estimate_columns(target_names(first), layout)
    with SessionWriter(out, cols, {"softphantom": __version__, **(metadata or {}), **layout.to_meta()},
                       label=str(out)) as w:
        w.write_rows([m.get(c) for c in cols] for m in messages)
    return w.path


def export_estimate_csv(recording: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Export the ``/estimate`` channel of a recording to the estimate CSV read by ``evaluate``.

    Raises :class:`~softphantom.errors.FileFormatError` if the recording holds no estimate.
    """
    rec = read_recording(recording)
    if not rec.estimates:
        raise FileFormatError(f"{recording}: no message on {TOPIC_ESTIMATE}")
    meta: dict[str, Any] = {"source": f"recording:{Path(recording).name}", "complete": rec.complete}
    if "model" in rec.metadata:
        meta["model"] = rec.metadata["model"]
    if rec.geometry and "contact_radius_mm" in rec.geometry:  # the estimator's contact patch
        meta["contact_radius_mm"] = rec.geometry["contact_radius_mm"]
    return write_estimate_csv(rec.estimates, out, meta, rec.layout)


def estimate_file_layout(path, meta: Mapping[str, Any], columns) -> ChannelLayout:
    """An estimate file's layout: its metadata's ``channels``; an older release's file: the
    channels its columns name (:func:`~softphantom.records.channels.read_layout`)."""
    return read_layout(meta, f"{path}: line 1: metadata", sensing=arm_names_of(columns, "dVmeas_"),
                       actuated=pressure_names_of(columns))


def read_estimate_csv(path: str | os.PathLike) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Read an estimate file as messages: its metadata and one dict per row (numbers as float,
    missing ones None; ``qp_status`` and ``status`` text); the file's layout is
    :func:`estimate_file_layout` of them. Raises :class:`~softphantom.errors.FileFormatError`
    naming the line."""
    f = read_session_file(path)
    if "t_s" not in f.header or "force_y_N" not in f.header:
        raise FileFormatError(f"{path}: line {f.header_line}: not an estimate CSV header (needs t_s, force_*_N)")
    out = []
    for k, (line, r) in enumerate(f.rows):
        d: dict[str, Any] = {}
        for c, v in zip(f.header, r):
            if c in ("qp_status", "status"):
                d[c] = v
            else:
                try:
                    d[c] = float(v) if v != "" else None
                except ValueError:
                    raise FileFormatError(f"{path}: line {line}: column {c} is not a number: {v!r}") from None
        d["seq"] = k
        out.append(d)
    return f.meta, out
