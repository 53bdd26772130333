"""NatNet: the real Motive 2.1 packets decode to OptiTrack's own SampleClient printout; frames,
model definitions and server info round-trip through our encoder for 3.0 and 4.1; a pcap/pcapng
capture of a session is a truth file through the API and the CLI."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracker_paths import shared  # noqa: E402

from softphantom.errors import FileFormatError  # noqa: E402
from softphantom.sensing.recording import TruncatedRecordingWarning  # noqa: E402
from softphantom.tracking import detect_format, read_track  # noqa: E402
from softphantom.tracking.natnet import (  # noqa: E402
    NAT_FRAMEOFDATA,
    NAT_MODELDEF,
    NAT_SERVERINFO,
    Frame,
    LabeledMarker,
    ModelDefs,
    NatNetError,
    RigidBody,
    RigidBodyDef,
    ServerInfo,
    decode_packet,
    encode_frame,
    encode_model_defs,
    encode_server_info,
    frame_version_from_size,
    split_packet,
)


def real(name):
    return shared("natnet", name).read_bytes()


def sample_client_frame(frame_id: int) -> dict:
    """The values OptiTrack's SampleClient printed for one frame (2 decimals)."""
    text = shared("natnet", "SampleClient_output.txt").read_text()
    head = text[: text.index("FrameID :")]
    block = text[text.index(f"FrameID : {frame_id}"):]
    block = block[: block.index("Device [Count=", 1)]
    num = r"(-?[\d.]+)"
    out = {
        "app": re.search(r"Application: (\w+) \(ver\. ([\d.]+)\)", head).groups(),
        "natnet": re.search(r"NatNet Version: ([\d.]+)", head).group(1),
        "timestamp": float(re.search(r"Timestamp : " + num, block).group(1)),
        "software_ms": float(re.search(r"Software latency : " + num, block).group(1)),
        "system_ms": float(re.search(r"System latency : " + num, block).group(1)),
        "other": [tuple(map(float, m)) for m in re.findall(r"Other Marker \d+ : " + r"\s+".join([num] * 3), block)],
        "rb": re.search(r"Rigid Body \[ID=(\d+)\s+Error=" + num + r"\s+Valid=(\d)\]", block).groups(),
        "rb_pose": tuple(map(float, re.search(r"qw\s+" + r"\s+".join([num] * 7), block).groups())),
        "labeled": re.findall(r"ModelID=(\d+), MarkerID=(\d+), Occluded=(\d), PCSolved=(\d), ModelSolved=(\d)\] "
                              r"\[size=" + num + r"\] \[pos=" + ",".join([num] * 3) + r"\]", block),
    }
    return out


# ---------------------------------------------------------------- the real packets
def test_real_server_info():
    msg, info = decode_packet(real("serverinfo_packet_v3.bin"))
    ref = sample_client_frame(162734)
    assert msg == NAT_SERVERINFO
    assert info.app_name == ref["app"][0] == "Motive"  # the uninitialised bytes after the NUL are ignored
    assert ".".join(map(str, info.app_version)) == ref["app"][1] == "2.1.0.0"
    assert ".".join(map(str, info.natnet_version)) == ref["natnet"] == "3.0.0.0"
    assert info.clock_hz == 3312787 and info.data_port == 1511
    assert info.multicast and info.multicast_group == "239.255.42.99"


def test_real_model_definitions():
    msg, defs = decode_packet(real("modeldef_packet_v3.bin"), (3, 0))
    assert msg == NAT_MODELDEF
    assert defs.marker_sets == {"RaceQuad": tuple(f"Marker{i}" for i in range(1, 6)),
                                "all": tuple(f"RaceQuad_{i}" for i in range(1, 6))}
    (rb,) = defs.rigid_bodies
    assert (rb.name, rb.id, rb.parent_id, len(rb.markers)) == ("RaceQuad", 2, -1, 5)
    # the markers' offsets are a rigid body's: a few cm to a few dm from the pivot
    d = np.linalg.norm(np.array(rb.markers), axis=1)
    assert np.all((0.02 < d) & (d < 0.3))
    assert defs.body_id("RaceQuad") == 2


