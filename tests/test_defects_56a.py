"""Issue #56 (defects found as a lab would use the tools): a replay at its recording's contact, a
tare under load, an estimator at rest, a urethra label too large, the Foxglove socket's rules,
acquire's event times, a replay cut mid-row, ``estimate --out`` and ``calibrate``'s files checked
first."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softphantom.cli import main


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err and err.startswith("error: "), err
    return err


def _meta(path) -> dict:
    return json.loads(open(path).readline()[1:])


def _recording(path, n=40, meta=None, load=None):
    """A sensing recording of ``n`` samples at 77 Hz of the BIP's chain (``load(k)``: the five
    channels' pressures in Pa at sample k, default at rest)."""
    from softphantom.sensing.chain import default_chain, nominal_tare, simulate_raw, to_measurement
    from softphantom.sensing.recording import Recorder

    chain = default_chain()
    tare = nominal_tare(chain)
    rng = np.random.default_rng(0)
    with Recorder(path, {"tare": tare.to_dict(), "chain": chain.summary(), **(meta or {})}, layout=chain.layout) as r:
        for k in range(n):
            p = np.zeros(5) if load is None else np.asarray(load(k), float)
            r.write(to_measurement(k / 77.0, k, k / 77.0, simulate_raw(p, 100, rng), 100, chain, tare))
    return path


# --- 1. a replay is estimated at its recording's contact ------------------------------------------

def test_a_virtual_run_records_its_scenarios_contact_and_the_replay_uses_it(coarse_model, coarse_model_dir,
                                                                            coarse_truth_p1, tmp_path):
    from softphantom.virtual import VirtualConfig, scenario_from_dict, simulate, write_run

    sc = scenario_from_dict({"name": "off", "duration_s": 1.6, "rest_s": 1.0, "push": [
        {"point": "off-centre", "start_s": 1.1, "rise_s": 0.2, "hold_s": 0.0, "fall_s": 0.2,
         "force_N": [0.0, 0.5, 0.0]}]}, "off.toml")
    run = simulate(sc, coarse_model, VirtualConfig.seeded(seed=1, osr=100, order=1), truth_mesh=coarse_truth_p1)
    paths = write_run(run, tmp_path / "run")
    assert _meta(paths["recording"])["contact"] == "off-centre"
    out = tmp_path / "e.csv"
    assert main(["estimate", "--model", str(coarse_model_dir), "--source", f"replay:{paths['recording']}",
                 "--estimator", "refresh", "--out", str(out)]) == 0
    meta = _meta(out)
    assert (meta["contact"], meta["contact_from"], meta["recording_contact"]) == ("off-centre", "recording",
                                                                                   "off-centre")


def test_a_replay_without_a_contact_on_a_model_of_several_asks_for_at(coarse_model_dir, tmp_path, capsys):
    rec = _recording(tmp_path / "r.csv")
    out = tmp_path / "e.csv"
    assert main(["estimate", "--model", str(coarse_model_dir), "--source", f"replay:{rec}", "--out", str(out)]) == 2
    assert _one_line(capsys) == (f"error: --source replay:{rec}: the recording names no contact point and this "
                                 "model has several (on-centre, off-centre); give --at")
    assert not out.exists()


# --- 17. estimate's --out is checked before any work --------------------------------------------

def test_estimate_refuses_an_out_it_cannot_create_before_reading_the_model(coarse_model_dir, tmp_path, capsys,
                                                                           monkeypatch):
    import softphantom.design

    def no(*a, **k):
        raise AssertionError("the model was read before --out was checked")

    monkeypatch.setattr(softphantom.design, "load_model", no)
    rec = _recording(tmp_path / "r.csv", meta={"contact": "on-centre"})
    (tmp_path / "file").write_text("x")
    out = tmp_path / "file" / "sub" / "e.csv"
    assert main(["estimate", "--model", str(coarse_model_dir), "--source", f"replay:{rec}", "--out", str(out)]) == 2
    assert _one_line(capsys) == (f"error: --out {out}: cannot be created ({tmp_path / 'file'} is a file, "
                                 "not a directory)")


