"""softphantom live: drive the page's server from the synthetic source; check the endpoints, the
SSE frames every browser shares, the link and envelope status, replay of a recording, the CLI; and
driven by the virtual phantom through the real estimator. The page itself in Chromium:
tests/test_live_page.py."""

from __future__ import annotations

import json
import re
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from softphantom.records import BIP_LAYOUT, ChannelLayout
from softphantom.cli import main
from softphantom.errors import UserError
from softphantom.fem import DEFAULT_CONTACT_RADIUS_M
from softphantom.stream import EstimateSubscriber, read_estimate_csv, read_recording
from softphantom.viz.live import (
    EstimateSource,
    LiveConfig,
    LiveGeometry,
    LiveSession,
    EstimateReplay,
    SyntheticSource,
    ellipsoid_geometry,
)
from softphantom.sources import open_source
from softphantom.viz.live.source import decode_positions_mm
from softphantom.estimation import Estimator, EstimatorConfig
from softphantom.viz.live import EstimatorSource
from softphantom.virtual import VirtualConfig, scenario_from_dict, simulate

VENDOR = Path(__file__).parents[1] / "softphantom" / "viz" / "live" / "static" / "vendor"


def _get(url: str, timeout: float = 30.0) -> bytes:
    with urllib.request.urlopen(url, timeout=timeout) as r:
        assert r.status == 200
        return r.read()


def _wait_state(url: str, ok, timeout_s: float = 60.0) -> dict:
    """Poll ``api/state`` until ``ok(state)`` or ``timeout_s``; the last state either way."""
    deadline = time.monotonic() + timeout_s
    while True:
        state = json.loads(_get(url + "api/state", timeout=30.0))
        if ok(state) or time.monotonic() > deadline:
            return state
        time.sleep(0.1)


def _ticks(status: dict, latest: dict, rate_Hz: float) -> tuple[int, int]:
    """(estimates + skipped, ticks up to the latest t_s): equal when every tick is shown or counted."""
    return status["estimates"] + status["skipped_total"], round(latest["t_s"] * rate_Hz) + 1


def _sse_frames(url: str, n: int, timeout: float = 30.0) -> list[dict]:
    frames = []
    with urllib.request.urlopen(url + "api/events", timeout=timeout) as r:
        assert r.headers["Content-Type"] == "text/event-stream"
        for line in r:
            if line.startswith(b"data: "):
                frames.append(json.loads(line[6:]))
                if len(frames) >= n:
                    break
    return frames


def test_synthetic_source_is_an_estimate_source_and_geometry_from_a_model():
    src = SyntheticSource(rate_Hz=100, duration_s=0.3, realtime=False, subdivisions=2)
    assert isinstance(src, EstimateSource)
    ests = list(src)
    assert len(ests) == 30 and all(e.status == "ok" for e in ests)
    pos = src.node_positions()
    u = np.linalg.norm(pos - src.geometry.nodes, axis=1)
    assert u.max() > 1e-4  # it deforms
    # LiveGeometry.from_model takes the outer surface of a PhantomModel-like object, reindexed
    g = ellipsoid_geometry(subdivisions=1)
    extra = np.zeros((5, 3))  # interior nodes that are not on the surface
    model = SimpleNamespace(nodes=np.vstack([extra, g.nodes]), outer_faces=g.faces + 5,
                            targets={"apex": np.array([0.0, -0.01, 0.0])},
                            p_ext={"on-centre": g.p_ext, "off-centre": g.p_ext + 0.005})
    lg = LiveGeometry.from_model(model)
    np.testing.assert_array_equal(lg.node_index, np.arange(5, 5 + len(np.unique(g.faces))))
    np.testing.assert_allclose(lg.nodes[lg.faces], g.nodes[g.faces])
    with pytest.raises(UserError, match="no interaction point 'top'"):
        LiveGeometry.from_model(model, p_ext="top")
    j = lg.to_json()
    assert LiveGeometry.from_json(j).faces.shape == lg.faces.shape
    assert j["nodes_mm"][j["p_ext_node"]] == pytest.approx((g.p_ext * 1e3).tolist())