def test_real_frame_equals_sample_client_printout():
    _, info = decode_packet(real("serverinfo_packet_v3.bin"))
    msg, f = decode_packet(real("mocapframe_packet_v3.bin"), info.version)
    ref = sample_client_frame(162734)
    assert msg == NAT_FRAMEOFDATA and f.frame_number == 162734
    assert round(f.timestamp_s, 2) == ref["timestamp"]
    assert round(f.software_latency_s(info.clock_hz) * 1e3, 2) == ref["software_ms"]
    assert round(f.system_latency_s(info.clock_hz) * 1e3, 2) == ref["system_ms"]
    assert np.array_equal(np.round(np.array(f.other_markers), 2), np.array(ref["other"]))
    (rb,) = f.rigid_bodies
    rid, err, valid = ref["rb"]
    assert rb.id == int(rid) and round(rb.mean_error, 2) == float(err) and rb.tracking_valid == bool(int(valid))
    np.testing.assert_array_equal(np.round(np.r_[rb.position, rb.quat_xyzw], 2), ref["rb_pose"])
    got = [(m.model_id, m.marker_id, int(m.occluded), int(m.pc_solved), int(m.model_solved),
            round(m.size, 2), *np.round(m.position, 2)) for m in f.labeled_markers]
    want = [tuple(int(x) for x in r[:5]) + tuple(float(x) for x in r[5:]) for r in ref["labeled"]]
    assert got == want and len(got) == 6
    # the upstream reference values (float32 exact to 7 digits)
    np.testing.assert_allclose(rb.position, (0.1744466, 1.4471314, -0.7343040), atol=5e-8)
    np.testing.assert_allclose(rb.quat_xyzw, (-0.05459423, 0.5099482, 0.04370357, -0.8573577), atol=5e-8)
    assert rb.mean_error == pytest.approx(0.0005152203, abs=1e-10) and f.timestamp_s == pytest.approx(1356.117, abs=5e-4)


def test_real_frame_reencodes_to_the_captured_bytes():
    data = real("mocapframe_packet_v3.bin")
    _, f = decode_packet(data, (3, 0))
    assert encode_frame(f, (3, 0)) == data
    assert frame_version_from_size(split_packet(data)[1]) == (3, 0)
    _, defs = decode_packet(real("modeldef_packet_v3.bin"), (3, 0))
    assert decode_packet(encode_model_defs(defs, (3, 0)), (3, 0))[1] == defs


def test_real_frame_truncated_names_the_byte():
    data = real("mocapframe_packet_v3.bin")
    cut = data[:200]
    with pytest.raises(NatNetError, match=r"byte 2: payload size 332 but only 196 bytes follow"):
        decode_packet(cut, (3, 0))
    with pytest.raises(NatNetError, match=r"FrameOfData \(NatNet 3\.0\): payload byte 196: labeled marker residual needs 4 bytes, the packet ends at byte 196"):
        decode_packet(cut[:2] + (196).to_bytes(2, "little") + cut[4:], (3, 0))


# ---------------------------------------------------------------- our encoder, both layouts
def synthetic_frame(i: int, valid: bool = True) -> Frame:
    """Frame i of a synthetic session: body 2 at (0.17 + 0.001 i, 1.45, −0.73) m, turning about y."""
    a = np.radians(0.2 * i) / 2
    return Frame(
        frame_number=1000 + i,
        marker_sets={"bip": ((0.1, 1.5, -0.8), (0.2, 1.5, -0.7))},
        other_markers=((0.3, 1.4, -0.7),),
        rigid_bodies=(RigidBody(2, (0.17 + 0.001 * i, 1.45, -0.73), (0.0, np.sin(a), 0.0, np.cos(a)), 0.0005, valid),
                      RigidBody(5, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 1.0))),
        labeled_markers=(LabeledMarker((2 << 16) | 1, (0.1, 1.5, -0.8), 0.02, 0x0A, 0.0002),),
        timestamp_s=500.0 + i / 120, stamp_mid_exposure=10_000_000 + i * 27_606,
        stamp_data_received=10_000_000 + i * 27_606 + 15_290, stamp_transmit=10_000_000 + i * 27_606 + 18_204,
        params=0x01,
    )


DEFS = ModelDefs({"bip": ("Marker1", "Marker2")},
                 (RigidBodyDef(2, "bip", -1, (0, 0, 0), ((0.03, 0, 0), (-0.03, 0, 0.02), (0, 0.03, 0))),
                  RigidBodyDef(5, "ref", -1, (0, 0, 0), ((0.05, 0, 0), (0, 0.05, 0), (0, 0, 0.05)))))


