"""Evaluation metrics, Table I comparison and the estimate/truth files, against hand-computed cases."""

import sys
from pathlib import Path

import numpy as np
import pytest

from softphantom.errors import FileFormatError
from softphantom.evaluation import (
    Series6,
    compare_table_i,
    error_stats,
    evaluate,
    read_estimate,
    read_table,
    read_truth,
    write_table,
    write_truth,
)
from softphantom.pose import Pose6

sys.path.insert(0, str(Path(__file__).resolve().parent))
from evaluation_synth import motion, write_run  # noqa: E402


def test_error_stats_hand_computed():
    s = error_stats("y", "mm", np.array([1.0, 2.0, 4.0]), np.array([1.0, 1.0, 2.0]), lag_ms=12.0)
    # errors 0, 1, 2
    assert s.rmse == pytest.approx(np.sqrt(5 / 3), abs=1e-15)
    assert s.bias == pytest.approx(1.0) and s.max_abs == 2.0 and s.peak_truth == 2.0 and s.n == 3
    # r = (15/9) / sqrt(42/9 · 6/9) = 15 / sqrt(252)
    assert s.corr == pytest.approx(15 / np.sqrt(252), abs=1e-14)
    assert s.lag_ms == 12.0
    flat = error_stats("x", "mm", np.array([1.0, 1.0]), np.array([0.0, 2.0]))
    assert np.isnan(flat.corr) and flat.bias == 0.0 and flat.max_abs == 1.0


def _series(t, v, force=None, targets=None):
    return Series6(np.asarray(t, float), Pose6.from_mm_deg(v), force=force, targets=targets or {}, source="mem")


def test_evaluate_constant_bias_given_lag():
    t = np.linspace(0, 4, 401)
    v = np.zeros((401, 6))
    v[:, 1] = np.interp(t, [0, 1, 2, 3, 4], [0, 0, 5, 5, 0])  # piecewise linear: interpolation exact
    v[:, 3] = 0.5 * v[:, 1]
    te = np.linspace(0.5, 3.5, 97)
    ve = np.column_stack([np.interp(te, t, v[:, k]) for k in range(6)])
    ve[:, 1] += 0.5  # +0.5 mm bias in y
    ve[:, 3] -= 0.2  # −0.2° in yaw
    ev = evaluate(_series(t, v), _series(te, ve), lag_ms=0.0)
    y, yaw, x = ev.dof[1], ev.dof[3], ev.dof[0]
    assert (y.rmse, y.bias, y.max_abs) == pytest.approx((0.5, 0.5, 0.5), abs=1e-9)
    assert y.corr == pytest.approx(1.0, abs=1e-12)
    assert (yaw.rmse, yaw.bias) == pytest.approx((0.2, -0.2), abs=1e-9)
    assert x.rmse == 0.0 and np.isnan(x.corr)
    assert ev.lag is None and ev.lag_source == "given" and ev.mask.all()


def test_evaluate_measures_lag_and_gain_error(tmp_path):
    gain, lag = 1.05, 100.0
    pe, pt = write_run(tmp_path, lag_ms=lag, gain=gain, noise_mm=0.0, est_noise=0.0, est_start_s=0.0)
    est, tru = read_estimate(pe), read_truth(pt)
    ev = evaluate(tru, est)
    assert abs(ev.lag_ms - lag) < 2.0  # noise-free: well within the 5 ms of the issue
    assert all(abs(s.lag_ms - lag) < 5.0 for s in ev.dof)
    # with the given lag the error is exactly (gain − 1)·truth at the compared samples
    ev = evaluate(tru, est, lag_ms=lag)
    v_true, f_true = motion(est.t[ev.mask] - lag / 1e3)
    for k, s in enumerate(ev.dof):
        e = (gain - 1) * v_true[:, k]
        assert s.rmse == pytest.approx(np.sqrt(np.mean(e**2)), abs=2e-3)
        assert s.bias == pytest.approx(np.mean(e), abs=2e-3)
        assert s.corr == pytest.approx(1.0, abs=1e-5)
    fy = ev.force[1]
    assert fy.name == "force_y" and fy.max_abs == pytest.approx((gain - 1) * 3.0, abs=1e-3)
    (target,) = ev.targets
    d = (gain - 1) * np.linalg.norm(v_true[:, :3] * [0.8, 0.9, 1.0], axis=1)
    assert target.name == "seed_1" and target.max_abs == pytest.approx(d.max(), abs=2e-3)
    assert target.rmse == pytest.approx(np.sqrt(np.mean(d**2)), abs=2e-3)