def test_live_page_endpoints_frames_and_stream(tmp_path):
    src = SyntheticSource(rate_Hz=200, duration_s=None)
    rec = tmp_path / "live.mcap"
    cfg = LiveConfig(http_port=0, stream_port=0, record=rec, view_rate_Hz=30)
    with LiveSession(src, cfg) as s:
        assert s.url.startswith("http://127.0.0.1:")
        assert s.stream_endpoint.startswith("tcp://127.0.0.1:")
        sub = EstimateSubscriber(s.stream_endpoint)
        try:
            html = _get(s.url).decode()
            for el in ('id="view3d"', 'id="status"', 'id="plot-force"', 'id="plot-position"',
                       'id="plot-rotation"', 'id="plot-cavities"', 'id="targets"', "/static/live.js",
                       'id="colorbar"', 'id="badge-link"', 'id="badge-envelope"'):
                assert el in html
            js = _get(s.url + "static/live.js").decode()
            assert "EventSource" in js and "http" not in js  # nothing fetched from outside
            # the libraries come from the package, and the browser may load nothing from elsewhere
            with urllib.request.urlopen(s.url + "static/vendor/live-libs.min.js", timeout=30) as r:
                assert r.status == 200 and "javascript" in r.headers["Content-Type"]
                assert r.read() == (VENDOR / "live-libs.min.js").read_bytes()
            with urllib.request.urlopen(s.url, timeout=30) as r:
                csp = r.headers["Content-Security-Policy"]
            assert "default-src 'self'" in csp and "script-src 'self';" in csp and "http" not in csp
            geo = json.loads(_get(s.url + "api/geometry"))
            assert len(geo["nodes_mm"]) == len(src.geometry.nodes) and set(geo["targets_mm"]) == {"apex", "base", "lesion"}
            frames = _sse_frames(s.url, 6)
            assert any(f["samples"] for f in frames) and any("surface_mm_f32_b64" in f for f in frames)
            seqs = [m["seq"] for f in frames for m in f["samples"]]
            # the page names its fields in its own code: each unit-named one must be a key the server
            # sends (an estimate message, the status, the geometry), so a renamed column fails here
            sent = {k for f in frames for m in f["samples"] for k in m} | set(geo)
            sent |= {k for f in frames if "status" in f for k in f["status"]}
            read = set(re.findall(r"\b([a-z][a-z0-9_]*_(?:mm|deg|N|kPa|Hz|ms|s))\b", js))
            assert read and read <= sent, sorted(read - sent)
            assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
            surf = decode_positions_mm(next(f["surface_mm_f32_b64"] for f in frames if "surface_mm_f32_b64" in f))
            assert surf.shape == src.geometry.nodes.shape
            # > 200 estimates shown, however loaded the machine (the rate figure: test_status_rate_*)
            state = _wait_state(s.url, lambda x: x["status"]["estimates"] > 200 and x["status"]["sensor_health"] == "ok")
            st = state["status"]
            assert st["sensor_health"] == "ok" and st["step_ms"] is not None and st["estimates"] > 200, st
            # every 200 Hz tick of the source was shown or counted as skipped
            assert _ticks(st, state["latest"], 200.0)[0] == _ticks(st, state["latest"], 200.0)[1], st
            assert st["stream"]["enabled"] and st["recording"]["enabled"]
            for k in ("force_y_N", "y_mm", "pitch_deg", "dVmeas_back_xpos_mm3", "apex_dy_mm", "seq", "t_s"):
                assert k in state["latest"]
            assert _get_status(s.url + "nope") == 404
            m = sub.recv(timeout_s=30.0)
            assert m is not None and "force_y_N" in m
        finally:
            sub.close()
    r = read_recording(rec)
    assert r.complete and len(r.estimates) > 200 and r.geometry is not None and len(r.surface) >= 5
    assert [m["seq"] for m in r.estimates] == list(range(len(r.estimates)))


def test_the_end_of_a_source_reaches_the_page_as_ended():
    """A replay that runs out and the session stopped at once (what ``softphantom live`` does): each
    event stream ends with a frame whose status is finished (link ``ended``), then the ``end`` event
    (the page stops reconnecting, docs/live.md)."""
    import threading

    src = SyntheticSource(rate_Hz=200, duration_s=1.0, subdivisions=1)
    events: list[tuple[str, bytes]] = []
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, view_rate_Hz=30)) as s:
        _wait_state(s.url, lambda x: x["status"]["estimates"] > 20)

        def read() -> None:
            kind = b"message"
            with urllib.request.urlopen(s.url + "api/events", timeout=30) as r:
                for line in r:  # until the server ends the response
                    if line.startswith(b"event: "):
                        kind = line[7:].strip()
                    elif line.startswith(b"data: "):
                        events.append((kind.decode(), line[6:].strip()))

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        deadline = time.monotonic() + 30
        while not events and time.monotonic() < deadline:
            time.sleep(0.02)
        assert s.wait(30)  # the source ends ...
    reader.join(30)  # ... and the session is stopped right after it (the with block)
    assert not reader.is_alive() and events and events[-1][0] == "end", events[-3:]
    kind, last = events[-2]
    assert kind == "frame" and json.loads(last)["status"]["finished"] is True
    assert json.loads(last)["status"]["link"] == "ended"


