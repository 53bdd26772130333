"""The bench in one place (softphantom.sensing.bench): BenchConfig, open_source (softphantom.sources), the tare, the
new-board policy, and the options reaching the commands and the recordings' metadata."""

from __future__ import annotations

import numpy as np
import pytest
import serial

from softphantom.cli import main
from softphantom.design import save_model
from softphantom.errors import UserError
from softphantom.evaluation.files import read_table
from softphantom.sensing.bench import BenchConfig, NewBoardError, RetareSource
from softphantom.sensing.chain import default_chain, nominal_tare
from softphantom.sensing.measurement import TUBE_ID_M, TUBE_LENGTH_M
from softphantom.sources import open_source
from softphantom.sensing.pneumatics import tube_volume_m3
from softphantom.sensing.protocol import encode_data
from softphantom.sensing.recording import Recorder, read_recording
from softphantom.sensing.sources import FrameSource, SerialSource

REST25 = [12787, 12787, 12787, 12787, 1011]


@pytest.fixture(scope="module")
def model_dir(coarse_model, tmp_path_factory):
    d = tmp_path_factory.mktemp("bench_model")
    save_model(coarse_model, d)
    return d


def test_bench_config_is_the_one_place_for_the_chain(coarse_model):
    b = BenchConfig()
    assert (b.tube_length_m, b.tube_id_m) == (TUBE_LENGTH_M, TUBE_ID_M) == (12.0, 1.2e-3)
    v_tube = tube_volume_m3(12.0, 1.2e-3)
    assert np.allclose(b.chain().v_total_m3, np.array([514, 514, 486, 486]) * 1e-9 + v_tube)   # DESIGN.md §3
    m = BenchConfig.from_model(coarse_model, tube_length_m=3.0)
    arms = {a.name: a.cavity_volume_mm3 for a in coarse_model.design.arms}
    assert m.cavity_volumes_m3[0] == pytest.approx(arms["front_zpos"] * 1e-9) and m.tube_length_m == 3.0
    o = BenchConfig.from_options(6.0, 0.8, 95.0, model=coarse_model)
    assert (o.tube_length_m, o.tube_id_m, o.p0_Pa) == (6.0, pytest.approx(0.8e-3), 95_000.0)
    assert np.allclose(o.chain().v_total_m3, np.asarray(m.cavity_volumes_m3) + tube_volume_m3(6.0, 0.8e-3))
    assert BenchConfig.from_meta({"bench": o.to_meta()}).same_as(o)
    # recordings written before the bench entry: the design keys and p0_Pa
    legacy = {"design": {"arm_cavity_mm3": [514, 514, 486, 486], "tube_length_m": 12.0, "tube_id_mm": 1.2},
              "p0_Pa": 99_000.0}
    assert BenchConfig.from_meta(legacy).same_as(BenchConfig(p0_Pa=99_000.0))
    for kw, msg in ((dict(tube_length_m=0.0), "--tube-length-m"), (dict(tube_id_m=float("nan")), "--tube-id-mm"),
                    (dict(p0_Pa=-1.0), "--p0-kPa"), (dict(cavity_volumes_m3=(1e-9,) * 3), "cavity volumes")):
        with pytest.raises(UserError, match=msg):
            BenchConfig(**kw)


def _record(path, bench, contact="off-centre", n=40, push_codes=0):
    chain = bench.chain()
    tare = nominal_tare(chain, bench.p0_Pa)
    raw = np.array(REST25)
    frames = []
    for k in range(n):
        r = raw.copy()
        r[2] += int(push_codes * k / n)
        frames.append(encode_data(k, 13_000 * k, 25, r))
    ms = list(FrameSource([b"".join(frames)], chain, tare))
    with Recorder(path, {"bench": bench.to_meta(), "tare": tare.to_dict(), "chain": chain.summary(),
                         "contact": contact}, layout=chain.layout) as rec:
        for m in ms:
            rec.write(m)
    return ms


def test_replay_follows_the_recording_and_reconverts_on_a_different_tube(tmp_path):
    short = BenchConfig(tube_length_m=3.0)
    ms = _record(tmp_path / "r.csv", short, push_codes=400)
    opened = open_source(f"replay:{tmp_path / 'r.csv'}")
    got = list(opened.source)
    assert opened.bench.same_as(short) and not opened.meta["reconverted"]
    assert opened.meta["recording_contact"] == "off-centre"
    assert np.allclose([m.dV for m in got], [m.dV for m in ms])
    # the same pressures behind 12 m of tube mean a larger volume change: re-converted from raw
    long = open_source(f"replay:{tmp_path / 'r.csv'}", options={"tube_length_m": 12.0})
    got12 = list(long.source)
    assert long.meta["reconverted"] and long.bench.tube_length_m == 12.0
    ratio = got12[-1].dV[2] / got[-1].dV[2]
    assert ratio == pytest.approx(BenchConfig().chain().v_total_m3[2] / short.chain().v_total_m3[2], rel=1e-6)   # the file keeps 1e-6 mm³