def test_estimate_makes_the_folders_of_out(coarse_model_dir, tmp_path):
    rec = _recording(tmp_path / "r.csv", n=5, meta={"contact": "on-centre"})
    out = tmp_path / "missing_dir" / "x.csv"
    assert main(["estimate", "--model", str(coarse_model_dir), "--source", f"replay:{rec}", "--estimator",
                 "refresh", "--out", str(out)]) == 0
    assert out.is_file()


# --- 18. calibrate names a missing --truth or --known-loads file before reading the recording -----

@pytest.mark.parametrize("missing", ["--truth", "--known-loads"])
def test_calibrate_names_a_missing_file_first(coarse_model_dir, tmp_path, capsys, monkeypatch, missing):
    import softphantom.calibration.run as run

    monkeypatch.setattr(run, "load_session", lambda *a, **k: pytest.fail("the recording was read"))
    rec = _recording(tmp_path / "r.csv", n=5)
    truth = tmp_path / "take.csv"
    truth.write_text("t_s,x_mm\n")
    args = ["calibrate", "--model", str(coarse_model_dir), "--recording", str(rec), "--out", str(tmp_path / "cal"),
            "--truth", str(tmp_path / "missing.csv" if missing == "--truth" else truth)]
    if missing == "--known-loads":
        args += ["--known-loads", str(tmp_path / "missing.csv")]
    assert main(args) == 2
    assert _one_line(capsys) == f"error: {missing} {tmp_path / 'missing.csv'}: no such file"
    assert not (tmp_path / "cal").exists()


# --- 3. a label too large to be a urethra -------------------------------------------------------

def test_a_zone_is_not_taken_for_the_urethra(tmp_path, capsys, monkeypatch):
    nib = pytest.importorskip("nibabel")
    pytest.importorskip("skimage")
    import softphantom.design.anatomy_import as anatomy
    from label_maps import zonal_label_map
    from softphantom.design.anatomy import MAX_URETHRA_SHARE, AnatomyOptions, anatomy_from_labels
    from softphantom.errors import DesignError

    data, affine, _, _ = zonal_label_map(45.0)
    share = np.count_nonzero(data == 2) / np.count_nonzero(data)
    assert share > 2 * MAX_URETHRA_SHARE  # the transition zone: about a fifth of the gland
    monkeypatch.setitem(anatomy_from_labels.__globals__, "_marching_cubes",  # the module this function runs in
                        lambda *a: pytest.fail("refused after the surface was made"))
    with pytest.raises(DesignError, match=rf"urethra label 2 holds {share:.0%} of the gland, too much for a urethra"):
        anatomy_from_labels(data, affine, AnatomyOptions())
    path = tmp_path / "zones.nii.gz"
    nib.save(nib.Nifti1Image(data, affine), str(path))
    assert main(["design", "--anatomy", str(path), "--out", str(tmp_path / "o")]) == 2
    err = _one_line(capsys)
    assert "if the labels are zones, give --gland-labels 1,2 " in err and "radius" not in err, err
    assert not (tmp_path / "o").exists()
    # a urethra as thin as a urethra passes the check (the BIP's: 2 % of its bulb)
    thin = np.where(data > 0, 1, 0).astype(np.int16)
    centre = np.argwhere(thin > 0).mean(axis=0).round().astype(int)
    thin[centre[0] - 2:centre[0] + 3, centre[1] - 2:centre[1] + 3, :] *= 2
    assert 0 < np.count_nonzero(thin == 2) / np.count_nonzero(thin) < MAX_URETHRA_SHARE
    anatomy._check_urethra_share(thin, thin > 0, AnatomyOptions(), "map")


# --- 5. acquire's event rows at their own times -------------------------------------------------