def test_the_page_server_does_not_import_the_session():
    """One direction: server (the session) → web (the page's server) → state; web and state never
    import the session's module (not even for type checking)."""
    import ast

    live = Path(__file__).parents[1] / "softphantom" / "viz" / "live"

    def imports(name: str) -> set[str]:
        out = set()
        for node in ast.walk(ast.parse((live / name).read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                out.add(node.module)
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
        return out

    assert "softphantom.viz.live.server" not in imports("web.py")
    assert not {"softphantom.viz.live.server", "softphantom.viz.live.web"} & imports("state.py")
    assert "softphantom.viz.live.web" in imports("server.py")


def test_every_browser_gets_the_same_frames_from_its_own_start():
    src = SyntheticSource(rate_Hz=200, duration_s=None, subdivisions=1)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, view_rate_Hz=30)) as s:
        _wait_state(s.url, lambda x: x["status"]["estimates"] > 50)
        out = {}

        def read(name: str, n: int) -> None:
            out[name] = _sse_frames(s.url, n)

        import threading

        a = threading.Thread(target=read, args=("a", 40))
        a.start()
        time.sleep(0.3)
        read("b", 12)
        a.join(30)
    fa, fb = out["a"], out["b"]
    # each starts with the history (every estimate so far, none missing), then the shared frames
    for frames in (fa, fb):
        seqs = [m["seq"] for f in frames for m in f["samples"]]
        first = [m["seq"] for m in frames[0]["samples"]]
        assert first == list(range(first[0], first[-1] + 1)) and len(first) > 50
        assert sorted(set(seqs)) == list(range(seqs[0], seqs[-1] + 1))  # no gap (overlap is filtered by seq)
        assert "surface_mm_f32_b64" in frames[0]
    # b's frames after its history are frames a received too: one frame, encoded once, for every browser
    later_b = [json.dumps(f["samples"]) for f in fb[1:]]
    all_a = {json.dumps(f["samples"]) for f in fa}
    assert later_b and sum(f in all_a for f in later_b) >= len(later_b) - 1


def test_a_stalled_browser_loses_frames_then_its_slot_not_the_others():
    import socket

    def open_stream(port: int, rcvbuf: int | None = None) -> socket.socket:
        c = socket.socket()
        if rcvbuf:
            c.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        c.connect(("127.0.0.1", port))
        c.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
        assert c.recv(12) == b"HTTP/1.1 200"
        return c

    src = SyntheticSource(rate_Hz=200, duration_s=None, subdivisions=5)  # 10 k nodes: 160 kB a surface
    # a queue of 64 frames is 2.1 s at 30 Hz: it overflows before the 4 s timeout drops the browser
    cfg = LiveConfig(http_port=0, stream_port=None, view_rate_Hz=30, max_clients=2, client_timeout_s=4.0)
    with LiveSession(src, cfg) as s:
        port = int(s.url.split(":")[2].split("/")[0])
        stalled = open_stream(port, rcvbuf=4096)  # then it reads nothing more
        frames = _sse_frames(s.url, 3)  # another browser is served meanwhile
        deadline = time.monotonic() + 60
        while s.state.status()["view_dropped"] == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert s.state.status()["view_dropped"] > 0  # its queue overflowed: the estimates it lost, counted
        held = open_stream(port)  # both slots taken: one more is refused until the stalled one is dropped
        codes = []
        while time.monotonic() < deadline:
            try:
                codes.append(urllib.request.urlopen(s.url + "api/state", timeout=10).status)
                break
            except urllib.error.HTTPError as e:
                codes.append(e.code)
                time.sleep(0.2)
        held.close()
        stalled.close()
    assert all(f["samples"] for f in frames[1:])
    assert codes[-1] == 200 and codes[0] == 503 and set(codes[:-1]) == {503}


