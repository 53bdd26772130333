"""Every tracker reader on a file cut short: at any byte offset it returns the exact prefix of the
samples (no value changed) or refuses with a one-line ``UserError``; never a raw exception.

Cut offsets are drawn by hypothesis (derandomized: the same offsets every run), over the project's
own Motive CSV fixtures, the real exports in ``../shared/fixtures`` (when present), the truth CSV and
session recording that ``softphantom track`` writes, NatNet captures (pcap, pcapng, the real Motive
packets) and ROS 1 / ROS 2 (sqlite3, mcap) bags.
"""

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracker_paths import OWN, SHARED_ROOT  # noqa: E402

from softphantom.errors import UserError  # noqa: E402
from softphantom.evaluation import read_truth  # noqa: E402
from softphantom.sensing.recording import TruncatedRecordingWarning  # noqa: E402
from softphantom.tracking import read_track  # noqa: E402

EXAMPLES = 40  # offsets per file drawn by hypothesis
GRID = 50  # evenly spaced offsets per file
TAIL = 100  # every offset of the last bytes


def _sink_files(d: Path) -> dict[str, Path]:
    """The truth CSV and session recording that ``track`` writes (with lost frames)."""
    from test_tracking_record import feed

    from softphantom.tracking.record import TrackerSink

    out = {}
    for suffix in (".csv", ".mcap"):
        p = d / f"take{suffix}"
        with TrackerSink(p, body="bip", meta={"natnet_server": "127.0.0.1:1510"}) as sink:
            feed(sink)
        out[suffix] = p
    return out


def _captures(d: Path) -> dict[str, Path]:
    from test_natnet import real, session, write_capture

    out = {"pcap": write_capture(d / "s.pcap", session((3, 0), n=30, lost=(12,), dropped=(20,))),
           "pcapng": write_capture(d / "s.pcapng", session((4, 1), n=30, lost=(12,), dropped=(20,)), pcapng=True)}
    try:
        msgs = [(1.0, real("serverinfo_packet_v3.bin"), True), (1.01, real("modeldef_packet_v3.bin"), True),
                (1.02, real("mocapframe_packet_v3.bin"), False)]
        out["real-pcap"] = write_capture(d / "real.pcap", msgs)
    except pytest.skip.Exception:
        pass
    return out


