"""End to end without hardware: the virtual tracker served as NatNet on loopback →
``softphantom track --natnet 127.0.0.1`` → ``softphantom evaluate``."""

import re
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from softphantom.cli import main  # noqa: E402
from softphantom.evaluation import read_truth, write_table  # noqa: E402
from softphantom.pose import Pose6, matrix_from_ypr, pose_of_markers  # noqa: E402
from softphantom.tracking import make_track, pose_columns, read_track, register_track  # noqa: E402
from softphantom.virtual.natnet_server import serve_natnet  # noqa: E402
from softphantom.virtual.tracker import TrackerConfig, simulate_tracker  # noqa: E402
from tracker_paths import written_json  # noqa: E402

REST = np.array([[0.02, 0.0, 0.01], [-0.015, 0.01, 0.015], [0.0, -0.02, 0.012], [0.005, 0.005, 0.025]])


def motion(t):
    """Relative pose of the marker body: a push (y up to 4 mm, yaw up to 3°) from 0.8 s to 1.6 s."""
    s = np.clip((np.asarray(t) - 0.8) / 0.4, 0, 1) - np.clip((np.asarray(t) - 1.2) / 0.4, 0, 1)
    s = 0.5 - 0.5 * np.cos(np.pi * s)
    return s[:, None] * np.array([0.0, 0.004, 0.0]), s[:, None] * np.array([np.radians(3.0), 0.0, 0.0])


@dataclass
class _Scenario:
    duration_s: float = 2.0


@dataclass
class _Samples:
    markers: np.ndarray


class FakeTruth:
    """What simulate_tracker needs of a Truth: a rigid motion of four markers, no FEM."""

    scenario = _Scenario()
    rest_markers = REST

    def sample(self, t):
        xyz, ypr = motion(t)
        R = matrix_from_ypr(ypr)
        return _Samples(np.einsum("nij,kj->nki", R, REST) + xyz[:, None, :])


@pytest.fixture(scope="module")
def stream():
    return simulate_tracker(FakeTruth(), TrackerConfig(seed=3, lost_fraction=0.02))


def _serve(stream, **kw):
    port = []
    ready = threading.Event()
    stop = threading.Event()

    def on_ready(p):
        port.append(p)
        ready.set()

    th = threading.Thread(target=serve_natnet, args=(stream, REST), daemon=True,
                          kwargs=dict(command_port=0, stop=stop.is_set, on_ready=on_ready, **kw))
    th.start()
    assert ready.wait(5)
    return port[0], stop, th


@pytest.mark.parametrize("suffix, version", [(".csv", (4, 1)), (".mcap", (3, 0))])
def test_virtual_serve_track_evaluate(tmp_path, capsys, stream, suffix, version):
    port, stop, th = _serve(stream, version=version, speed=4.0)
    out = tmp_path / f"truth{suffix}"
    try:
        code = main(["track", "--natnet", "127.0.0.1", "--command-port", str(port), "--data-port", "0",
                     "--out", str(out), "--frames", "260"])
    finally:
        stop.set()
        th.join(5)
    printed = capsys.readouterr()
    assert code == 0, printed.err
    text = " ".join(printed.out.split())
    assert "connected: Motive 3.1.0.0 at 127.0.0.1" in text and "'bip' (id 1)" in text
    m = re.search(r"(\d+) frames of 'bip'.*body lost in (\d+), frames lost (\d+)", text)
    n, lost_body, lost_frames = map(int, m.groups())
    assert n == 260 and lost_frames == 0
    # every frame of the take arrived in order, with the stream's own lost frames flagged
    extra = max(n - len(stream.t_take), 0)  # after the scenario the server repeats the last frame
    assert lost_body == int((~stream.valid[:n]).sum()) + extra * int(not stream.valid[-1])
    tru = read_truth(out)
    if suffix == ".mcap":
        tr = read_track(out)
        assert tr.meta["format"] == "softphantom-mcap" and tr.meta["frames_missing"] == 0
        assert tr.meta["latency_ms_median"] == pytest.approx(stream.latency_s * 1e3, abs=1e-3)
        m = min(len(tr), len(stream.t_take))
        np.testing.assert_allclose(tr.t[:m], stream.t_take[:m], atol=1e-9)
    # what the server was given is what was recorded (float32 on the wire), registered by the same
    # rest window as the stream itself would be
    ref = register_track(make_track(stream.t_take, stream.position, stream.quat_xyzw, clock="take",
                                    source="stream", name="bip"))
    cols = pose_columns(ref)
    k = tru.t <= stream.t_take[-1] + 1e-9  # after the scenario the server repeats the last pose
    j = cols["t_s"] <= tru.t[k][-1] + 1e-9  # a loaded machine may have recorded less than all of it
    np.testing.assert_allclose(tru.t[k], cols["t_s"][j], atol=1e-9)
    want = np.column_stack([cols[c] for c in Pose6.COLUMNS])[j]
    np.testing.assert_allclose(tru.mm_deg()[k], want, atol=2e-3)
    # and it is the motion, up to the tracker's noise (0.19 mm per marker, markers ~3 cm apart)
    xyz, ypr = motion(tru.t - stream.clock_offset_s)
    rms = np.sqrt(np.mean((tru.mm_deg() - Pose6(xyz, ypr).to_mm_deg()) ** 2, axis=0))
    assert rms[:3].max() < 0.3 and rms[3:].max() < 0.8, rms
    # evaluate against an estimate that is the motion on the take's clock: errors are the tracker's
    t_est = np.arange(0.0, tru.t[-1], 1 / 77)
    xe, ye = motion(t_est - stream.clock_offset_s)
    v = Pose6(xe, ye).to_mm_deg()
    est = tmp_path / "est.csv"
    write_table(est, {"softphantom": "test"}, {"t_s": t_est, **{c: v[:, k] for k, c in enumerate(Pose6.COLUMNS)}})
    assert main(["evaluate", "--estimate", str(est), "--truth", str(out), "--out", str(tmp_path / "rep"),
                 "--lag-ms", "0"]) == 0
    rep = capsys.readouterr().out
    rmse = [float(x) for x in re.findall(r"\((?:mm|deg)\)\s+│\s+([-\d.]+)", rep)]
    assert len(rmse) == 6 and max(rmse[:3]) < 0.3, rep