def test_link_and_envelope_status_from_the_estimates():
    from softphantom.viz.live.server import LiveState

    state = LiveState()
    state.push({"seq": 0, "status": "ok", "in_envelope": 1, "step_ms": 0.4})
    st = state.status()
    assert (st["link"], st["in_envelope"], st["last_event"]) == ("ok", True, None)
    state.push({"seq": 1, "status": "ok", "in_envelope": 0, "step_ms": 0.5})
    assert state.status()["in_envelope"] is False
    for seq, marker in enumerate(["event:silent: no valid frame for 0.5 s", "event:disconnected: port failed",
                                  "event:reconnected: /dev/ttyACM0"], start=2):
        state.push({"seq": seq, "status": marker, "step_ms": 0.0})  # markers: numbers null, no step
        st = state.status()
        assert st["link"] == "outage" and st["link_detail"] == marker[len("event:"):]
    assert st["in_envelope"] is False and st["step_p99_ms"] == pytest.approx(0.499)  # the markers' 0 ms ignored
    state.push({"seq": 5, "status": "event:resumed: after 3.2 s", "step_ms": 0.0})
    assert state.status()["link"] == "ok" and state.status()["last_event"] == "resumed: after 3.2 s"
    state.push({"seq": 6, "status": "event:silent: no valid frame for 0.5 s", "step_ms": 0.0})
    state.push({"seq": 7, "status": "ok", "in_envelope": 1, "step_ms": 0.4})  # a sample: the link is up
    assert state.status()["link"] == "ok" and state.status()["in_envelope"] is True
    state.finish("board unplugged")
    assert state.status()["link"] == "error" and state.status()["link_detail"] == "board unplugged"


def test_vendored_libraries_are_the_locked_versions():
    import hashlib

    lock = json.loads((VENDOR / "package-lock.json").read_text())["packages"]
    want = {name: lock[f"node_modules/{name}"]["version"] for name in ("three", "uplot")}
    assert json.loads((VENDOR / "package.json").read_text())["dependencies"] == want  # pinned exactly
    bundle = (VENDOR / "live-libs.min.js").read_bytes()
    assert bundle.startswith(f"/* three@{want['three']}, uplot@{want['uplot']} (MIT".encode())
    assert f'"{want["three"].split(".")[1]}"'.encode() in bundle  # three.REVISION of that version
    for line in (VENDOR / "SHA256SUMS").read_text().splitlines():
        digest, name = line.split()
        assert hashlib.sha256((VENDOR / name).read_bytes()).hexdigest() == digest, name
    for name in ("LICENSE-three.txt", "LICENSE-uplot.txt"):
        assert "MIT License" in (VENDOR / name).read_text() or "Permission is hereby granted" in (VENDOR / name).read_text()


def test_status_rate_and_health_on_a_controlled_clock(monkeypatch):
    """The page's rate figure and stall detection, on a fake clock (no wall-clock speed involved)."""
    import softphantom.viz.live.state as srv

    clock = [1000.0]
    monkeypatch.setattr(srv, "time", SimpleNamespace(monotonic=lambda: clock[0], time=time.time,
                                                     perf_counter=time.perf_counter))
    state = srv.LiveState(history=50)
    for k in range(201):  # 200 Hz for 1 s
        state.push({"seq": k, "skipped": 1 if k % 50 == 0 else 0, "step_ms": 0.5, "status": "ok"})
        clock[0] += 0.005
    st = state.status()
    assert st["rate_Hz"] == pytest.approx(200.0) and st["estimates"] == 201 and st["skipped_total"] == 5
    assert st["sensor_health"] == "ok" and st["step_p99_ms"] == pytest.approx(0.5)
    clock[0] += 1.5  # no estimate for 1.5 s: stalled, and the 2 s window holds only the last 0.5 s
    st = state.status()
    assert st["sensor_health"].startswith("stalled (1.5 s") and st["rate_Hz"] == pytest.approx(200.0)
    clock[0] += 3.0
    assert state.status()["rate_Hz"] == 0.0
    state.finish()
    assert state.status()["sensor_health"] == "ok"  # a finished source is not stalled


def _get_status(url: str) -> int:
    try:
        urllib.request.urlopen(url, timeout=5)
    except urllib.error.HTTPError as e:
        return e.code
    return 200


def test_replay_of_a_recording_shows_the_recorded_deformation(tmp_path):
    rec = tmp_path / "s.mcap"
    src = SyntheticSource(rate_Hz=200, duration_s=1.0, subdivisions=2)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, record=rec, record_surface_Hz=20)) as s:
        assert s.wait(timeout_s=120.0)
    r = read_recording(rec)
    n = len(r.estimates)  # 200 less what a loaded machine made the real-time source skip (counted)
    assert n + sum(m["skipped"] for m in r.estimates) == 200 and r.estimates[-1]["seq"] == n - 1
    # the surface is recorded at ≤ 20 Hz: a few snapshots, each at an estimate, in order
    surf_seqs = [m["seq"] for m in r.surface]
    assert 2 <= len(surf_seqs) <= n and surf_seqs == sorted(set(surf_seqs)) and surf_seqs[-1] <= n - 1
    rp = open_source(f"replay:{rec}", speed=0).source
    assert isinstance(rp, EstimateReplay) and rp.geometry.nodes.shape == src.geometry.nodes.shape
    with LiveSession(rp, LiveConfig(http_port=0, stream_port=None)) as s2:
        assert s2.wait(timeout_s=120.0)
        st = json.loads(_get(s2.url + "api/state"))
    assert st["status"]["estimates"] == n and st["status"]["finished"]
    assert st["latest"]["seq"] == n - 1
    assert st["latest"]["force_y_N"] == pytest.approx(r.estimates[-1]["force_y_N"])
    final = decode_positions_mm(st["surface_mm_f32_b64"])
    np.testing.assert_allclose(final, decode_positions_mm(r.surface[-1]["positions_mm_f32_b64"]), atol=1e-6)
    # and an estimate CSV replays too (plots only: no geometry in a CSV)
    assert main(["recording-csv", str(rec), "--out", str(tmp_path / "e.csv")]) == 0
    rc = open_source(f"replay:{tmp_path / 'e.csv'}", speed=0).source
    assert rc.geometry is None and len(list(rc)) == n