def test_cli_estimate_takes_bench_and_contact_from_the_recording(tmp_path, model_dir, capsys):
    _record(tmp_path / "r.csv", BenchConfig(tube_length_m=3.0), contact="off-centre")
    # the refresh estimator: what is tested is the recording's metadata reaching the estimate; the
    # default atlas would build 700 solves per contact point first (717-772 s of this test at load 11-16)
    out = tmp_path / "e.csv"
    assert main(["estimate", "--model", str(model_dir), "--source", f"replay:{tmp_path / 'r.csv'}",
                 "--out", str(out), "--estimator", "refresh"]) == 0, capsys.readouterr().err
    meta = read_table(out).meta
    assert meta["contact"] == "off-centre" and meta["bench"]["tube_length_m"] == 3.0
    out2 = tmp_path / "e2.csv"
    assert main(["estimate", "--model", str(model_dir), "--source", f"replay:{tmp_path / 'r.csv'}",
                 "--out", str(out2), "--tube-length-m", "12", "--tube-id-mm", "1.2", "--at", "on-centre", "--estimator", "refresh"]) == 0
    meta2 = read_table(out2).meta
    assert meta2["contact"] == "on-centre" and meta2["bench"]["tube_length_m"] == 12.0 and meta2["reconverted"]
    assert main(["estimate", "--model", str(model_dir), "--source", f"replay:{tmp_path / 'r.csv'}",
                 "--out", str(tmp_path / "e3.csv"), "--tube-id-mm", "0", "--estimator", "refresh"]) == 2
    assert "--tube-id-mm" in capsys.readouterr().err


