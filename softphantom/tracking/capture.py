"""A captured NatNet session (pcap or pcapng, e.g. from Wireshark or tcpdump) as a tracker file.

Packets are read with dpkt (Ethernet, Linux cooked SLL/SLL2, BSD loopback and raw-IP link types),
IPv4 fragments are put back together (a NatNet frame with many markers exceeds one Ethernet frame),
and every UDP payload that is a whole NatNet message (id 1, 5 or 7 with a size field equal to the
payload's length) is taken, whatever the ports. The NatNet version comes from the server-info reply
in the capture, else from ``natnet_version=`` (e.g. ``"4.1"``), else from the frames' layout when
exactly one version reads them to their end; the rigid body's name from the model definitions, when
captured (else give its numeric id). A frame seen twice (multicast and unicast both captured) counts
once; gaps in the frame numbers are counted in ``meta["frames_missing"]``. A capture cut inside its
last record (the capturing program killed) is read up to that record, with a warning naming its byte.

The clock is Motive's frame timestamp (``natnet_timestamp``, s since Motive's clock started);
``meta["capture_minus_timestamp_s"]`` is the median offset of the capture's own clock.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np

from softphantom.errors import FileFormatError
from softphantom.tracking.natnet import (
    NAT_FRAMEOFDATA,
    NAT_MODELDEF,
    NAT_SERVERINFO,
    SUPPORTED,
    NatNetError,
    decode_frame,
    decode_model_defs,
    decode_server_info,
    frame_version_from_size,
)
from softphantom.tracking.track import PoseTrack, make_track, warn_truncated

_NATNET_IDS = (NAT_SERVERINFO, NAT_MODELDEF, NAT_FRAMEOFDATA)


def parse_version(text: str) -> tuple[int, int]:
    """``"4.1"`` → ``(4, 1)`` (a supported NatNet version).

    >>> parse_version("3.0")
    (3, 0)
    """
    try:
        v = tuple(int(x) for x in str(text).split(".")[:2])
        v = (v + (0,))[:2]
    except ValueError:
        v = ()
    if v not in SUPPORTED:
        raise FileFormatError(f"NatNet version {text!r} not supported; known: {', '.join('%d.%d' % s for s in SUPPORTED)}")
    return v


def complete_records_end(data: bytes) -> int:
    """Where the last whole record of a pcap or pcapng capture ends (``len(data)`` unless the file
    was cut inside a record; a header too short to tell is left to the reader to refuse).

    >>> hdr = b"\\xd4\\xc3\\xb2\\xa1" + bytes(20); rec = bytes(8) + (4).to_bytes(4, "little") * 2 + b"abcd"
    >>> complete_records_end(hdr + rec + rec[:10]), len(hdr + rec)
    (44, 44)
    """
    if data[:4] == b"\x0a\x0d\x0d\x0a":  # pcapng: blocks of type, total length (each section says its byte order)
        off, order = 0, "<"
        while off + 12 <= len(data):
            if data[off:off + 4] == b"\x0a\x0d\x0d\x0a":
                order = "<" if data[off + 8:off + 12] == b"\x4d\x3c\x2b\x1a" else ">"
            (length,) = struct.unpack_from(order + "I", data, off + 4)
            if length < 12 or off + length > len(data):
                break
            off += length
        return off if off >= 12 else len(data)
    if len(data) < 24 or data[:4] not in _PCAP_ORDER:
        return len(data)
    order, off = _PCAP_ORDER[data[:4]], 24
    while off + 16 <= len(data):
        (caplen,) = struct.unpack_from(order + "I", data, off + 8)
        if off + 16 + caplen > len(data):
            break
        off += 16 + caplen
    return off


_PCAP_ORDER = {b"\xd4\xc3\xb2\xa1": "<", b"\x4d\x3c\xb2\xa1": "<", b"\xa1\xb2\xc3\xd4": ">", b"\xa1\xb2\x3c\x4d": ">"}


def udp_payloads(data: bytes, label: str):
    """``(capture time s, UDP payload, (src, sport, dst, dport))`` of every UDP/IPv4 datagram of
    the capture ``data``."""
    import dpkt

    with io.BytesIO(data) as fh:
        try:
            head = fh.read(4)
            fh.seek(0)
            reader = dpkt.pcapng.Reader(fh) if head == b"\x0a\x0d\x0d\x0a" else dpkt.pcap.Reader(fh)
        except (ValueError, dpkt.dpkt.NeedData, dpkt.dpkt.UnpackError) as exc:
            raise FileFormatError(f"{label}: byte 0: not a readable capture ({exc})") from None
        link = reader.datalink()
        frags: dict[tuple, dict[int, bytes]] = {}
        count = 0
        try:
            for ts, buf in reader:
                count += 1
                ip = _ip_of(link, buf, dpkt)
                if ip == "short":
                    raise FileFormatError(
                        f"{label}: packet {count}: the record holds only {len(buf)} bytes of its datagram"
                        " (truncated capture, or a snap length too short)")
                if ip is None or ip.p != dpkt.ip.IP_PROTO_UDP:
                    continue
                data = ip.data if isinstance(ip.data, bytes) else bytes(ip.data)
                if ip.mf or ip.offset:  # a fragment: keep until the last one, then join if none is missing
                    key = (ip.src, ip.dst, ip.id)
                    parts = frags.setdefault(key, {})
                    parts[ip.offset] = data
                    if ip.mf:
                        continue
                    joined = b""
                    for o in sorted(frags.pop(key)):
                        if o != len(joined):
                            joined = None
                            break
                        joined += parts[o]
                    if joined is None:
                        continue
                    data = joined
                if len(data) < 8:
                    continue
                udp = dpkt.udp.UDP(data)
                addr = (_dotted(ip.src), udp.sport, _dotted(ip.dst), udp.dport)
                yield float(ts), bytes(udp.data), addr
        except (dpkt.dpkt.NeedData, dpkt.dpkt.UnpackError, ValueError) as exc:
            raise FileFormatError(f"{label}: packet {count + 1}: {exc} (truncated capture?)") from None


def _dotted(b: bytes) -> str:
    return ".".join(str(x) for x in b)


def _ip_of(link: int, buf: bytes, dpkt):
    try:
        if link == dpkt.pcap.DLT_EN10MB:
            pkt = dpkt.ethernet.Ethernet(buf).data
        elif link in (dpkt.pcap.DLT_NULL, dpkt.pcap.DLT_LOOP):
            pkt = dpkt.loopback.Loopback(buf).data
        elif link == dpkt.pcap.DLT_LINUX_SLL:
            pkt = dpkt.sll.SLL(buf).data
        elif link == 276:  # DLT_LINUX_SLL2
            pkt = dpkt.sll2.SLL2(buf).data
        elif link in (dpkt.pcap.DLT_RAW, 12, 14, 228):
            pkt = dpkt.ip.IP(buf)
        else:
            raise FileFormatError(f"capture link type {link} is not read (Ethernet, Linux cooked, loopback, raw IP are)")
    except dpkt.dpkt.NeedData:
        return "short"
    except dpkt.dpkt.UnpackError:
        return None
    if isinstance(pkt, dpkt.ip.IP) and len(bytes(pkt)) < pkt.len:
        return "short"
    return pkt if isinstance(pkt, dpkt.ip.IP) else None


def read_natnet_capture(path: str | Path, body: str | None = None, natnet_version: str | None = None) -> PoseTrack:
    """Read one rigid body from a pcap/pcapng capture of a NatNet stream (see the module docstring)."""
    path = Path(path)
    label = f"{path} (natnet-pcap)"
    try:
        capture = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot read ({exc.strerror})") from None
    end = complete_records_end(capture)  # a capture cut inside its last record (tcpdump killed): drop that record
    info = defs = None
    frames_raw: list[tuple[float, bytes]] = []
    udp = 0
    for ts, data, _addr in udp_payloads(capture[:end], label):
        udp += 1
        if len(data) < 4:
            continue
        msg_id, size = int.from_bytes(data[:2], "little"), int.from_bytes(data[2:4], "little")
        if msg_id not in _NATNET_IDS or size != len(data) - 4:
            continue
        payload = data[4:]
        try:
            if msg_id == NAT_SERVERINFO:
                info = decode_server_info(payload, f"{label}: server info")
            elif msg_id == NAT_MODELDEF:
                defs = payload
            else:
                frames_raw.append((ts, payload))
        except NatNetError as exc:
            raise FileFormatError(str(exc)) from None
    if not frames_raw:
        raise FileFormatError(f"{label}: no NatNet FrameOfData among its {udp} UDP datagrams")
    given = parse_version(natnet_version) if natnet_version else None
    how = ""
    if info is not None:
        version = tuple(info.natnet_version[:2])
        if given and given != version:
            raise FileFormatError(f"{label}: the captured server info says NatNet {version[0]}.{version[1]},"
                                  f" --natnet-version says {natnet_version}")
        how = "server info"
    elif given:
        version, how = given, "given"
    else:
        version = frame_version_from_size(frames_raw[0][1])
        if version is None:
            raise FileFormatError(
                f"{label}: no server-info reply in the capture (start the capture before the client connects)"
                " and the frames' layout does not tell the NatNet version: give it (--natnet-version 3.0|4.1)"
            )
        how = "inferred from the frame layout"
    try:
        model = decode_model_defs(defs, version, f"{label}: model definitions") if defs is not None else None
        frames = [(ts, decode_frame(p, version, f"{label}: FrameOfData")) for ts, p in frames_raw]
    except NatNetError as exc:
        raise FileFormatError(str(exc)) from None
    body_id, name = _choose_body(label, model, frames, body)
    seen: dict[int, tuple[float, object]] = {}
    for ts, f in frames:
        seen.setdefault(f.frame_number, (ts, f))
    order = sorted(seen)
    t, t_cap, pos, quat, valid, lat = [], [], [], [], [], []
    for k in order:
        ts, f = seen[k]
        rb = f.body(body_id)
        t.append(f.timestamp_s)
        t_cap.append(ts)
        ok = rb is not None and rb.tracking_valid
        valid.append(ok)
        pos.append(rb.position if ok else (np.nan,) * 3)
        quat.append(rb.quat_xyzw if ok else (np.nan,) * 4)
        if info is not None and (s := f.system_latency_s(info.clock_hz)) is not None:
            lat.append(s)
    t = np.asarray(t)
    meta = {
        "format": "natnet-pcap",
        "natnet_version": f"{version[0]}.{version[1]} ({how})",
        "server": f"{info.app_name} {'.'.join(map(str, info.app_version))}" if info else "",
        "body_id": body_id,
        "frames_missing": int(order[-1] - order[0] + 1 - len(order)),
        "frames_duplicate": len(frames) - len(order),
        "capture_minus_timestamp_s": float(np.median(np.asarray(t_cap) - t)),
        "system_latency_ms_median": float(np.median(lat) * 1e3) if lat else float("nan"),
    }
    p = np.asarray(pos, float)
    p[~np.asarray(valid)] = np.nan
    if end < len(capture):
        warn_truncated(f"{label}: the capture ends inside the record at byte {end} ({len(capture) - end} bytes of it):"
                       " a packet cut short, dropped")
    return make_track(t, p, np.asarray(quat, float), clock="natnet_timestamp", source=f"{path} (natnet-pcap)",
                      name=name, meta=meta)


def _choose_body(label, model, frames, body) -> tuple[int, str]:
    ids = sorted({b.id for _, f in frames for b in f.rigid_bodies})
    names = {b.id: b.name for b in model.rigid_bodies} if model is not None else {}
    listing = ", ".join(f"{names[i]} (id {i})" if i in names else f"id {i}" for i in ids) or "none"
    if body is None:
        if len(ids) != 1:
            raise FileFormatError(f"{label}: {len(ids)} rigid bodies in the frames, choose one: {listing}")
        return ids[0], names.get(ids[0], f"id {ids[0]}")
    by_name = {v: k for k, v in names.items()}
    if body in by_name:
        return by_name[body], body
    if body.isdigit() and int(body) in ids:
        return int(body), names.get(int(body), f"id {body}")
    hint = "" if model is not None else " (no model definitions in the capture: name the body by its numeric id)"
    raise FileFormatError(f"{label}: no rigid body {body!r}; the frames have: {listing}{hint}")