def _estimate_file(path, targets, peak, xyz_mm, ypr_deg, meta) -> None:
    """An estimate file: a push rising to ``peak`` N (pose rising to ``xyz_mm``/``ypr_deg``) at 100 Hz
    for 0.5 s, then a link event's marker (numbers NaN)."""
    from softphantom.estimation import Estimate
    from softphantom.estimation.stream import marker_estimate, write_estimates
    from softphantom.pose import Pose6
    from softphantom.sensing.sources import SourceEvent

    ests = []
    for k in range(51):
        a = k / 50
        ests.append(Estimate(t=k / 100, force=a * np.asarray(peak, float), p_urethra=500.0 * a,
                             pose=Pose6(a * np.asarray(xyz_mm) * 1e-3, a * np.radians(ypr_deg)),
                             target_shift={n: np.zeros(3) for n in targets}, volume_pred=np.zeros(4),
                             volume_meas=np.zeros(4), cond_W=20.0, qp_status="optimal", step_time=1e-4,
                             layout=BIP_LAYOUT))
    ests.append(marker_estimate(SourceEvent(0.51, "silent", "no valid frame for 0.5 s"), targets, BIP_LAYOUT))
    write_estimates(path, ests, targets, meta, BIP_LAYOUT)


@pytest.fixture(scope="module")
def coarse_atlas(shared_dir):
    """The coarse model's small on-centre atlas (shared_models.cached_atlas: f_y up to 1.2 N, p_u up to 4 kPa)."""
    from shared_models import cached_atlas

    return cached_atlas(shared_dir)


def test_replay_of_an_estimate_file_moves_the_phantom(coarse_model, coarse_model_dir, coarse_atlas, tmp_path):
    """``live --source replay:estimate.csv --model DIR``: the surface is the model's atlas field at
    each estimate's loads (the atlas cached in DIR/atlas for the file's contact); without an atlas
    the rest shape moved rigidly by the estimated pose; the page is told which."""
    import shutil

    from softphantom.estimation.atlas.store import atlas_path, save_atlas
    from softphantom.pose import matrix_from_ypr

    at = coarse_atlas
    mdir = tmp_path / "model"
    shutil.copytree(coarse_model_dir, mdir)
    save_atlas(at, atlas_path(mdir, at.key))
    peak, xyz_mm, ypr_deg = (0.2, 1.0, -0.1), (0.3, 2.0, -0.5), (3.0, -2.0, 1.0)
    meta = {"contact": "on-centre", "contact_radius_mm": at.provenance["contact_radius_m"] * 1e3}
    csv = tmp_path / "estimate.csv"
    _estimate_file(csv, list(coarse_model.targets), peak, xyz_mm, ypr_deg, meta)

    rp = open_source(f"replay:{csv}", model=mdir, speed=0).source
    assert isinstance(rp, EstimateReplay) and rp.atlas is not None and "atlas" in rp.surface_shows
    with LiveSession(rp, LiveConfig(http_port=0, stream_port=None)) as s:
        assert s.wait(timeout_s=60.0)
        st = json.loads(_get(s.url + "api/state"))
        geo = json.loads(_get(s.url + "api/geometry"))
    assert "atlas" in geo["surface_shows"]
    shown = decode_positions_mm(st["surface_mm_f32_b64"])  # the last estimate's (the marker keeps it)
    want = at.nodes(np.array([*peak, 500.0]))[rp.geometry.node_index]
    np.testing.assert_allclose(shown, want, atol=2e-7)
    assert st["status"]["surface_max_mm"] > 0.3, st["status"]["surface_max_mm"]

    # a model without an atlas (or for another contact): rigid motion by the estimated pose
    for model, m in ((coarse_model, None), (mdir, {**meta, "contact": "off-centre"})):
        if m is not None:
            _estimate_file(csv, list(coarse_model.targets), peak, xyz_mm, ypr_deg, m)
        rp = open_source(f"replay:{csv}", model=model, speed=0).source
        assert rp.atlas is None and "rigidly" in rp.surface_shows
        with LiveSession(rp, LiveConfig(http_port=0, stream_port=None)) as s:
            assert s.wait(timeout_s=60.0)
            st = json.loads(_get(s.url + "api/state"))
        R = matrix_from_ypr(np.radians(ypr_deg))
        want = rp.geometry.nodes @ R.T + np.asarray(xyz_mm) * 1e-3
        np.testing.assert_allclose(decode_positions_mm(st["surface_mm_f32_b64"]), want, atol=2e-7)
        assert st["status"]["surface_max_mm"] > 2.0
    assert np.linalg.norm(rp.geometry.p_ext - coarse_model.p_ext["off-centre"]) < 1e-9  # the file's contact