def _bags(d: Path) -> dict[str, Path]:
    """One vrpn body, 20 poses: a ROS 1 bag and the storage files of ROS 2 sqlite3 and mcap bags."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_typestore
    from test_tracking_readers import _pose_msgs

    topic, kind = "/vrpn_client_node/bip/pose", "geometry_msgs/msg/PoseStamped"
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    out = {"ros1": d / "vrpn.bag"}
    with Writer1(out["ros1"]) as w:
        c = w.add_connection(topic, kind, typestore=ts1)
        for t, msg in _pose_msgs(ts1, 20, 0.0):
            w.write(c, t, ts1.serialize_ros1(msg, kind))
    ts2 = get_typestore(Stores.ROS2_HUMBLE)
    for key, plug in (("sqlite3", StoragePlugin.SQLITE3), ("mcap", StoragePlugin.MCAP)):
        with Writer2(d / key, version=8, storage_plugin=plug) as w:
            c = w.add_connection(topic, kind, typestore=ts2)
            for t, msg in _pose_msgs(ts2, 20, 0.0):
                w.write(c, t, ts2.serialize_cdr(msg, kind))
        (out[key],) = [f for f in (d / key).iterdir() if f.suffix in (".db3", ".mcap")]
    return out


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """name → (path, reader, whether every loss of samples is detectable from the file itself)."""
    d = tmp_path_factory.mktemp("whole")
    out = {}
    for name in ("motive_mm_euler.csv", "motive_fv121_like.csv", "motive_fv125_motive31_mm.csv"):
        out[name] = (OWN / name, lambda p: read_track(p, body="bip" if "euler" in str(p) else None), True)
    for name in ("motive_fv1.21_quaternion_m_120Hz.csv", "motive_fv1.23_quaternion_m_120Hz_lostframe.csv",
                 "ros1_vicon_transformstamped.bag"):
        p = SHARED_ROOT / "fixtures" / "tracker" / name
        if p.exists():
            out[f"real {name}"] = (p, read_track, p.suffix == ".csv")
    sink = _sink_files(d)
    out["track .csv"] = (sink[".csv"], read_truth, True)  # the truth CSV: read as it was registered
    out["track .mcap"] = (sink[".mcap"], read_track, True)
    for k, p in _captures(d).items():  # (a cut between two packets looks like a shorter capture)
        out[f"capture {k}"] = (p, read_track if k == "real-pcap" else lambda p: read_track(p, body="bip"), False)
    for k, p in _bags(d).items():
        out[f"bag {k}"] = (p, read_track, False)
    return out


def _samples(x) -> dict[str, np.ndarray]:
    if hasattr(x, "quat_xyzw"):  # a PoseTrack
        return {"t": x.t, "position": x.position, "quat_xyzw": x.quat_xyzw, "valid": x.valid}
    return {"t": x.t, "pose": x.mm_deg()}  # a Series6


def check_cut(path: Path, data: bytes, cut: int, reader, ref, detectable: bool, work: Path) -> str:
    """Read ``data[:cut]`` (written under ``work`` with ``path``'s name): the exact prefix of
    ``ref``'s samples, or a one-line UserError."""
    p = work / path.name
    p.write_bytes(data[:cut])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            got = reader(p)
        except UserError as exc:
            msg = str(exc)
            assert msg.strip() and "\n" not in msg and len(msg) < 600, f"cut at byte {cut}: {msg!r}"
            return "error"
        except Exception as exc:  # noqa: BLE001 -- the point: nothing but a UserError
            raise AssertionError(f"{path.name} cut at byte {cut}: {type(exc).__name__}: {exc}") from exc
    have, want = _samples(got), _samples(ref)
    m = len(have["t"])
    assert 0 < m <= len(want["t"]), f"cut at byte {cut}: {m} samples of {len(want['t'])}"
    for k in want:
        np.testing.assert_array_equal(have[k], want[k][:m], err_msg=f"{path.name} cut at byte {cut}: {k}")
    said = [str(w.message) for w in caught if issubclass(w.category, TruncatedRecordingWarning)]
    said += [w for w in getattr(got, "meta", {}).get("warnings", [])]
    if got.meta.get("complete") is False:
        said.append("incomplete")
    if detectable and m < len(want["t"]):
        assert said, f"{path.name} cut at byte {cut}: {m} of {len(want['t'])} samples read without a word"
    for w in said:
        assert "\n" not in w, w
    return "prefix"


NAMES = ["motive_mm_euler.csv", "motive_fv121_like.csv", "motive_fv125_motive31_mm.csv",
         "real motive_fv1.21_quaternion_m_120Hz.csv", "real motive_fv1.23_quaternion_m_120Hz_lostframe.csv",
         "real ros1_vicon_transformstamped.bag", "track .csv", "track .mcap", "capture pcap", "capture pcapng",
         "capture real-pcap", "bag ros1", "bag sqlite3", "bag mcap"]


@pytest.mark.parametrize("name", NAMES)
def test_cut_anywhere_gives_the_prefix_or_a_clear_error(name, files, tmp_path_factory):
    if name not in files:
        pytest.skip(f"{name}: real fixture not present (../shared/fixtures or SOFTPHANTOM_SHARED)")
    path, reader, detectable = files[name]
    data = path.read_bytes()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedRecordingWarning)
        ref = reader(path)
    work = tmp_path_factory.mktemp("cut")
    seen = []

    @settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow])
    @given(st.integers(min_value=0, max_value=len(data) - 1))
    def cut_at(cut):
        seen.append((cut, check_cut(path, data, cut, reader, ref, detectable, work)))

    cut_at()
    # and, fixed: an even grid over the file, and every offset of its last bytes (where a file
    # written as it goes is cut when its writer dies)
    n = len(data)
    for cut in sorted(set(range(0, n, max(n // GRID, 1))) | set(range(max(n - TAIL, 0), n))):
        seen.append((cut, check_cut(path, data, cut, reader, ref, detectable, work)))
    kinds = [k for _, k in seen]
    print(f"{name}: {n} bytes, {len(seen)} cuts: {kinds.count('prefix')} prefix, {kinds.count('error')} error")
    # the last row or record cut short (the usual way a file ends early) is read, not refused
    if not name.startswith(("bag", "real ros1", "capture real")):  # (bags need their index; one frame)
        assert check_cut(path, data, len(data) - 3, reader, ref, detectable, work) == "prefix", name
    assert len(seen) >= EXAMPLES + min(TAIL, len(data))