def test_track_refuses_when_no_server(tmp_path, capsys):
    code = main(["track", "--natnet", "127.0.0.1", "--command-port", "9", "--data-port", "0",
                 "--out", str(tmp_path / "x.csv"), "--connect-timeout-s", "0.5"])
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "no NatNet server answered at 127.0.0.1:9 within 0.5 s" in err


def test_track_body_choice(tmp_path, capsys, stream):
    port, stop, th = _serve(stream)
    try:
        code = main(["track", "--natnet", "127.0.0.1", "--command-port", str(port), "--data-port", "0",
                     "--body", "nobody", "--out", str(tmp_path / "x.mcap"), "--duration-s", "0.3"])
    finally:
        stop.set()
        th.join(5)
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "no rigid body 'nobody'; it streams: bip (id 1)" in err


def test_live_shows_and_records_the_tracker(tmp_path, stream):
    from softphantom.tracking.client import NatNetConfig
    from softphantom.sources import open_source
    from softphantom.viz.live import LiveConfig, LiveSession
    from softphantom.viz.live.tracker import NatNetTrackerFeed, TrackedSource

    port, stop, th = _serve(stream, speed=1.0)
    rec = tmp_path / "session.mcap"
    try:
        feed = NatNetTrackerFeed(NatNetConfig(command_port=port, data_port=0)).start()
        src = TrackedSource(open_source("synthetic", rate_Hz=77.0, duration_s=None, speed=1.0).source, feed)
        with LiveSession(src, LiveConfig(http_port=0, stream_port=None, record=rec, duration_s=1.5)) as s:
            s.wait(timeout_s=20)
            frame, _, _ = s.state.frame_since(-1, 0)
    finally:
        stop.set()
        th.join(5)
    shown = [m["tracker"] for m in frame["samples"] if "tracker" in m]
    assert shown and set(shown[-1]) == set(Pose6.COLUMNS)  # the page gets the tracker beside the estimate
    tr = read_track(rec)  # and the recording's /tracker is a truth file: the served poses
    assert tr.name == "bip" and len(tr) > 20 and tr.meta["frames_missing"] == 0
    m = min(len(tr), len(stream.t_take))
    np.testing.assert_allclose(tr.t[:m], stream.t_take[:m], atol=1e-9)
    v = tr.valid[:m]
    assert np.array_equal(v, stream.valid[:m])
    np.testing.assert_allclose(tr.position[:m][v], stream.position[:m][v], atol=1e-6)


def test_live_tracker_option_checked(capsys):
    assert main(["live", "--tracker", "vrpn:host", "--no-stream", "--http-port", "0", "--duration-s", "1"]) == 2
    assert "--tracker must be natnet:HOST or natnet:HOST:PORT, got 'vrpn:host'" in " ".join(capsys.readouterr().err.split())