class _Bench:
    """A scripted board behind a fake serial port, on a fake host clock: each port read takes the
    next item of ``script`` (bytes arrive; ``"unplug"`` fails the port, which then refuses to open
    for ``out_s``) and moves the clock 20 ms; the opener moves it 1 s per refused attempt."""

    REST = [51150 // 4, 51150 // 4, 51150 // 4, 51150 // 4, 4046 // 4]

    def __init__(self, script, out_s=22.5):
        import collections

        self.t = 1000.0
        self.script = collections.deque(script)
        self.out_s = out_s
        self.back_at = self.unplugged_at = None
        self.opened_at = []

    def clock(self):
        return self.t

    def opener(self, url, **kw):
        import serial

        if self.back_at is not None and self.t < self.back_at:
            self.t += 1.0
            raise serial.SerialException("no such device")
        self.opened_at.append(self.t)
        return _Port(self)

    @classmethod
    def frames(cls, seqs, t0_us=0, dt_us=20_000, info=False):
        from softphantom.sensing.protocol import encode_data, encode_info

        head = encode_info(0, t0_us, (1, 0, 0), 5, 25) if info else b""
        return head + b"".join(encode_data(k, t0_us + dt_us * i, 25, cls.REST) for i, k in enumerate(seqs))


class _Port:
    def __init__(self, bench):
        self.bench, self.timeout, self.in_waiting = bench, 0.05, 1

    def read(self, n=1):
        import time

        import serial

        b = self.bench
        b.t += 0.02
        item = b.script.popleft() if b.script else b""
        if item == "unplug":
            b.back_at, b.unplugged_at = b.t + b.out_s, b.t
            raise serial.SerialException("device reports readiness to read but returned no data")
        if not item:
            time.sleep(0.002)
        return item

    def write(self, data):
        return len(data)

    def close(self):
        pass


def _acquire_with(bench, monkeypatch, tmp_path, *args):
    import softphantom.sensing.sources as sources

    class Scripted(sources.SerialSource):
        def __init__(self, url, chain, **kw):
            super().__init__(url, chain, opener=bench.opener, clock=bench.clock, reconnect_every_s=0.25, **kw)

    monkeypatch.setattr(sources, "SerialSource", Scripted)
    out = tmp_path / "a.csv"
    rc = main(["acquire", "--port", "fake", "--out", str(out), "--tare-s", "0.2", *args])
    return rc, out


def _rows(path):
    """(t_s, status) of every row, markers included."""
    lines = open(path).read().splitlines()[2:]
    return [(float(line.split(",")[0]), line.rsplit(",", 1)[1]) for line in lines]


def _unplug_script(n_before=30):
    board1 = [_Bench.frames([], info=True)] + [_Bench.frames([k], t0_us=20_000 * (k + 1)) for k in range(n_before)]
    # the board is back 22.5 s later, restarted: its clock begins again; its first frames come at once
    return board1 + ["unplug"] + [b""] * 3 + [_Bench.frames(range(4), t0_us=5_000, info=True)] + \
        [_Bench.frames([k], t0_us=5_000 + 20_000 * k) for k in range(4, 40)]


def test_acquire_marks_an_unplug_and_a_new_board_at_their_own_times(tmp_path, monkeypatch, capsys):
    bench = _Bench(_unplug_script())
    rc, out = _acquire_with(bench, monkeypatch, tmp_path, "--on-new-board", "retare", "--duration-s", "1.5")
    text = capsys.readouterr().out
    assert rc == 0 and f"to {out}" in " ".join(text.split()), text
    rows = _rows(out)
    t = np.array([r[0] for r in rows])
    assert np.all(np.diff(t) >= 0)                                            # marker rows included
    ev = {s.split(":")[1]: tt for tt, s in rows if s.startswith("event:")}
    assert list(ev)[:5] == ["disconnected", "reconnected", "restart", "resumed", "retared"], ev
    assert ev["disconnected"] == pytest.approx(bench.unplugged_at, abs=1e-9)     # when the port failed
    assert ev["reconnected"] == pytest.approx(bench.opened_at[1], abs=1e-9)      # when it opened again
    assert ev["reconnected"] - ev["disconnected"] > 22.5
    assert ev["reconnected"] < ev["restart"] <= ev["resumed"] <= ev["retared"]
    # the new board's first burst of 4 frames keeps its board-clock spacing: no two samples share a time
    samples = np.array([tt for tt, s in rows if not s.startswith("event:")])
    after = samples[samples >= ev["restart"] - 0.1]
    assert len(after) >= 30 and np.all(np.diff(after) > 0.019), np.diff(after)[:6]


def test_acquire_stopped_by_a_new_board_says_what_it_kept(tmp_path, monkeypatch, capsys):
    bench = _Bench(_unplug_script())
    rc, out = _acquire_with(bench, monkeypatch, tmp_path, "--duration-s", "5")
    cap = capsys.readouterr()
    assert rc == 2 and "the board restarted or was replaced at t = " in cap.err
    t_err = float(cap.err.split("at t = ")[1].split(" s")[0])
    assert f"link events to {out}" in " ".join(cap.out.split()), cap.out
    rows = _rows(out)
    restart = [tt for tt, s in rows if s.startswith("event:restart")]
    assert restart == [pytest.approx(t_err, abs=1e-3)]
    after = rows[[s for _, s in rows].index(next(s for _, s in rows if s.startswith("event:restart"))):]
    assert all(s.startswith("event:") for _, s in after)                       # the new board's frames: not kept
    assert np.all(np.diff([r[0] for r in rows]) >= 0)


# --- 4. the Foxglove socket under the page's rules ----------------------------------------------

def _ws_open(port, host, origin=None, target="/"):
    """The HTTP status a WebSocket opening request gets from 127.0.0.1:``port``, and the socket."""
    import base64
    import os
    import socket

    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    req = (f"GET {target} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}\r\nSec-WebSocket-Version: 13\r\n"
           "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n" + (f"Origin: {origin}\r\n" if origin else "") + "\r\n")
    s.sendall(req.encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(4096)
        if not chunk:
            break
        head += chunk
    return int(head.split(b" ", 2)[1]), s


def test_the_foxglove_socket_keeps_the_pages_host_and_origin_rules(caplog):
    import logging
    import socket
    import struct
    import time

    from softphantom.stream.foxglove import FoxgloveServer
    from softphantom.viz.live.security import websocket_check

    srv = FoxgloveServer("127.0.0.1", 0, check=websocket_check("127.0.0.1"))
    try:
        p = srv.port
        for host, origin, status in ((f"evil.example:{p}", "http://evil.example", 403),   # DNS rebinding
                                     (f"127.0.0.1:{p}", "http://evil.example", 403),      # another site's page
                                     (f"127.0.0.1:{p}", "null", 403),                     # a sandboxed frame
                                     (f"127.0.0.1:{p}", None, 101),                       # a program, the desktop app
                                     (f"localhost:{p}", "https://app.foxglove.dev", 101),  # Foxglove's web app
                                     (f"localhost:{p}", "http://localhost:8765", 101)):   # a page of this machine
            got, s = _ws_open(p, host, origin)
            assert got == status, (host, origin, got)
            if got == 101:  # a client that drops without closing: not an error line
                caplog.clear()
                with caplog.at_level(logging.DEBUG):
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                    s.close()
                    time.sleep(0.5)
                assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.records
            s.close()
        caplog.clear()
        with caplog.at_level(logging.DEBUG):  # a client still connected when the session ends
            got, s = _ws_open(p, f"127.0.0.1:{p}")
            srv.close()
            s.close()
            time.sleep(0.5)
        assert got == 101 and not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.records
    finally:
        srv.close()


def test_the_foxglove_socket_beyond_loopback_needs_the_token():
    from softphantom.stream.foxglove import FoxgloveServer
    from softphantom.viz.live.security import websocket_check

    # the rules of a session on every interface, with its token (the gate itself bound to loopback here)
    check = websocket_check("0.0.0.0", token="s3cret")
    srv = FoxgloveServer("127.0.0.1", 0, check=check, token="s3cret")
    try:
        p = srv.port
        assert srv.url == f"ws://127.0.0.1:{p}/?token=s3cret"
        for target, status in (("/", 401), ("/?token=wrong", 401), ("/?token=s3cret", 101)):
            got, s = _ws_open(p, f"127.0.0.1:{p}", target=target)
            s.close()
            assert got == status, (target, got)
    finally:
        srv.close()


def test_live_beyond_loopback_prints_the_foxglove_address_with_its_token(capsys):
    assert main(["live", "--listen-host", "0.0.0.0", "--allow-remote", "--foxglove", "--foxglove-port", "0",
                 "--duration-s", "0.5", "--http-port", "0", "--no-stream"]) == 0
    cap = capsys.readouterr()
    token = cap.out.split("?token=")[1].split()[0]
    assert f"/?token={token}" in cap.out.split("Foxglove: ")[1].split()[0]
    assert "Foxglove server has no authentication" not in cap.err


# --- 16. a replay cut short says so --------------------------------------------------------------

def test_a_session_recording_cut_short_is_replayed_with_one_warning(tmp_path, capsys):
    rec = tmp_path / "s.mcap"
    assert main(["live", "--source", "synthetic", "--duration-s", "1", "--http-port", "0", "--no-stream",
                 "--record", str(rec)]) == 0
    data = rec.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])  # its writer killed: no footer, a chunk cut
    capsys.readouterr()
    assert main(["live", "--source", f"replay:{cut}", "--speed", "0", "--http-port", "0", "--no-stream"]) == 0
    cap = capsys.readouterr()
    said = [ln for ln in (cap.out + cap.err).splitlines() if "truncated file" in ln]
    assert len(said) == 1 and said[0].startswith(f"warning: {cut}: not closed cleanly"), cap
    shown = int(cap.out.split("done: ")[1].split()[0])
    assert f", {shown} estimates), the rest dropped" in said[0]