def test_cli_live_runs_records_and_rejects_bad_options(tmp_path, capsys):
    rec = tmp_path / "cli.mcap"
    assert main(["live", "--source", "synthetic", "--duration-s", "1.0", "--http-port", "0", "--stream-port", "0",
                 "--rate-Hz", "100", "--record", str(rec)]) == 0
    out = capsys.readouterr().out
    assert "live page: http://127.0.0.1:" in out and "estimate stream: tcp://127.0.0.1:" in out
    est = read_recording(rec).estimates  # 1 s of a 100 Hz source: each tick recorded or counted as skipped
    assert est and [m["seq"] for m in est] == list(range(len(est)))
    assert len(est) + sum(m["skipped"] for m in est) == round(est[-1]["t_s"] * 100) + 1
    for argv, msg in [
        (["live", "--source", "bogus"], "unknown --source"),
        (["live", "--source", "virtual:needle-insertion"], "needs --model"),
        (["live", "--source", "replay:/no/such.mcap"], "replay file not found"),
        (["live", "--record", str(tmp_path / "x.txt")], "--record must name an .mcap"),
        (["live", "--view-rate-Hz", "0"], "--view-rate-Hz"),
        (["live", "--rate-Hz", "-1", "--http-port", "0"], "--rate-Hz"),
    ]:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err


def test_geometry_of_the_real_phantom_model(coarse_model):
    g = LiveGeometry.from_model(coarse_model)
    assert len(g.faces) == len(coarse_model.outer_faces) and len(g.nodes) < len(coarse_model.nodes)
    np.testing.assert_allclose(g.nodes[g.faces], np.asarray(coarse_model.nodes)[coarse_model.outer_faces])
    assert set(g.targets) == set(coarse_model.targets)
    j = g.to_json()
    assert np.linalg.norm(np.array(j["nodes_mm"][j["p_ext_node"]]) - g.p_ext * 1e3) < 5.0  # a surface node near p_ext


# --- driven by the virtual phantom through the real estimator ---------------------------------

PUSH = {"name": "live-push", "duration_s": 3.6, "rest_s": 0.8,
        "push": [{"point": "on-centre", "start_s": 0.9, "rise_s": 0.8, "hold_s": 0.6, "fall_s": 0.6,
                  "force_N": [0.2, 2.0, -0.2]}]}


@pytest.fixture(scope="module")
def virtual_run(coarse_model, coarse_truth_p1):
    # the shared truth mesh is the one simulate would mesh for this config (P1, 0.75 × 12 mm)
    return simulate(scenario_from_dict(PUSH, "live"), coarse_model, VirtualConfig.seeded(seed=5, osr=25, order=1),
                    truth_mesh=coarse_truth_p1)


