"""Tracker readers: Motive CSV (own fixtures + real exports from other labs), ROS 1/2 bags, mcap."""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softphantom.errors import FileFormatError
from softphantom.sensing.recording import TruncatedRecordingWarning
from softphantom.tracking import detect_format, pose_topics, read_track, rigid_bodies

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracker_paths import OWN  # noqa: E402
from tracker_paths import shared as _shared  # noqa: E402


def shared(name):
    return _shared("tracker", name)


# ---------------------------------------------------------------- Motive CSV, own fixtures
def test_motive_millimetres_euler_two_bodies_quoted_crlf():
    assert rigid_bodies(OWN / "motive_mm_euler.csv") == ["bip", "ref, frame"]
    tr = read_track(OWN / "motive_mm_euler.csv", body="bip")
    assert tr.name == "bip" and tr.clock == "take_time" and "motive-csv" in tr.source
    assert tr.meta["length_units"] == "Millimeters" and tr.meta["rotation_type"] == "XYZ"
    assert tr.meta["frame_rate_hz"] == 120.0
    i = np.arange(12)
    np.testing.assert_allclose(tr.t, np.round(i / 120, 6))
    assert list(np.flatnonzero(~tr.valid)) == [5]  # the blank frame
    assert np.all(np.isnan(tr.position[5]))
    v = tr.valid
    want = np.column_stack([10 + i, 20 - 0.5 * i, 30 + 0 * i]) * 1e-3
    np.testing.assert_allclose(tr.position[v], want[v], atol=1e-12)
    # Euler XYZ about the rotating axes, degrees (independent check: scipy)
    ref = Rotation.from_euler("XYZ", np.column_stack([i, -2 * i, 0.5 * i])[v], degrees=True)
    dots = np.abs(np.sum(tr.quat_xyzw[v] * ref.as_quat(), axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)
    other = read_track(OWN / "motive_mm_euler.csv", body="ref, frame")
    np.testing.assert_allclose(other.position, np.tile([0.1, 0, 0], (12, 1)), atol=1e-12)


def test_motive_body_choice_errors_list_bodies():
    with pytest.raises(FileFormatError, match=r"2 rigid bodies.*bip, ref, frame"):
        read_track(OWN / "motive_mm_euler.csv")
    with pytest.raises(FileFormatError, match=r"no rigid body named 'nope'.*bip, ref, frame"):
        read_track(OWN / "motive_mm_euler.csv", body="nope")


def test_motive_truncated_names_line():
    """Cut inside frame 8, no final newline: the rows before it are read as they are, the cut one is
    dropped with a warning naming its line and byte (and the frames the header counts)."""
    with pytest.warns(TruncatedRecordingWarning, match=r"line 16 \(byte 2074, 28 bytes\) ends without a newline: a row"
                      r" cut short, dropped; 8 of the 12 frames its metadata counts"):
        tr = read_track(OWN / "motive_truncated.csv", body="bip")
    full = read_track(OWN / "motive_mm_euler.csv", body="bip")
    np.testing.assert_array_equal(tr.t, full.t[:8])
    np.testing.assert_array_equal(tr.position, full.position[:8])


def test_real_motive_cut_inside_a_number():
    """The last row's position z ``-2.209460`` cut to ``-2.2`` (9.5 mm off) is not read as a value."""
    data = shared("motive_fv1.23_quaternion_m_120Hz_lostframe.csv").read_bytes()
    last = data.rindex(b"\n498,")
    cut = data.index(b"-2.209460", last) + len(b"-2.2")
    full = read_track(shared("motive_fv1.23_quaternion_m_120Hz_lostframe.csv"))
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "cut.csv"
        p.write_bytes(data[:cut])
        with pytest.warns(TruncatedRecordingWarning, match=rf"line 506 \(byte {last + 1}, {cut - last - 1} bytes\).*"
                          r"498 of the 499 frames"):
            tr = read_track(p)
    assert len(tr) == 498 and len(full) == 499
    np.testing.assert_array_equal(tr.position, full.position[:498])
    np.testing.assert_array_equal(tr.quat_xyzw, full.quat_xyzw[:498])


def test_motive_malformed_cell_names_line_and_column():
    with pytest.raises(FileFormatError, match=r"line 11, column 8 \(bip Position Z\): '18.5.0' is not a number"):
        read_track(OWN / "motive_malformed_row.csv", body="bip")


def test_motive_without_rigid_body():
    with pytest.raises(FileFormatError, match="no rigid body"):
        read_track(OWN / "motive_markers_only.csv")


def test_motive_header_cut_off(tmp_path):
    text = (OWN / "motive_mm_euler.csv").read_bytes()
    p = tmp_path / "head.csv"
    p.write_bytes(text[: text.index(b"Frame,Time")])
    with pytest.raises(FileFormatError, match=r"line 3 has the 'Rigid Body' type row but no 'Frame,Time"):
        read_track(p, body="bip")
    p.write_bytes(text[: text.index(b"0,0.000000")])
    with pytest.raises(FileFormatError, match="no data rows"):
        read_track(p, body="bip")
    p.write_bytes(b"")
    with pytest.raises(FileFormatError):
        read_track(p, format="motive-csv")


# ---------------------------------------------------------------- Motive CSV, real exports
def test_real_motive_fv121():
    tr = read_track(shared("motive_fv1.21_quaternion_m_120Hz.csv"))
    assert tr.name == "Rigid Body 1" and len(tr) == 250 and tr.valid.all()
    assert tr.meta["format_version"] == "1.21" and tr.meta["length_units"] == "Meters"
    assert tr.rate_hz == pytest.approx(120.0, rel=1e-3)
    np.testing.assert_allclose(tr.position[0], [0.060002, 0.019150, 0.076611])
    np.testing.assert_allclose(np.linalg.norm(tr.quat_xyzw, axis=1), 1.0, atol=1e-12)
    # the rigid body sits at the centroid of its three markers (Motive's default pivot)
    markers0 = np.array([[0.009986, 0.019136, 0.009807], [0.009956, 0.019187, 0.210196], [0.160064, 0.019128, 0.009831]])
    assert np.linalg.norm(markers0.mean(0) - tr.position[0]) < 1e-4


def test_real_motive_fv123_lost_frame():
    tr = read_track(shared("motive_fv1.23_quaternion_m_120Hz_lostframe.csv"))
    assert tr.name == "ernesto_body" and len(tr) == 499
    assert list(np.flatnonzero(~tr.valid)) == [4]
    assert tr.meta["capture_start_time"] == "2020-01-16 07.07.59.330"
    np.testing.assert_allclose(tr.quat_xyzw[0], np.array([-0.008570, -0.649345, -0.001615, -0.760444]) / np.linalg.norm([-0.008570, -0.649345, -0.001615, -0.760444]))


# ---------------------------------------------------------------- ROS bags
def test_real_ros1_vicon_transformstamped_clocks():
    p = shared("ros1_vicon_transformstamped.bag")
    assert detect_format(p) == "ros1-bag"
    assert pose_topics(p) == {"/vicon/t265_tracker/t265_tracker": "geometry_msgs/msg/TransformStamped"}
    tr = read_track(p)
    assert tr.clock == "header_stamp" and tr.name == "t265_tracker" and len(tr) == 57 and tr.valid.all()
    assert tr.rate_hz == pytest.approx(50.0, rel=0.01)
    assert tr.meta["receive_minus_stamp_s"] == pytest.approx(0.295, abs=0.01)
    rt = read_track(p, clock="receive_time")
    assert np.median(rt.t - tr.t) == pytest.approx(tr.meta["receive_minus_stamp_s"])
    np.testing.assert_allclose(tr.position[0], [-1.0275484874791208, 1.356312360541053, 0.8057809045368314])


def _pose_msgs(typestore, n, body_offset):
    PS = typestore.types["geometry_msgs/msg/PoseStamped"]
    Header, Time = typestore.types["std_msgs/msg/Header"], typestore.types["builtin_interfaces/msg/Time"]
    Pose = typestore.types["geometry_msgs/msg/Pose"]
    Point, Quat = typestore.types["geometry_msgs/msg/Point"], typestore.types["geometry_msgs/msg/Quaternion"]
    q = Rotation.from_euler("ZXY", np.column_stack([np.linspace(0, 0.2, n), np.zeros(n), np.zeros(n)])).as_quat()
    out = []
    seq = {"seq": 0} if "seq" in Header.__dataclass_fields__ else {}  # ROS 1 headers have a seq
    for i in range(n):
        stamp_ns = 1_700_000_000_000_000_000 + i * 8_333_333
        msg = PS(
            Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="world", **seq),
            Pose(position=Point(x=body_offset + 0.001 * i, y=0.002, z=0.003),
                 orientation=Quat(x=q[i, 0], y=q[i, 1], z=q[i, 2], w=q[i, 3])),
        )
        out.append((stamp_ns + 50_000_000, msg))  # received 50 ms after the stamp
    return out


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """ROS 1 bag, ROS 2 sqlite3 bag and ROS 2 mcap bag with vrpn_client_ros topics for 2 bodies."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    d = tmp_path_factory.mktemp("bags")
    out = {}
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    p1 = d / "vrpn.bag"
    with Writer1(p1) as w:
        for body, off in (("bip", 0.0), ("ref", 1.0)):
            c = w.add_connection(f"/vrpn_client_node/{body}/pose", "geometry_msgs/msg/PoseStamped", typestore=ts1)
            for ts, msg in _pose_msgs(ts1, 30, off):
                w.write(c, ts, ts1.serialize_ros1(msg, "geometry_msgs/msg/PoseStamped"))
    out["ros1"] = p1
    ts2 = get_typestore(Stores.ROS2_HUMBLE)
    for key, plug in (("sqlite3", StoragePlugin.SQLITE3), ("mcap", StoragePlugin.MCAP)):
        p2 = d / f"vrpn_{key}"
        with Writer2(p2, version=8, storage_plugin=plug) as w:
            for body, off in (("bip", 0.0), ("ref", 1.0)):
                c = w.add_connection(f"/vrpn_client_node/{body}/pose", "geometry_msgs/msg/PoseStamped", typestore=ts2)
                for ts, msg in _pose_msgs(ts2, 30, off):
                    w.write(c, ts, ts2.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
        out[key] = p2
    return out


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_vrpn_bags_roundtrip(bags, kind):
    p = bags[kind]
    with pytest.raises(FileFormatError, match=r"2 pose topics.*/vrpn_client_node/bip/pose, /vrpn_client_node/ref/pose"):
        read_track(p)
    with pytest.raises(FileFormatError, match="no pose topic for body 'nobody'"):
        read_track(p, body="nobody")
    tr = read_track(p, body="bip")
    assert tr.name == "bip" and len(tr) == 30 and tr.valid.all()
    np.testing.assert_allclose(tr.position[:, 0], 0.001 * np.arange(30), atol=1e-15)
    np.testing.assert_allclose(np.diff(tr.t), 1 / 120, atol=1e-6)
    assert tr.meta["receive_minus_stamp_s"] == pytest.approx(0.050, abs=1e-6)
    yaw = Rotation.from_quat(tr.quat_xyzw).as_euler("ZXY")[:, 0]
    np.testing.assert_allclose(yaw, np.linspace(0, 0.2, 30), atol=1e-12)
    rt = read_track(p, body="/vrpn_client_node/ref/pose", clock="receive_time")
    assert rt.clock == "receive_time"
    np.testing.assert_allclose(rt.t - tr.t, 0.050, atol=1e-6)
    np.testing.assert_allclose(rt.position[:, 0], 1.0 + 0.001 * np.arange(30), atol=1e-15)
    # a bare storage file reads the same as its bag directory
    if kind != "ros1":
        (inner,) = [f for f in p.iterdir() if f.suffix in (".db3", ".mcap")]
        assert detect_format(inner) == ("mcap" if kind == "mcap" else "ros2-bag")
        np.testing.assert_array_equal(read_track(inner, body="bip").position, tr.position)


def test_truncated_ros1_bag_names_offset(tmp_path, bags):
    data = bags["ros1"].read_bytes()
    p = tmp_path / "cut.bag"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match=rf"truncated: the bag header puts the index at byte \d+, the file ends at byte {len(data) // 2}"):
        read_track(p, body="bip")


def test_truncated_real_ros1_bag(tmp_path):
    data = shared("ros1_vicon_transformstamped.bag").read_bytes()
    p = tmp_path / "cut.bag"
    p.write_bytes(data[:200_000])
    with pytest.raises(FileFormatError, match="file ends at byte 200000"):
        read_track(p)


def test_truncated_mcap_and_sqlite(tmp_path, bags):
    (m,) = bags["mcap"].glob("*.mcap")
    data = m.read_bytes()
    p = tmp_path / "cut.mcap"
    p.write_bytes(data[: len(data) - 100])
    with pytest.raises(FileFormatError, match=rf"truncated: no MCAP end magic.*ends at byte {len(data) - 100}"):
        read_track(p)
    (s,) = bags["sqlite3"].glob("*.db3")
    data = s.read_bytes()
    p = tmp_path / "cut.db3"
    p.write_bytes(data[:5000])
    with pytest.raises(FileFormatError, match=r"truncated: the SQLite header announces \d+ bytes, the file ends at byte 5000"):
        read_track(p)


def test_garbage_and_unknown(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"\x00\x01garbage")
    with pytest.raises(FileFormatError, match="cannot tell the tracker format"):
        read_track(p)
    p = tmp_path / "x.bag"
    p.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 40)
    with pytest.raises(FileFormatError, match="not a readable ROS bag"):
        read_track(p)
    with pytest.raises(FileFormatError, match="no such file"):
        read_track(tmp_path / "missing.bag", format="ros1-bag")