def test_replay_of_a_bench_entry_of_another_shape_falls_back_to_the_design(tmp_path, coarse_model, model_dir,
                                                                            capsys):
    """A recording whose ``bench`` metadata has another shape (another program, an older version)
    is replayed with the design's bench, its raw sums re-converted, and one note says what was
    unusable; the same raw sums recorded with the design's bench give the same volumes."""
    import json

    design = BenchConfig.from_model(coarse_model)
    want = _record(tmp_path / "design.csv", design, push_codes=400)
    _record(tmp_path / "r.csv", BenchConfig(tube_length_m=3.0), push_codes=400)
    lines = (tmp_path / "r.csv").read_text().splitlines(keepends=True)
    meta = json.loads(lines[0][2:])
    meta["bench"] = {"tube_m": 3.0, "tube_diameter_mm": 1.2, "cavities_mm3": [514, 514, 486, 486]}
    (tmp_path / "r.csv").write_text("# " + json.dumps(meta) + "\n" + "".join(lines[1:]))
    opened = open_source(f"replay:{tmp_path / 'r.csv'}", coarse_model)
    assert opened.bench.same_as(design) and opened.meta["reconverted"]
    assert len(opened.notes) == 1 and "\n" not in opened.notes[0]
    assert "no 'tube_length_m'" in opened.notes[0] and "tube_m" in opened.notes[0] and "design's bench" in opened.notes[0]
    assert np.allclose([m.dV for m in opened.source], [m.dV for m in want], rtol=1e-6, atol=1e-15)
    # the command says it in one line and goes on
    out = tmp_path / "e.csv"
    assert main(["estimate", "--model", str(model_dir), "--source", f"replay:{tmp_path / 'r.csv'}",
                 "--out", str(out), "--estimator", "refresh"]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert sum("note:" in ln and "no 'tube_length_m'" in ln for ln in printed.splitlines()) == 1
    assert read_table(out).meta["bench"] == design.to_meta()


class _Loop:
    """A loop:// board whose frames the test writes; ``restart`` = a new board (clock from 0)."""

    def __init__(self):
        self.ports = []

    def __call__(self, url, **kw):
        p = serial.serial_for_url("loop://", **kw)
        self.ports.append(p)
        return p

    def send(self, seqs, t0_us, push=0):
        raw = np.array(REST25)
        raw[0] += push
        self.ports[-1].write(b"".join(encode_data(k, t0_us + 13_000 * i, 25, raw) for i, k in enumerate(seqs)))


def _serial(policy, board):
    src = SerialSource("fake", default_chain(), opener=board, reconnect_every_s=0.01)
    src.read(0.001)
    board.send(range(10), 5_000_000)
    return RetareSource(src, BenchConfig(), policy, tare_s=0.05, label="--source serial:fake")


def test_new_board_policy_stop_refuses_with_one_line():
    board = _Loop()
    src = _serial("stop", board)
    board.send(range(10, 20), 5_130_000)
    board.send(range(0, 10), 1_000)                       # the clock restarted: a new board
    got = []
    with pytest.raises(NewBoardError, match="restarted or was replaced.*--on-new-board retare"):
        for _ in range(20):
            got += src.read(0.01)
    assert [m.seq for m in got] == list(range(20))        # the old board's frames all came out first
    assert [e.kind for e in src.events()] == ["restart"]  # the marker is not lost
    src.close()


def test_new_board_policy_retare_holds_the_window_back_and_drops_nothing():
    board = _Loop()
    src = _serial("retare", board)
    board.send(range(0, 12), 1_000, push=300)            # new board, different zero (+300 codes)
    got = []
    for _ in range(20):
        got += src.read(0.01)
    kinds = [e.kind for e in src.events()]
    assert kinds == ["restart", "retared"]
    # the old board's 10 frames, then the new board's, its tare window included, re-converted
    assert [m.seq for m in got] == list(range(10)) + list(range(12))
    assert np.allclose([m.dp[0] for m in got[10:]], 0.0, atol=1.0)   # the new zero is removed
    src.close()
    with pytest.raises(UserError, match="--on-new-board"):
        RetareSource(src.inner, BenchConfig(), "ignore")


def _info_alone_then_new_board(policy):
    """The new board's first message is an INFO frame alone (read on its own), then its frames
    with another zero (+300 codes)."""
    from softphantom.sensing.protocol import encode_info

    board = _Loop()
    src = _serial(policy, board)
    got = []
    for _ in range(5):
        got += src.read(0.01)
    board.ports[-1].write(encode_info(0, 800, osr=25))
    return board, src, got


def test_new_board_announced_by_an_info_frame_alone_still_stops():
    board, src, got = _info_alone_then_new_board("stop")
    with pytest.raises(NewBoardError, match="restarted or was replaced"):
        got += src.read(0.01)                          # the INFO frame alone: stop at once
    board.send(range(0, 12), 1_000, push=300)
    with pytest.raises(NewBoardError):                 # and for good
        src.read(0.01)
    assert [m.seq for m in got] == list(range(10))      # none of the new board's frames got through
    assert [e.kind for e in src.events()] == ["restart"]
    src.close()


def test_new_board_announced_by_an_info_frame_alone_is_retared():
    board, src, got = _info_alone_then_new_board("retare")
    got += src.read(0.01)
    board.send(range(0, 12), 1_000, push=300)
    for _ in range(20):
        got += src.read(0.01)
    assert [e.kind for e in src.events()] == ["restart", "retared"]
    assert [m.seq for m in got] == list(range(10)) + list(range(12))
    assert np.allclose([m.dp[0] for m in got[10:]], 0.0, atol=1.0)   # the new board's zero, not the old one's
    src.close()


def test_virtual_phantom_uses_the_same_bench(coarse_model):
    from softphantom.cli.options import VirtualOptions
    from softphantom.cli.virtual import _config
    from softphantom.virtual.run import host_bench, host_chain

    cfg = _config(VirtualOptions(tube_length_m=3.0, tube_id_mm=1.0))
    assert (cfg.board.tube_length_m, cfg.board.tube_id_m) == (3.0, pytest.approx(1.0e-3))
    hb = host_bench(coarse_model, cfg.board)
    assert hb.same_as(BenchConfig.from_model(coarse_model, tube_length_m=3.0, tube_id_m=1.0e-3))
    assert np.allclose(host_chain(coarse_model, cfg.board).v_total_m3, hb.chain().v_total_m3)


def test_estimate_output_has_the_retared_marker_after_an_info_frame_alone(tmp_path):
    import threading

    from stub_estimators import EchoEstimator

    from softphantom.estimation import estimate_stream
    from softphantom.evaluation.files import read_table

    board, src, got = _info_alone_then_new_board("retare")
    assert src.read(0.01) == []                                    # the INFO frame alone
    board.send(range(0, 12), 1_000, push=300)
    stop = threading.Event()
    threading.Timer(10.0, stop.set).start()                        # a safety net: 12 frames come at once
    s = estimate_stream(src, EchoEstimator(), tmp_path / "e.csv", live=True, stop=stop, max_samples=12)
    stop.set()
    assert s["events"] == {"restart": 1, "retared": 1}
    status = list(read_table(tmp_path / "e.csv").columns["status"])
    assert status[0].startswith("event:restart") and status[1].startswith("event:retared")


def test_cli_says_a_truncated_recording_in_one_line(tmp_path, model_dir, capsys):
    rec = tmp_path / "r.csv"
    _record(rec, BenchConfig())
    data = rec.read_bytes()
    rec.write_bytes(data[:-20])                                   # killed mid-row
    assert main(["estimate", "--model", str(model_dir), "--source", f"replay:{rec}", "--out", str(tmp_path / "e.csv"),
                 "--estimator", "refresh"]) == 0
    cap = capsys.readouterr()
    said = [ln for ln in (cap.out + cap.err).splitlines() if "truncated file" in ln or "Warning:" in ln or "warn(" in ln]
    assert len(said) == 1 and said[0].startswith("warning: ") and "a row cut short, dropped" in said[0], said