def test_live_from_the_virtual_phantom(coarse_model, virtual_run, tmp_path):
    # async, as `softphantom live` runs a paced source: the background equilibrium keeps steps short
    est = Estimator(coarse_model, EstimatorConfig.box(10.0, contact="on-centre", mode="async"))
    # paced at twice the scenario's clock (the release still settles: |F_y| ≤ 0.1 N at the end, in tries)
    src = EstimatorSource(coarse_model, virtual_run.source(tare=True), est, live=False, speed=2.0)
    n_nodes = len(coarse_model.nodes)
    rec = tmp_path / "virtual.mcap"
    with LiveSession(src, LiveConfig(http_port=0, stream_port=0, record=rec, view_rate_Hz=20)) as s:
        sub = EstimateSubscriber(s.stream_endpoint)
        try:
            geo = json.loads(_get(s.url + "api/geometry"))
            assert len(geo["nodes_mm"]) == len(src.geometry.nodes) and set(geo["targets_mm"]) == set(coarse_model.targets)
            assert geo["contact_radius_mm"] == pytest.approx(DEFAULT_CONTACT_RADIUS_M * 1e3)  # the estimator's patch
            frames = _sse_frames(s.url, 4, timeout=20.0)
            assert any(f["samples"] for f in frames)
            got = []
            deadline = time.monotonic() + 300  # the whole 3.6 s scenario, however loaded the machine
            while not s.wait(timeout_s=0.05) and time.monotonic() < deadline:
                while (m := sub.recv(timeout_s=0)) is not None:
                    got.append(m)
            assert s.wait(timeout_s=0), "the scenario did not finish in 300 s"
            while (m := sub.recv(timeout_s=1.0)) is not None:  # the last ones, on their way (loopback)
                got.append(m)
            st = s.state.status()
        finally:
            sub.close()
    seqs = [m["seq"] for m in got]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # in order, no duplicates
    # live=False: every board sample of the 3.6 s scenario is estimated and shown, none skipped
    n_samples = sum(1 for _ in virtual_run.source(tare=True))
    assert st["estimates"] == n_samples >= 3.6 * 76 and st["skipped_total"] == 0
    # the estimate saw the push: +y motion of the bulb with a +y force, then back
    fy = np.array([m["force_y_N"] for m in got])
    y = np.array([m["y_mm"] for m in got])
    assert fy.max() > 1.0 and y.max() > 1.0
    # and it comes down after the release (how far depends on how many async refreshes a loaded
    # machine completes in the last second: the estimator's tracking accuracy is tested in
    # test_estimation.py, not here)
    assert fy[-1] < fy.max() - 0.5
    r = read_recording(rec)
    assert r.complete and len(r.estimates) == st["estimates"] and len(r.sensors) == len(r.estimates)
    assert r.geometry is not None and len(r.surface) >= 3
    # the contact model is recorded: in the geometry and in the CSV exported from the recording
    assert r.geometry["contact_radius_mm"] == pytest.approx(DEFAULT_CONTACT_RADIUS_M * 1e3)
    assert main(["recording-csv", str(rec), "--out", str(tmp_path / "e.csv")]) == 0
    assert read_estimate_csv(tmp_path / "e.csv")[0]["contact_radius_mm"] == pytest.approx(4.0)
    assert est.node_positions().shape == (n_nodes, 3)


# --- a phantom of five arms (names from its design) ---------------------------------------------

FIVE = {"arm_names": ["front_zpos", "front_zneg", "back_xpos", "back_xneg", "top"],
        "arms": {"top": {"direction": [0.0, 0.6, 1.0], "cavity_volume_mm3": 486.0}}}


@pytest.fixture(scope="module")
def five_model_dir(five_arms_model_dir, five_arms_model):
    """The five-arm design of tests/test_arms_generic.py, meshed at 12 mm (linear) once per run and
    saved (conftest; read only)."""
    import dataclasses

    from softphantom.design.params import design_from_dict

    want = design_from_dict(FIVE)
    assert five_arms_model.design == dataclasses.replace(want, mesh=want.mesh.scaled_to(12.0))
    return five_arms_model_dir


def _five_arm_estimate_file(path, targets) -> None:
    """51 estimates at 100 Hz; at estimate i arm k (0-based, sensor order) measured (k + 1) · i mm³
    and predicted half that, so each value names its arm and its estimate."""
    from dataclasses import replace

    from softphantom.estimation.stream import write_estimates

    k = np.arange(1, 6)
    five = ChannelLayout(tuple(FIVE["arm_names"]), (), ("urethra",))
    ests = [replace(e, t=i / 100, layout=five, volume_meas=k * i * 1e-9,
                    volume_pred=k * i * 0.5e-9, target_shift={n: np.zeros(3) for n in targets})
            for i, e in enumerate(SyntheticSource(rate_Hz=100, duration_s=0.51, realtime=False, subdivisions=1))]
    write_estimates(path, ests, targets, {"contact": "on-centre"}, five)