@pytest.mark.parametrize("version", [(3, 0), (4, 0), (4, 1), (4, 2)])
def test_roundtrip_each_version(version):
    f = synthetic_frame(3)
    _, g = decode_packet(encode_frame(f, version), version)
    assert g.frame_number == f.frame_number and g.params == 1 and g.is_recording and not g.models_changed
    np.testing.assert_allclose(g.rigid_bodies[0].position, f.rigid_bodies[0].position, rtol=1e-7)
    assert g.labeled_markers[0].model_id == 2 and g.labeled_markers[0].marker_id == 1 and g.labeled_markers[0].pc_solved
    assert g.timestamp_s == f.timestamp_s
    assert (g.precision_s is not None) == (version >= (4, 1))
    _, d = decode_packet(encode_model_defs(DEFS, version), version)
    assert d.marker_sets == DEFS.marker_sets and [b.name for b in d.rigid_bodies] == ["bip", "ref"]
    assert bool(d.rigid_bodies[0].marker_names) == (version >= (4, 0))
    # the 4.1 layout read as 3.0 (or the reverse) is refused, never misread
    other = (3, 0) if version >= (4, 1) else (4, 1)
    with pytest.raises(NatNetError):
        decode_packet(encode_frame(f, version), other)
    if version in ((3, 0), (4, 1)):
        assert frame_version_from_size(split_packet(encode_frame(f, version))[1]) == version


# ---------------------------------------------------------------- captures
def _udp_packet(payload, sport, dport, ident, src=b"\xc0\xa8\x00\x6a", dst=b"\xc0\xa8\x00\x64"):
    import dpkt

    udp = dpkt.udp.UDP(sport=sport, dport=dport, data=payload)
    udp.ulen = 8 + len(payload)
    return dpkt.ip.IP(src=src, dst=dst, p=dpkt.ip.IP_PROTO_UDP, data=udp, id=ident, ttl=64)


def _fragments(ip, size=480):
    """IPv4 fragments of ``ip`` (payload cut every ``size`` bytes, a multiple of 8)."""
    import dpkt

    body = bytes(ip.data)
    out = []
    for k in range(0, len(body), size):
        part = body[k:k + size]
        frag = dpkt.ip.IP(src=ip.src, dst=ip.dst, p=ip.p, id=ip.id, ttl=64, data=part)
        frag.offset, frag.mf = k, int(k + size < len(body))
        out.append(frag)
    return out


def write_capture(path, messages, pcapng=False, fragment_every=0):
    """``messages``: (time s, NatNet packet bytes, from command port?) → a pcap(ng) on Ethernet."""
    import dpkt

    with open(path, "wb") as fh:
        w = dpkt.pcapng.Writer(fh) if pcapng else dpkt.pcap.Writer(fh)
        for k, (ts, data, command) in enumerate(messages):
            ip = _udp_packet(data, 1510 if command else 1511, 50000 if command else 1511, k + 1)
            parts = _fragments(ip) if fragment_every and k % fragment_every == 0 else [ip]
            for p in parts:
                eth = dpkt.ethernet.Ethernet(src=b"\x02" * 6, dst=b"\x04" * 6, type=dpkt.ethernet.ETH_TYPE_IP, data=p)
                w.writepkt(bytes(eth), ts=ts)
    return path


def session(version=(4, 1), n=120, lost=(50,), dropped=(80,), server_info=True, defs=True):
    info = ServerInfo("Motive", (3, 1, 0, 0), tuple(version) + (0, 0), 3312787, 1511, False, "0.0.0.0")
    msgs = []
    if server_info:
        msgs.append((10.0, encode_server_info(info), True))
    if defs:
        msgs.append((10.001, encode_model_defs(DEFS, version), True))
    for i in range(n):
        if i in dropped:
            continue
        msgs.append((10.01 + i / 120, encode_frame(synthetic_frame(i, i not in lost), version), False))
    return msgs


@pytest.mark.parametrize("pcapng", [False, True])
@pytest.mark.parametrize("version", [(3, 0), (4, 1)])
def test_capture_as_tracker_file(tmp_path, version, pcapng):
    msgs = session(version)
    msgs.insert(40, msgs[40])  # the same frame twice (multicast and unicast captured)
    p = write_capture(tmp_path / ("s.pcapng" if pcapng else "s.pcap"), msgs, pcapng, fragment_every=7)
    assert detect_format(p) == "natnet-pcap"
    with pytest.raises(FileFormatError, match=r"\(natnet-pcap\): 2 rigid bodies in the frames, choose one: bip \(id 2\), ref \(id 5\)"):
        read_track(p)
    tr = read_track(p, body="bip")
    assert tr.name == "bip" and len(tr) == 119 and list(np.flatnonzero(~tr.valid)) == [50]
    assert tr.meta["frames_missing"] == 1 and tr.meta["frames_duplicate"] == 1
    assert tr.meta["natnet_version"] == f"{version[0]}.{version[1]} (server info)"
    assert tr.meta["system_latency_ms_median"] == pytest.approx(18204 / 3312787 * 1e3)
    i = np.array([k for k in range(120) if k != 80])
    np.testing.assert_allclose(tr.t, 500.0 + i / 120)
    v = tr.valid
    np.testing.assert_allclose(tr.position[v, 0], (0.17 + 0.001 * i[v]).astype(np.float32), rtol=1e-7)
    assert tr.meta["capture_minus_timestamp_s"] == pytest.approx(10.01 - 500.0, abs=1e-6)