def test_client_reconnects_when_the_server_restarts(stream):
    """Motive restarted: no frame for reconnect_s, the client connects again, frame numbers start over."""
    import socket
    import time

    from softphantom.tracking.client import NatNetClient, NatNetConfig

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()

    def start():
        stop = threading.Event()
        th = threading.Thread(target=serve_natnet, args=(stream, REST), daemon=True,
                              kwargs=dict(command_port=port, stop=stop.is_set))
        th.start()
        return stop, th

    stop1, th1 = start()
    servers = [(stop1, th1)]
    got = []
    t0 = time.monotonic()
    with NatNetClient(NatNetConfig(command_port=port, data_port=0, reconnect_s=0.5)) as c:
        for _, f in c.frames(stop=lambda: time.monotonic() - t0 > 60 or len(got) >= 60):
            got.append(f.frame_number)
            if len(got) == 30:  # the first server goes away; a new one starts on the same port
                stop1.set()
                th1.join(5)
                time.sleep(0.3)
                servers.append(start())
        stats = c.stats
    for stop, th in servers:
        stop.set()
        th.join(5)
    assert len(got) >= 60 and stats.reconnects >= 1
    drops = [k for k in range(1, len(got)) if got[k] < got[k - 1]]
    assert len(drops) == 1  # the new server's frames, from its start (after those already on the way)
    k = drops[0]
    assert got[:k] == list(range(1, k + 1)) and got[k:] == list(range(got[k], got[k] + len(got) - k))
    assert stats.lost == 0


def test_virtual_serve_natnet_helper(stream, capsys):
    """``virtual serve --natnet``'s server thread, on a run-like object (no FEM); its console says
    when a take starts."""
    from types import SimpleNamespace

    from softphantom.cli.virtual import _start_natnet
    from softphantom.tracking.client import NatNetClient, NatNetConfig

    run = SimpleNamespace(tracker=stream, truth=SimpleNamespace(rest_markers=REST, marker_names=("m1", "m2", "m3", "m4")))
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    stop = _start_natnet(run, "127.0.0.1", port, "3.0", 1.0)
    try:
        with NatNetClient(NatNetConfig(command_port=port, data_port=0)) as c:
            info = c.connect()
            assert info.natnet_version[:2] == (3, 0)
            assert c.choose_body(None) == (1, "bip")
            assert c.models.marker_sets == {"bip": ("m1", "m2", "m3", "m4")}
            np.testing.assert_allclose(c.models.rigid_bodies[0].markers, REST, atol=1e-7)
    finally:
        stop()
    out = " ".join(capsys.readouterr().out.split())
    assert re.search(r"NatNet client 127\.0\.0\.1:\d+ connected: the take starts", out), out


def _free_udp_port():
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_multicast_on_loopback(stream):
    """The server multicasts (TTL 0, loopback interface); the client joins the group on 127.0.0.1
    because the server info says multicast."""
    import socket

    from softphantom.tracking.client import NatNetClient, NatNetConfig

    data_port = _free_udp_port()
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                         socket.inet_aton("239.255.42.99") + socket.inet_aton("127.0.0.1"))
    except OSError as exc:
        pytest.skip(f"this machine cannot join a multicast group on loopback ({exc.strerror})")
    finally:
        probe.close()
    port, stop, th = _serve(stream, multicast=True, data_port=data_port)
    got = []
    try:
        with NatNetClient(NatNetConfig(command_port=port, data_port=data_port, local="127.0.0.1")) as c:
            info = c.connect()
            assert info.multicast and info.multicast_group == "239.255.42.99" and info.data_port == data_port
            for _, f in c.frames(stop=lambda: len(got) >= 50):
                got.append(f.frame_number)
            stats = c.stats
    finally:
        stop.set()
        th.join(5)
    assert got[:50] == list(range(got[0], got[0] + 50)) and stats.duplicates == 0 and stats.lost == 0


def _estimate_file(tmp_path, t_end, clock_offset_s):
    """An estimate that is the motion on the take's clock."""
    t_est = np.arange(0.0, t_end, 1 / 77)
    xe, ye = motion(t_est - clock_offset_s)
    v = Pose6(xe, ye).to_mm_deg()
    est = tmp_path / "est.csv"
    write_table(est, {"softphantom": "test"}, {"t_s": t_est, **{c: v[:, k] for k, c in enumerate(Pose6.COLUMNS)}})
    return est


def squash(text: str) -> str:
    return "".join(text.split())