def test_five_arms_replayed_to_the_page_the_stream_and_the_recording(five_model_dir, coarse_model_dir, tmp_path, capsys):
    """An estimate file of five arms replayed with its model: the page is told the five arms (state
    and geometry, the top arm's cavity drawn), its frames, the stream and the recording carry five
    named volume series with their values, and the recording replays with its arms."""
    arms = FIVE["arm_names"]
    csv = tmp_path / "five.csv"
    _five_arm_estimate_file(csv, ["apex"])
    rp = open_source(f"replay:{csv}", model=five_model_dir, speed=1.0).source
    assert rp.arm_names == tuple(arms) and rp.geometry.arm_names == tuple(arms) and "top" in rp.geometry.cavities
    rec = tmp_path / "five.mcap"
    with LiveSession(rp, LiveConfig(http_port=0, stream_port=0, record=rec, view_rate_Hz=20)) as s:
        sub = EstimateSubscriber(s.stream_endpoint)
        try:
            st = json.loads(_get(s.url + "api/state"))
            geo = json.loads(_get(s.url + "api/geometry"))
            assert st["arms"] == arms and geo["arms"] == arms and "top" in geo["cavities"]
            frames = _sse_frames(s.url, 3)
            got = []
            while not s.wait(timeout_s=0.05):
                while (m := sub.recv(timeout_s=0)) is not None:
                    got.append(m)
            while (m := sub.recv(timeout_s=0.5)) is not None:
                got.append(m)
        finally:
            sub.close()
    samples = [m for f in frames for m in f["samples"]]
    assert samples and got
    for m in samples + got:  # five named series, each with its arm's values
        assert [k for k in m if k.startswith("dVmeas_")] == [f"dVmeas_{a}_mm3" for a in arms]
        for k, a in enumerate(arms):
            assert m[f"dVmeas_{a}_mm3"] == pytest.approx((k + 1) * m["seq"])
            assert m[f"dVpred_{a}_mm3"] == pytest.approx(0.5 * (k + 1) * m["seq"])
    r = read_recording(rec)
    assert r.arm_names == tuple(arms) and r.geometry["arms"] == arms and len(r.estimates) == 51
    assert r.estimates[-1]["dVmeas_top_mm3"] == pytest.approx(250.0)
    again = open_source(f"replay:{rec}", speed=0).source
    assert again.arm_names == tuple(arms) and again.geometry.arm_names == tuple(arms)
    # with a model of other arms: one line naming both lists
    assert main(["live", "--source", f"replay:{csv}", "--model", str(coarse_model_dir), "--http-port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "(front_zpos, front_zneg, back_xpos, back_xneg, top)" in err, err
    assert "are not the model's (front_zpos, front_zneg, back_xpos, back_xneg)" in err, err


def test_live_estimates_a_five_arm_board_recording(five_model_dir, tmp_path):
    """``live`` over a sensing recording of a five-arm board (six channels) with its model: every
    sample estimated through all five arms, the sensor samples recorded with the board's names."""
    from softphantom.design import load_model
    from softphantom.sensing.bench import BenchConfig
    from softphantom.sensing.chain import nominal_tare, simulate_raw, to_measurement
    from softphantom.sensing.pneumatics import boyle_dp
    from softphantom.sensing.recording import Recorder

    arms = tuple(FIVE["arm_names"])
    bench = BenchConfig.from_model(load_model(five_model_dir))
    chain, rng = bench.chain(), np.random.default_rng(3)
    tare = nominal_tare(chain, bench.p0_Pa)
    # volumes of a push of about (0.2, 1, -0.1) N on this model, reached at sample 10 and held
    dV = np.array([2.54, 1.25, -2.23, -1.19, -0.94]) * 1e-9
    path = tmp_path / "board.csv"
    with Recorder(path, {"bench": bench.to_meta(), "tare": tare.to_dict(), "chain": chain.summary(),
                         "contact": "on-centre"}, layout=bench.layout) as r:
        for k in range(20):
            p = np.r_[boyle_dp(dV * min(1.0, k / 10), chain.v_total_m3, tare.p0_Pa), 0.0]
            r.write(to_measurement(k / 77, k, k / 77, simulate_raw(p, 100, rng, chain.transducers), 100, chain, tare))
    rec = tmp_path / "board.mcap"
    assert main(["live", "--source", f"replay:{path}", "--model", str(five_model_dir), "--estimator", "refresh",
                 "--speed", "0", "--no-stream", "--http-port", "0", "--record", str(rec),
                 "--lag-compensation", "off"]) == 0  # the estimator takes the recorded volumes as they are
    r = read_recording(rec)
    assert r.arm_names == arms and len(r.estimates) == len(r.sensors) == 20
    assert [k for k in r.sensors[0] if k.startswith("raw_")] == [f"raw_{a}" for a in (*arms, "urethra")]
    for e, m in zip(r.estimates, r.sensors):  # the estimator took each sample's five volumes
        for a in arms:
            assert e[f"dVmeas_{a}_mm3"] == pytest.approx(m[f"dV_{a}_mm3"], abs=1e-9)
    assert r.sensors[-1]["dV_top_mm3"] == pytest.approx(-0.94, abs=0.1)  # through the chain and its noise
    assert 0.6 < r.estimates[-1]["force_y_N"] < 1.4, r.estimates[-1]["force_y_N"]
