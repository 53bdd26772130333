"""estimate_stream, the estimate CSV and ``softphantom estimate``."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from softphantom.records import BIP_LAYOUT
from softphantom.cli import main
from softphantom.design import save_model
from softphantom.estimation import Estimate, estimate_columns, estimate_stream
from softphantom.evaluation import read_estimate
from softphantom.evaluation.files import read_table
from softphantom.pose import Pose6
from softphantom.sensing import Measurement
from softphantom.sensing.chain import default_chain, nominal_tare, simulate_raw, to_measurement
from softphantom.sensing.pneumatics import boyle_dp
from softphantom.sensing.recording import Recorder
from softphantom.sensing.sources import SensorSource, SourceStats
from softphantom.sensing.protocol import DecoderStats
from softphantom.stream.schema import csv_columns


@pytest.fixture(scope="module")
def model_dir(coarse_model, tmp_path_factory):
    d = tmp_path_factory.mktemp("est_model")
    save_model(coarse_model, d)
    return d


def _recording(path, n=30, bad=(7,)):
    """A sensing recording of a push ramping to ~1 N (volumes of the linear rest model of the
    default BIP's order of magnitude), made through the chain; rows in ``bad`` are rail errors."""
    chain = default_chain()
    tare = nominal_tare(chain)
    rng = np.random.default_rng(1)
    target = np.array([0.6, 0.5, -2.7, -2.6]) * 1e-9
    with Recorder(path, {"tare": tare.to_dict(), "chain": chain.summary(), "contact": "on-centre"},
                  layout=chain.layout) as rec:
        for k in range(n):
            dV = target * k / (n - 1)
            p = np.r_[boyle_dp(dV, chain.v_total_m3, tare.p0_Pa), 0.0]
            raw = simulate_raw(p, 100, rng)
            if k in bad:
                raw[3] = 0  # disconnected back_xneg channel
            rec.write(to_measurement(k / 77.0, k, k / 77.0, raw, 100, chain, tare))
    return path


def test_cli_estimate_replay_writes_the_estimate_csv(model_dir, tmp_path, coarse_model):
    rec = _recording(tmp_path / "rec.csv")
    out = tmp_path / "est.csv"
    rc = main(["estimate", "--model", str(model_dir), "--source", f"replay:{rec}", "--out", str(out),
               "--max-force-N", "5", "--qp-solver", "quadprog", "--estimator", "refresh"])
    assert rc == 0
    tab = read_table(out)
    targets = list(coarse_model.targets)
    assert list(tab.columns) == estimate_columns(targets, BIP_LAYOUT) == csv_columns(targets, BIP_LAYOUT)
    assert tab.meta["softphantom"] and tab.meta["qp_solver"] == "quadprog" and tab.meta["mode"] == "sync"
    assert len(tab.columns["t_s"]) == 30
    status = tab.columns["qp_status"]
    assert status[7].startswith("rejected:rail:back_xneg")
    assert all(s == "optimal" for i, s in enumerate(status) if i != 7)
    # the rejected row repeats the previous state
    for c in ("force_y_N", "y_mm"):
        assert tab.columns[c][7] == tab.columns[c][6]
    f = np.column_stack([tab.columns[f"force_{a}_N"] for a in "xyz"])
    assert np.all(np.abs(f) <= 5.0 + 1e-9)
    assert f[-1, 1] > 0.3  # a push along +y was seen
    assert np.all(tab.columns["skipped"] == 0)
    assert read_estimate(out).pose.xyz.shape == (30, 3)  # evaluation reads it


class _FastLiveSource(SensorSource):
    """Delivers ``n`` samples in small batches every millisecond, whatever the consumer does."""

    live = True

    def __init__(self, n: int) -> None:
        self.n, self.k = n, 0
        self.closed = False

    def read(self, timeout_s=0.1):
        if self.k >= self.n:
            return None
        time.sleep(0.001)
        out = []
        for _ in range(2):
            if self.k < self.n:
                out.append(Measurement(self.k * 1e-3, self.k, 0.0, np.zeros(5, int), 100, np.zeros(4),
                                       np.zeros(4), 0.0))
                self.k += 1
        return out

    def stats(self):
        return SourceStats("ok", DecoderStats())

    def close(self):
        self.closed = True


class _SlowEstimator:
    from softphantom.records import BIP_LAYOUT as layout

    target_names = ()

    def __init__(self):
        self.seen = []

    def step(self, m, skipped=0):
        time.sleep(0.01)
        self.seen.append(m.seq)
        z = np.zeros(3)
        return Estimate(m.t, z, 0.0, Pose6(z, z), {}, np.zeros(4), np.zeros(4), 1.0, "optimal", 0.01, skipped,
                        layout=self.layout)


def test_live_stream_takes_the_newest_sample_and_counts_skipped(tmp_path):
    src, est = _FastLiveSource(400), _SlowEstimator()
    s = estimate_stream(src, est, tmp_path / "live.csv")
    tab = read_table(tmp_path / "live.csv")
    n = len(tab.columns["t_s"])
    assert s["estimates"] == n and tab.meta["live"] is True
    assert s["skipped"] > 0 and s["skipped"] == int(tab.columns["skipped"].sum())
    assert n + s["skipped"] == 400  # every sample either estimated or counted as skipped
    assert est.seen == sorted(est.seen) and est.seen[-1] == 399  # newest first, the last one reached
    assert src.closed


def test_stream_stop_event_ends_a_live_run(tmp_path):
    stop = threading.Event()
    src = _FastLiveSource(10**9)
    threading.Timer(0.2, stop.set).start()
    s = estimate_stream(src, _SlowEstimator(), tmp_path / "x.csv", stop=stop)
    assert 0 < s["estimates"] < 100 and src.closed


@pytest.mark.parametrize("args, msg", [
    (["--source", "bogus:x"], "unknown kind"),
    (["--source", "replay:/nonexistent.csv"], "no such file"),
    (["--qp-solver", "osqp"], "--qp-solver"),
    (["--max-force-N", "-1"], "--max-force-N"),
    (["--at", "middle"], "--at"),
])
def test_cli_estimate_bad_input_exits_2(model_dir, tmp_path, capsys, args, msg):
    rec = _recording(tmp_path / "r.csv", n=3, bad=())
    base = {"--model": str(model_dir), "--source": f"replay:{rec}", "--out": str(tmp_path / "o.csv")}
    for k, v in zip(args[::2], args[1::2]):
        base[k] = v
    argv = ["estimate"] + [x for kv in base.items() for x in kv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err


def test_cli_estimate_needs_a_model_dir(tmp_path, capsys):
    assert main(["estimate", "--model", str(tmp_path), "--source", "replay:x", "--out", str(tmp_path / "o.csv")]) == 2
    assert "not a model directory" in capsys.readouterr().err
