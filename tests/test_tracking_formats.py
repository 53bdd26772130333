"""Every tracker fixture through both doors, the Python API (``read_track``/``read_truth``) and the
CLI (``softphantom evaluate``): read correctly, or refused in one line that names the format and
the actual problem."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracker_paths import OWN, shared  # noqa: E402

from softphantom.records import BIP_LAYOUT
from softphantom.cli import main  # noqa: E402
from softphantom.errors import FileFormatError  # noqa: E402
from softphantom.evaluation import read_truth, write_table  # noqa: E402
from softphantom.pose import Pose6  # noqa: E402
from softphantom.tracking import detect_format, read_track  # noqa: E402

FV125 = OWN / "motive_fv125_motive31_mm.csv"
FV121 = OWN / "motive_fv121_like.csv"
EULER = OWN / "motive_mm_euler.csv"

_OPT_FLAGS = {"body": "--body", "length_unit": "--length-unit", "rotation_order": "--rotation-order",
              "clock": "--clock", "natnet_version": "--natnet-version"}


def cli_evaluate(tmp_path, truth, capsys, **opts):
    """Run ``softphantom evaluate`` on ``truth`` against an estimate equal to what the API reads
    from it (exit code, one-line message or the printed summary, the API's series or error)."""
    try:
        api = read_truth(truth, **opts)
    except FileFormatError as exc:
        api = exc
    est = tmp_path / "est.csv"
    if not isinstance(api, Exception):
        cols = {"t_s": api.t}
        for k, name in enumerate(Pose6.COLUMNS):
            cols[name] = api.mm_deg()[:, k]
        write_table(est, {"softphantom": "test"}, cols)
    else:
        write_table(est, {"softphantom": "test"}, {"t_s": [0.0, 1.0], **{c: [0.0, 0.0] for c in Pose6.COLUMNS}})
    argv = ["evaluate", "--estimate", str(est), "--truth", str(truth), "--out", str(tmp_path / "rep"), "--overwrite",
            "--lag-ms", "0"]
    for k, v in opts.items():
        argv += [_OPT_FLAGS[k], str(v)]
    code = main(argv)
    cap = capsys.readouterr()
    return code, " ".join(cap.err.split()), cap.out, api


def assert_both_refuse(tmp_path, capsys, truth, pattern, **opts):
    code, err, _, api = cli_evaluate(tmp_path, truth, capsys, **opts)
    assert isinstance(api, FileFormatError), "the API read what it should refuse"
    assert re.search(pattern, str(api)), str(api)
    assert code == 2 and err == "error: " + " ".join(str(api).split()), err  # the same one line
    return str(api)


def assert_both_read(tmp_path, capsys, truth, **opts):
    code, err, out, api = cli_evaluate(tmp_path, truth, capsys, **opts)
    assert code == 0, err
    assert not isinstance(api, Exception)
    # the estimate is the API's truth: the CLI read the same thing iff every RMSE is 0
    rmse = [float(m.group(1)) for m in re.finditer(r"\((?:mm|deg)\)\s+│\s+([-\d.]+)", out)]
    assert len(rmse) == 6 and max(rmse) == 0.0, out
    return api


# ---------------------------------------------------------------- read correctly
def test_motive31_fv125_parent_row_mm(tmp_path, capsys):
    assert detect_format(FV125) == "motive-csv"
    tr = read_track(FV125)
    assert tr.name == "bip" and len(tr) == 30 and tr.meta["format_version"] == "1.25"
    assert tr.meta["body_id"] == "9F:D842698FB0A611F0" and tr.meta["length_units"] == "Millimeters"
    assert list(np.flatnonzero(~tr.valid)) == [7]
    i = np.arange(30)
    v = tr.valid
    want = np.column_stack([150 + 0.5 * i, 1500 - 0.25 * i, -700 + 0 * i])[v] * 1e-3
    np.testing.assert_allclose(tr.position[v], want, atol=1e-12)
    ref = Rotation.from_euler("y", (0.4 * i[v])[:, None], degrees=True).as_quat()
    np.testing.assert_allclose(np.abs(np.sum(tr.quat_xyzw[v] * ref, axis=1)), 1.0, atol=1e-11)
    # the marker spacing check used the body's own 4 markers (6 pairs): closed form
    mk = np.array([(-30, 0, -20), (30, 0, -20), (30, 0, 20), (0, 30, 0)], float)
    d = [np.linalg.norm(mk[a] - mk[b]) for a in range(4) for b in range(a + 1, 4)]
    assert tr.meta["marker_spacing_mm"] == pytest.approx(np.median(d), abs=1e-5)
    assert_both_read(tmp_path, capsys, FV125)


def test_fv121_like_plain_time_no_label_cells(tmp_path, capsys):
    tr = read_track(FV121)
    assert tr.name == "Rigid Body 1" and len(tr) == 24 and tr.valid.all()
    i = np.arange(24)
    np.testing.assert_allclose(tr.position[:, 0], 0.06 + 0.001 * i, atol=1e-12)
    ref = Rotation.from_euler("y", (0.5 * i)[:, None], degrees=True).as_quat()
    np.testing.assert_allclose(np.abs(np.sum(tr.quat_xyzw * ref, axis=1)), 1.0, atol=1e-11)
    # its markers are found through the shared ID (names 'Rigid Body 1_1'..): 0.15/0.2/0.25 m apart
    assert tr.meta["marker_spacing_mm"] == pytest.approx(200.0, abs=1e-3)
    assert_both_read(tmp_path, capsys, FV121)


def test_euler_order_given_where_the_file_does_not_say(tmp_path, capsys):
    text = EULER.read_text().replace("Rotation Type,XYZ,", "")
    p = tmp_path / "euler_no_order.csv"
    p.write_text(text)
    msg = assert_both_refuse(tmp_path, capsys, p, r"no 'Rotation Type'.*--rotation-order", body="bip")
    assert "Motive CSV, Format Version 1.23" in msg
    a = read_track(p, body="bip", rotation_order="XYZ")
    b = read_track(EULER, body="bip")
    np.testing.assert_array_equal(a.quat_xyzw, b.quat_xyzw)
    assert a.meta["rotation_type"] == "XYZ (given)"
    assert_both_read(tmp_path, capsys, p, body="bip", rotation_order="XYZ")
    # a stated order wins only when the caller agrees
    assert_both_refuse(tmp_path, capsys, EULER, r"Rotation Type 'XYZ', --rotation-order says 'ZYX'", body="bip",
                       rotation_order="ZYX")


def test_length_unit_missing_refused_with_numbers_then_given(tmp_path, capsys):
    p = tmp_path / "no_units.csv"
    p.write_text(FV125.read_text().replace("Length Units,Millimeters,", ""))
    msg = assert_both_refuse(tmp_path, capsys, p, r"no 'Length Units'.*46\.9 file units apart.*--length-unit")
    assert "469 mm in Centimeters, 46.9 mm in Millimeters" in msg  # two plausible units: no guess
    a = read_track(p, length_unit="mm")
    np.testing.assert_array_equal(a.position, read_track(FV125).position)
    assert a.meta["length_units"].startswith("Millimeters (given")
    assert_both_read(tmp_path, capsys, p, length_unit="mm")
    assert_both_refuse(tmp_path, capsys, p, r"46\.9 m in Meters.*cannot be right", length_unit="m")


def test_length_unit_inferred_only_when_one_unit_fits(tmp_path):
    # the fv1.21-like body in millimetres: 200 mm spacing is 200 m or 2 m in the other units
    text = FV121.read_bytes().decode().replace("Length Units,Meters,", "")
    lines = text.split("\r\n")
    for k in range(7, len(lines) - 1):
        cells = lines[k].split(",")
        lines[k] = ",".join(cells[:6] + [f"{float(c) * 1e3:.3f}" if c and j % 4 != 3 else c
                                         for j, c in enumerate(cells[6:])])
    p = tmp_path / "mm_no_units.csv"
    p.write_bytes("\r\n".join(lines).encode())
    tr = read_track(p)
    np.testing.assert_allclose(tr.position[:, 0], 0.06 + 0.001 * np.arange(24), atol=1e-9)
    assert tr.meta["length_units"].startswith("Millimeters (inferred")


def test_stated_units_contradicted_by_the_markers(tmp_path, capsys):
    # the case: a take in mm (or cm) labelled metres would put the body metres off the floor
    p = tmp_path / "says_metres.csv"
    p.write_text(FV125.read_text().replace("Length Units,Millimeters", "Length Units,Meters"))
    assert_both_refuse(tmp_path, capsys, p, r"\(Motive CSV, Format Version 1\.25\): rigid body 'bip': its markers are"
                                            r" 46\.9 file units apart.*46\.9 m in Meters")
    assert_both_refuse(tmp_path, capsys, FV125, r"Length Units 'Millimeters', --length-unit says 'cm'", length_unit="cm")


def test_rigid_body_blank_in_every_row(tmp_path, capsys):
    lines = FV125.read_text().split("\n")
    for k in range(8, len(lines) - 1):
        cells = lines[k].split(",")
        lines[k] = ",".join(cells[:2] + [""] * 8 + cells[10:])
    p = tmp_path / "blank_body.csv"
    p.write_text("\n".join(lines))
    assert_both_refuse(tmp_path, capsys, p, r"Format Version 1\.25\): rigid body 'bip' is blank in all 30 frames")


def test_legacy_export_named_for_what_it_is(tmp_path, capsys):
    p = OWN / "optitrack_legacy_export.csv"
    assert detect_format(p) == "optitrack-legacy-csv"
    msg = assert_both_refuse(tmp_path, capsys, p, r"legacy OptiTrack export, 'OptiTrack Export Data'")
    assert "rigid bodies enabled" not in msg


@pytest.mark.parametrize("name, text", [
    ("notes.txt", "Calibration notes\nRigid Body 1 was re-made on Monday.\n"),
    ("table.csv", "what,where\nRigid Body,shelf 2\n"),
])
def test_text_mentioning_rigid_body_is_not_a_motive_csv(tmp_path, capsys, name, text):
    p = tmp_path / name
    p.write_text(text)
    msg = assert_both_refuse(tmp_path, capsys, p, r"cannot tell the tracker format")
    assert "rigid bodies enabled" not in msg


def test_option_that_does_not_apply_names_the_format(tmp_path):
    with pytest.raises(FileFormatError, match=r"\(motive-csv\): option\(s\) clock do not apply"):
        read_track(FV125, clock="receive_time")


# ---------------------------------------------------------------- ROS 1 bag through the CLI
@pytest.fixture(scope="module")
def vicon_bag(tmp_path_factory):
    """A ROS 1 bag like the real Vicon one: TransformStamped on /vicon/<body>/<body>, frame_id
    /world, 50 Hz, header stamps 295 ms older than the receive times; the body rests for 30
    samples, then moves along x (2 mm per sample) and turns about z (0.2° per sample)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    p = tmp_path_factory.mktemp("bag") / "vicon.bag"
    with Writer(p) as w:
        topic = "/vicon/t265_tracker/t265_tracker"
        c = w.add_connection(topic, "geometry_msgs/msg/TransformStamped", typestore=ts)
        for i in range(100):
            ns = 1_600_000_000_000_000_000 + i * 20_000_000
            k = max(i - 30, 0)
            q = Rotation.from_euler("z", 0.2 * k, degrees=True).as_quat()
            msg = T["geometry_msgs/msg/TransformStamped"](
                T["std_msgs/msg/Header"](seq=i, stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                         frame_id="/world"),
                "t265_tracker",
                T["geometry_msgs/msg/Transform"](T["geometry_msgs/msg/Vector3"](x=-1.0 + 0.002 * k, y=1.35, z=0.8),
                                                 T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])),
            )
            w.write(c, ns + 295_000_000, ts.serialize_ros1(msg, "geometry_msgs/msg/TransformStamped"))
    return p


def test_ros1_bag_as_truth_through_cli_and_api(tmp_path, capsys, vicon_bag):
    head = vicon_bag.read_bytes()[:13]
    assert head == b"#ROSBAG V2.0\n"  # starts with '#', as the project's own CSV does
    api = assert_both_read(tmp_path, capsys, vicon_bag)
    assert api.meta["format"] == "ros1-bag" and api.meta["receive_minus_stamp_s"] == pytest.approx(0.295, abs=1e-6)
    k = np.maximum(np.arange(100) - 30, 0)
    np.testing.assert_allclose(api.mm_deg()[:, 0], 2.0 * k, atol=1e-6)  # x from rest, mm
    np.testing.assert_allclose(api.mm_deg()[:, 3], 0.2 * k, atol=1e-6)  # yaw, deg
    assert_both_read(tmp_path, capsys, vicon_bag, clock="receive_time")
    assert_both_refuse(tmp_path, capsys, vicon_bag, r"\(ros1-bag\): option\(s\) length_unit do not apply",
                       length_unit="mm")


# ---------------------------------------------------------------- the real files, both doors
@pytest.mark.parametrize("name", ["motive_fv1.21_quaternion_m_120Hz.csv", "motive_fv1.23_quaternion_m_120Hz_lostframe.csv",
                                  "ros1_vicon_transformstamped.bag"])
def test_real_tracker_files_both_doors(tmp_path, capsys, name):
    p = shared("tracker", name)
    api = assert_both_read(tmp_path, capsys, p)
    if name.endswith(".csv"):
        assert 150 < api.meta["marker_spacing_mm"] < 250  # the bodies' own markers, in metres files


# ---------------------------------------------------------------- the project's own recordings
def test_session_recording_tracker_channel_both_forms(tmp_path, capsys):
    from softphantom.stream.recording import SessionRecorder

    raw, rel = tmp_path / "raw.mcap", tmp_path / "rel.mcap"
    n = 90
    k = np.maximum(np.arange(n) - 60, 0)  # 0.5 s at rest at 120 Hz, then a push along y
    with SessionRecorder(raw, layout=BIP_LAYOUT) as rec:
        rec.write_estimate({"seq": 0, "t_s": 0.0})
        for i in range(n):
            q = Rotation.from_euler("x", 0.1 * k[i], degrees=True).as_quat()
            rec.write_tracker({"t_s": i / 120, "valid": i != 70, "name": "bip", "frame": 1000 + i + (i > 80),
                               "position_m": [0.2, 0.9 + 0.001 * k[i], -0.4], "quat_xyzw": list(q), "latency_ms": 5.5})
    assert detect_format(raw) == "softphantom-mcap"
    tr = read_track(raw)
    assert tr.name == "bip" and len(tr) == n and list(np.flatnonzero(~tr.valid)) == [70]
    assert tr.meta["frames_missing"] == 1 and tr.meta["latency_ms_median"] == 5.5 and not tr.meta["registered"]
    api = assert_both_read(tmp_path, capsys, raw)
    np.testing.assert_allclose(api.mm_deg()[:, 1], k[np.arange(n) != 70], atol=1e-9)  # y mm from rest
    with SessionRecorder(rel, layout=None) as rec:
        for i in range(n):
            rec.write_tracker({"t_s": i / 120, "valid": True, "name": "bip", "x_mm": 0.0, "y_mm": float(k[i]),
                               "z_mm": 0.0, "yaw_deg": 0.5 * k[i], "pitch_deg": 0.0, "roll_deg": 0.0})
    api = assert_both_read(tmp_path, capsys, rel)
    assert api.meta["registered"] is True
    np.testing.assert_allclose(api.mm_deg()[:, 1], k, atol=1e-12)
    np.testing.assert_allclose(api.mm_deg()[:, 3], 0.5 * k, atol=1e-9)
    empty = tmp_path / "no_tracker.mcap"
    with SessionRecorder(empty, layout=BIP_LAYOUT) as rec:
        rec.write_estimate({"seq": 0, "t_s": 0.0})
    assert_both_refuse(tmp_path, capsys, empty, r"\(softphantom-mcap, session recording\): no /tracker messages \(it has: /estimate\)")