def test_a_sensing_recording_cut_mid_row_is_estimated_with_one_warning(coarse_model_dir, tmp_path, capsys):
    rec = _recording(tmp_path / "r.csv", n=12, meta={"contact": "on-centre"})
    rec.write_bytes(rec.read_bytes()[:-25])                                 # killed mid-row
    out = tmp_path / "e.csv"
    assert main(["estimate", "--model", str(coarse_model_dir), "--source", f"replay:{rec}", "--estimator",
                 "refresh", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    said = [ln for ln in (cap.out + cap.err).splitlines() if "truncated file" in ln]
    assert len(said) == 1 and "line 14" in said[0] and "a row cut short, dropped" in said[0], said
    assert len(open(out).read().splitlines()) == 2 + 11


# --- 2. a tare under load is refused; an estimator at rest says zero, or says it is off ----------

def test_a_tare_window_on_a_push_is_refused_and_rest_is_not():
    """A push as the scenarios make it (cosine ramps, a 0.8 s hold shorter than the window: the
    first push of push-on-centre, 60 Pa at the transducers as on the linear 12 mm model, through the
    12 m tube's lag and the board's noise): every 1 s window it moves is refused, every window at
    rest is tared."""
    from softphantom.sensing.chain import NotAtRestError, default_chain, simulate_raw, tare_from_window
    from softphantom.virtual.scenario import Event

    from softphantom.sensing.pneumatics import first_order_lag, tube_time_constant_s

    chain = default_chain()
    push = Event("push", 2.0, 1.2, 0.8, 1.0)
    t = np.arange(0.0, 7.0, 1 / 77.0)
    tau = tube_time_constant_s(12.0, 1.2e-3, 514e-9, 101_325.0)     # through the 12 m tube, as the board
    load = first_order_lag(60.0 * push.level(t), 1 / 77.0, tau, y0=0.0)
    p = np.zeros((len(t), 5))
    p[:, :4] = load[:, None] * np.array([1.0, 1.1, -1.2, -1.05])
    raw = simulate_raw(p, 25, np.random.default_rng(3), chain.transducers, 0.5)
    seen = []  # (the window's largest load Pa, its mean load Pa, the refusal or None)
    for i in range(0, len(t) - 77, 4):
        w = slice(i, i + 78)
        try:
            tare_from_window(raw[w], 25, t[w], chain)
            seen.append((load[w].max(), load[w].mean(), None))
        except NotAtRestError as exc:
            seen.append((load[w].max(), load[w].mean(), str(exc)))
    rest = [why for top, _, why in seen if top < 0.05]
    assert len(rest) >= 30 and rest == [None] * len(rest)                   # every window at rest is tared
    tared = [mean for top, mean, why in seen if why is None]
    assert max(tared) < 0.5, max(tared)                                     # none under load got through
    assert any("bends by" in why for _, _, why in seen if why)


def test_the_atlas_at_rest_is_checked_and_an_off_one_is_flagged(coarse_model, shared_dir, tmp_path, capsys):
    """The coarse model's small atlas (3 × 4 × 3 × 2 points) returns the rest state at rest; the
    same atlas with its volumes off by a constant 0.3 mm³ at zero load (as a grid too coarse near
    zero is) does not: estimate says so in one warning line, in the estimate file (``rest_check``,
    ``warnings``), and evaluate's notes read it."""
    import dataclasses

    from shared_models import atlas_config, cached_atlas

    from softphantom.design import save_model
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.check import GOALS
    from softphantom.estimation.atlas.estimator import AtlasEstimator
    from softphantom.estimation.atlas.store import atlas_path, save_atlas
    from softphantom.evaluation.files import read_estimate

    cfg = EstimatorConfig.box(10.0, contact="on-centre")
    good = AtlasEstimator(coarse_model, cfg, cached_atlas(shared_dir)).rest_check()
    assert good["ok"] and good["in_envelope"] and good["force_N"] < GOALS["force_N"], good
    base = cached_atlas(shared_dir)
    cV = base.cV.copy()
    cV[(0,) * (cV.ndim - 1)] += np.array([0.3, 0.3, -0.3, 0.0]) * 1e-9   # the constant term: V off by it everywhere
    atlas = dataclasses.replace(base, cV=cV)
    est = AtlasEstimator(coarse_model, cfg, atlas)
    rc = est.rest_check()
    # the closed form at rest: the atlas's own volumes and points at zero load, and the estimate there
    zero = atlas.coords(np.zeros(3), 0.0)
    assert rc["dV_at_zero_mm3"] == pytest.approx(float(np.abs(atlas.volumes(zero)[0]).max() * 1e9), rel=1e-9)
    lam = est.invert(np.zeros(4), 0.0, start=zero)[0]
    assert rc["force_N"] == pytest.approx(float(np.linalg.norm(atlas.forces(lam))), rel=1e-9)
    assert rc["pos_mm"] > GOALS["pos_mm"] and not rc["ok"]
    d = tmp_path / "model"
    save_model(coarse_model, d)
    save_atlas(atlas, atlas_path(d, atlas.key))
    rec = _recording(tmp_path / "r.csv", n=10, meta={"contact": "on-centre"})
    out = tmp_path / "e.csv"
    c = atlas_config()
    env = ",".join(f"{lo:g}:{hi:g}" for lo, hi in zip((*c.force_min_N, c.p_min_kPa), (*c.force_max_N, c.p_max_kPa)))
    assert main(["estimate", "--model", str(d), "--source", f"replay:{rec}", "--out", str(out),
                 "--atlas-grid", "3,4,3,2", "--envelope", env]) == 0
    said = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("warning: the atlas at rest")]
    assert len(said) == 1, said
    meta = _meta(out)
    assert meta["rest_check"]["ok"] is False and meta["rest_check"]["pos_mm"] == pytest.approx(rc["pos_mm"])
    assert any(w.startswith("the atlas at rest") for w in read_estimate(out).meta["warnings"])


def test_a_dropped_client_is_a_debug_line_on_the_receiving_and_the_sending_side():
    """The SDK logs a client that drops as an error on whichever side noticed it: a reset seen while
    sending (a message was on its way) is as routine as one seen while receiving; another send
    error stays an error."""
    import logging

    from softphantom.stream.foxglove import _QuietDisconnects

    def level(msg):
        r = logging.LogRecord("foxglove.websocket.connected_client.poller", logging.ERROR, "x.rs", 1, msg, None, None)
        _QuietDisconnects().filter(r)
        return r.levelno

    assert level("Error receiving from client 127.0.0.1:1: Connection reset") == logging.DEBUG
    assert level("Error sending message to client 127.0.0.1:1: IO error: Connection reset by peer (os error 104)") == logging.DEBUG
    assert level("Error sending message to client 127.0.0.1:1: IO error: Broken pipe (os error 32)") == logging.DEBUG
    assert level("Error sending message to client 127.0.0.1:1: message too large") == logging.ERROR