@pytest.mark.parametrize("suffix", [".mcap", ".csv"])
def test_track_with_the_body_lost(tmp_path, capsys, suffix):
    """Frames with the body lost (Motive clears tracking-valid) are recorded as gaps, counted in the
    file and in the summary; the file is complete; a cut copy of it is reported by evaluate."""
    lossy = simulate_tracker(FakeTruth(), TrackerConfig(seed=5, lost_fraction=0.05))
    n = 200
    lost = int((~lossy.valid[:n]).sum())
    assert lost >= 3
    port, stop, th = _serve(lossy, speed=4.0)
    out = tmp_path / f"take{suffix}"
    try:
        code = main(["track", "--natnet", "127.0.0.1", "--command-port", str(port), "--data-port", "0",
                     "--out", str(out), "--frames", str(n)])
    finally:
        stop.set()
        th.join(5)
    printed = capsys.readouterr()
    assert code == 0, printed.err
    # rich folds a long path anywhere (a worker's tmp path is over 80 characters): compare without whitespace
    assert squash(f"{n} frames of 'bip' to {out} (complete): body lost in {lost},") in squash(printed.out)
    data = written_json(out)
    assert data and not any(b"NaN" in d or b"nan" in d for d in data)
    tru = read_truth(out)
    assert len(tru.t) == n - lost and tru.meta["lost_frames"] == lost and tru.meta["warnings"] == []
    assert tru.meta["frames"] == n and tru.meta["frames_body_lost"] == lost
    # a copy cut short: evaluate says so, with the counts
    data = out.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) * 3 // 4])
    est = _estimate_file(tmp_path, tru.t[-1], lossy.clock_offset_s)
    code = main(["evaluate", "--estimate", str(est), "--truth", str(cut), "--out", str(tmp_path / "rep"), "--lag-ms", "0"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    text = squash(printed.out)
    want = "incomplete recording" if suffix == ".mcap" else "a row cut short, dropped (truncated file)"
    assert squash(f"note: {cut}") in text and squash(want) in text, text
    assert want in (tmp_path / "rep" / "report.html").read_text()


def _connect_raw(port):
    """A bare NatNet client: NAT_CONNECT from a UDP socket (the server then streams to it)."""
    import socket

    from softphantom.tracking.natnet import NAT_CONNECT, encode_request

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.sendto(encode_request(NAT_CONNECT, "Ping"), ("127.0.0.1", port))
    return s


def test_each_run_after_the_last_client_left_sees_the_whole_take(tmp_path, capsys, stream):
    """A first attempt that failed (a wrong --body) has started the take; the next run sees it from
    frame 1, since the first client said NAT_DISCONNECT when it closed."""
    events = []
    port, stop, th = _serve(stream, speed=2.0, on_event=events.append)
    try:
        base = ["track", "--natnet", "127.0.0.1", "--command-port", str(port), "--data-port", "0"]
        assert main(base + ["--body", "nobody", "--out", str(tmp_path / "x.csv"), "--frames", "5"]) == 2
        import time

        time.sleep(0.5)  # the take would be 60 frames on by now
        out = tmp_path / "take.mcap"
        assert main(base + ["--out", str(out), "--frames", "30"]) == 0
    finally:
        stop.set()
        th.join(5)
    printed = " ".join(capsys.readouterr().out.split())
    assert "joined a take" not in printed
    tr = read_track(out)
    np.testing.assert_allclose(tr.t[:30], stream.t_take[:30], atol=1e-9)
    assert sum("the take starts" in e for e in events) == 2 and any("disconnected" in e for e in events), events


def test_a_client_joining_a_running_take_is_warned(tmp_path, capsys, stream):
    """Another client keeps the take running: a late ``track`` says it joined mid-take (on the
    console, in the file, and evaluate says it again)."""
    import time

    events = []
    port, stop, th = _serve(stream, speed=2.0, on_event=events.append)
    other = _connect_raw(port)
    try:
        time.sleep(0.6)
        out = tmp_path / "late.csv"
        code = main(["track", "--natnet", "127.0.0.1", "--command-port", str(port), "--data-port", "0",
                     "--out", str(out), "--frames", "100"])
    finally:
        other.close()
        stop.set()
        th.join(5)
    printed = " ".join(capsys.readouterr().out.split())
    assert code == 0
    m = re.search(r"warning: joined a take already being recorded \(first frame (\d+), t = ([\d.]+) s\)", printed)
    assert m and int(m.group(1)) > 100, printed  # 0.6 s at 2x speed, 120 Hz: about frame 144
    k = int(m.group(1)) - 1
    n = len(stream.t_take)  # a loaded machine may join after the scenario: its clock runs on
    t_expected = stream.t_take[min(k, n - 1)] + max(k - n + 1, 0) / stream.config.rate_Hz
    assert float(m.group(2)) == pytest.approx(t_expected, abs=1e-3)
    assert any("joined the running take" in e for e in events), events
    tru = read_truth(out)
    assert tru.meta["joined_mid_take"] is True and tru.meta["first_frame"] == k + 1
    assert any("joined a take already under way" in w for w in tru.meta["warnings"])