def test_capture_without_server_info(tmp_path):
    p = write_capture(tmp_path / "late.pcap", session((4, 1), server_info=False, defs=False))
    tr = read_track(p, body="2")
    assert tr.meta["natnet_version"] == "4.1 (inferred from the frame layout)" and tr.name == "id 2"
    with pytest.raises(FileFormatError, match=r"no rigid body 'bip'.*numeric id"):
        read_track(p, body="bip")
    tr = read_track(p, body="2", natnet_version="4.1")
    assert tr.meta["natnet_version"] == "4.1 (given)"
    with pytest.raises(FileFormatError, match=r"FrameOfData \(NatNet 3\.0\): payload byte"):
        read_track(p, body="2", natnet_version="3.0")
    p2 = write_capture(tmp_path / "with_info.pcap", session((3, 0)))
    with pytest.raises(FileFormatError, match=r"server info says NatNet 3\.0, --natnet-version says 4\.1"):
        read_track(p2, body="bip", natnet_version="4.1")


def test_capture_broken(tmp_path):
    p = write_capture(tmp_path / "s.pcap", session((3, 0)))
    data = p.read_bytes()
    full = read_track(p, body="bip")
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(data[: len(data) - 30])  # the capturing program killed inside the last record
    last = len(data) - (16 + len(split_packet(encode_frame(synthetic_frame(119), (3, 0)))[1]) + 4 + 42)
    with pytest.warns(TruncatedRecordingWarning, match=rf"natnet-pcap\): the capture ends inside the record at byte"
                      rf" {last} \({len(data) - 30 - last} bytes of it\): a packet cut short, dropped"):
        tr = read_track(cut, body="bip")
    np.testing.assert_array_equal(tr.position, full.position[:-1])
    # a record cut by the capture's snap length (not by the end of the file) is refused
    snap = bytearray(data)
    first = 24 + 16 + int.from_bytes(data[32:36], "little")  # the 2nd record: model definitions
    n = int.from_bytes(data[first + 8:first + 12], "little")
    snap[first + 8:first + 12] = (60).to_bytes(4, "little")
    cut.write_bytes(bytes(snap[: first + 16 + 60]) + bytes(snap[first + 16 + n:]))
    with pytest.raises(FileFormatError, match=r"natnet-pcap\): packet 2: the record holds only 60 bytes.*snap length"):
        read_track(cut, body="bip")
    empty = write_capture(tmp_path / "e.pcap", [(1.0, b"\x08\x00\x03\x00hi\x00", True)])
    with pytest.raises(FileFormatError, match=r"no NatNet FrameOfData among its 1 UDP datagrams"):
        read_track(empty)


def test_capture_of_the_real_packets(tmp_path):
    msgs = [(1.0, real("serverinfo_packet_v3.bin"), True), (1.01, real("modeldef_packet_v3.bin"), True),
            (1.02, real("mocapframe_packet_v3.bin"), False)]
    tr = read_track(write_capture(tmp_path / "real.pcap", msgs))
    assert tr.name == "RaceQuad" and tr.meta["server"] == "Motive 2.1.0.0"
    np.testing.assert_allclose(tr.position[0], (0.1744466, 1.4471314, -0.7343040), atol=5e-8)


def test_capture_through_cli_and_api(tmp_path, capsys):
    from test_tracking_formats import assert_both_read, assert_both_refuse

    msgs = session((4, 1), n=240)
    p = write_capture(tmp_path / "take.pcapng", msgs, pcapng=True)
    api = assert_both_read(tmp_path, capsys, p, body="bip")
    assert api.meta["format"] == "natnet-pcap"
    assert_both_refuse(tmp_path, capsys, p, r"\(natnet-pcap\): no rigid body 'nobody'", body="nobody")