def test_evaluate_noisy_lag_and_rezeroed_clock(tmp_path):
    pe, pt = write_run(tmp_path, lag_ms=100.0, seed=3, est_start_s=0.0)
    tab = read_table(pt)
    cols = dict(tab.columns)
    cols["t_s"] = cols["t_s"] + 1.7e9  # truth on an epoch clock, estimate on seconds since start
    write_table(tmp_path / "epoch.csv", tab.meta, cols)
    est = read_estimate(pe)
    ev = evaluate(read_truth(tmp_path / "epoch.csv"), est)
    assert ev.clock_rezeroed and any("re-zeroed" in n for n in ev.notes)
    # both clocks re-zeroed at their first sample: the estimate's first (at ~13 ms) moves to 0
    assert abs(ev.lag_ms - (100.0 - 1e3 * est.t[0])) < 5.0


def test_force_unknown_to_truth_is_noted(tmp_path):
    t = np.linspace(0, 3, 301)
    v = np.zeros((301, 6))
    v[:, 1] = np.sin(t)
    ev = evaluate(_series(t, v), _series(t, v, force=np.zeros((301, 3))), lag_ms=0.0)
    assert ev.force == () and any("does not know the force" in n for n in ev.notes)


@pytest.mark.parametrize(
    "peak, flags",
    [
        # x, y, z mm; yaw, pitch, roll deg → flags in TABLE_I order:
        # yaw L, pitch L, x Stone, x Podder, y Stone, y Podder17, y Podder18, z Stone
        ([1.4, 6.6, 6.8, 13.0, 8.0, 0.0], ["within", "within", "within", "within", "within", "below", "within", "within"]),
        ([0.5, 31.0, 9.0, 13.5, 2.0, 5.0], ["above", "within", "below", "below", "above", "above", "above", "above"]),
    ],
)
def test_table_i_flags(peak, flags):
    v = np.zeros((5, 6))
    v[2] = -np.array(peak)  # the sign must not matter: max |Δ|
    rows = compare_table_i(v, v * 0.5)
    assert [r.flag for r in rows] == flags
    assert [r.ref.dof for r in rows] == ["yaw", "pitch", "x", "x", "y", "y", "y", "z"]
    assert rows[0].observed == peak[3] and rows[0].estimated == pytest.approx(peak[3] / 2)


def test_truth_file_roundtrip(tmp_path):
    t = np.linspace(0, 1, 11)
    v = np.column_stack([t * k for k in range(1, 7)])
    s = Series6(t, Pose6.from_mm_deg(v), force=np.column_stack([t, -t, 2 * t]), p_urethra=1e3 * t,
                targets={"apex": np.column_stack([t, t, t]) * 1e-3}, meta={"scenario": "x"})
    p = write_truth(tmp_path / "truth.csv", s)
    first = p.read_text().splitlines()[:2]
    assert first[0].startswith("# {") and '"scenario": "x"' in first[0]
    assert first[1].startswith("t_s,x_mm,y_mm,z_mm,yaw_deg,pitch_deg,roll_deg,force_x_N")
    back = read_truth(p)
    np.testing.assert_allclose(back.mm_deg(), v, atol=1e-8)
    np.testing.assert_allclose(back.force, s.force, atol=1e-8)
    np.testing.assert_allclose(back.p_urethra, s.p_urethra, atol=1e-6)
    np.testing.assert_allclose(back.targets["apex"], s.targets["apex"], atol=1e-12)


def test_broken_tables(tmp_path):
    p = tmp_path / "e.csv"
    p.write_text('# {"a": 1}\nt_s,x_mm,y_mm\n0,1,2\n')
    with pytest.raises(FileFormatError, match=r"lacks column\(s\) z_mm, yaw_deg, pitch_deg, roll_deg"):
        read_estimate(p)
    p.write_text("# {not json\nt_s\n0\n")
    with pytest.raises(FileFormatError, match="line 1: metadata is not JSON"):
        read_table(p)
    p.write_text("# {}\nt_s,x_mm\n0,1\n0.1,abc\n")
    with pytest.raises(FileFormatError, match=r"line 4, column 'x_mm': 'abc' is not a number"):
        read_table(p)
    p.write_text("# {}\nt_s,x_mm\n0,1\n0.1,-2.2")  # cut inside a number: the row is dropped, said so
    with pytest.warns(UserWarning, match=r"line 4 \(byte 18, 8 bytes\) ends without a newline: a row cut short, dropped \(truncated file\)"):
        assert list(read_table(p).columns["x_mm"]) == [1.0]
    p.write_text("# {}\n")
    with pytest.raises(FileFormatError, match="no CSV header"):
        read_table(p)
