"""Sensing chain: paper budget (Sec. III-D eq. 1–2), transducer/ADC, Boyle, tare, drift, tube lag."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softphantom.errors import UserError
from softphantom.sensing.board import frame_rate_Hz, uart_load
from softphantom.sensing.budget import BudgetParams, budget, digital_span_counts, effective_bits
from softphantom.sensing.chain import (
    MPX4250D,
    MPXV7002,
    NotAtRestError,
    channel_status,
    counts_to_pa,
    default_chain,
    nominal_tare,
    pa_to_counts,
    simulate_raw,
    tare_from_window,
    to_measurement,
)
from softphantom.sensing.pneumatics import (
    boyle_dp,
    boyle_dV,
    detect_drift,
    first_order_lag,
    loss_factor,
    poiseuille_resistance,
    thermal_dp_per_K,
    tube_time_constant_s,
    tube_volume_m3,
)

P0 = 101_325.0


# ---------------------------------------------------------------- the paper's numbers
def test_budget_reproduces_paper_digits():
    assert round(tube_volume_m3(12.0, 1.2e-3) * 1e9, 1) == 13571.7
    front, back = budget(BudgetParams(paper_rounding=True))
    # 514 mm³ (front, vertical) → 14 086 mm³ → 27.4; 486 mm³ (back, horizontal) → 14 058 → 28.9
    assert (round(front.v_total_mm3), round(back.v_total_mm3)) == (14086, 14058)
    assert (front.loss_factor, back.loss_factor) == (27.4, 28.9)
    assert round(front.effective_bits, 2) == 13.32
    assert round(back.span_counts_paper, 1) == 1505.9
    assert round(front.span_counts_paper, 1) == 1588.3
    assert round(back.resolution_Pa_paper, 1) == 11.3          # worst case: 17 kPa / 1505.9


def test_budget_exact_factors_and_the_datasheet_span():
    front, back = budget(BudgetParams())
    assert round(back.loss_factor, 1) == 28.9 and round(front.loss_factor, 1) == 27.4
    # without the paper's rounding of the factors: 1504.6 / 1588.1, still 11.3 Pa
    assert round(back.span_counts_paper, 1) == 1504.6 and round(front.span_counts_paper, 1) == 1588.1
    assert round(max(back.resolution_Pa_paper, front.resolution_Pa_paper), 1) == 11.3
    # 2^13.32 is exactly 1024·√100 levels over the ADC range
    assert 2 ** effective_bits(10, 100) == pytest.approx(10240.0, rel=1e-12)
    # the "·4" is the MPXV7002's ±2 kPa; its transfer function puts ±2 kPa on 0.1…0.9·VS,
    # so the ADC's whole range is 5 kPa and the real span is 0.8 of the paper's
    assert MPXV7002.ratio(-2000.0) == pytest.approx(0.1) and MPXV7002.ratio(2000.0) == pytest.approx(0.9)
    assert MPXV7002.adc_span_Pa == pytest.approx(5000.0)
    assert back.span_counts_datasheet == pytest.approx(0.8 * back.span_counts_paper)
    # peak at the transducer: +10 kPa cavity-equivalent / 28.9 stays well inside ±2 kPa
    assert back.transducer_peak_Pa == pytest.approx(10_000 / back.loss_factor)
    assert back.transducer_use < 0.2


def test_budget_moves_the_right_way():
    base = budget(BudgetParams())[1]
    short = budget(BudgetParams(tube_length_m=3.0))[1]
    more_osr = budget(BudgetParams(osr=400))[1]
    assert short.resolution_Pa_datasheet < base.resolution_Pa_datasheet
    assert short.tube_tau_s < base.tube_tau_s
    # 4× the readings → one more bit → half the Pa per level, at a quarter of the frame rate
    assert more_osr.resolution_Pa_datasheet == pytest.approx(base.resolution_Pa_datasheet / 2)
    assert more_osr.frame_rate_Hz == pytest.approx(base.frame_rate_Hz / 4)
    # a 1 m tube would drive the transducer past its ±2 kPa at +10 kPa cavity-equivalent
    assert budget(BudgetParams(tube_length_m=1.0))[1].transducer_use > 1.0
    with pytest.raises(UserError, match="tube_length_m"):
        budget(BudgetParams(tube_length_m=-1.0))
    assert digital_span_counts(13.0, 4000, 1.0, 4000) == 2**13


def test_board_modes_and_uart():
    assert round(frame_rate_Hz(100), 1) == 19.2 and round(frame_rate_Hz(25)) == 77
    assert uart_load(34, 25) < 0.25 and uart_load(34, 5) > 1.0   # OSR ≤ 5 is UART-bound at 115200


# ---------------------------------------------------------------- transducers and ADC
@settings(max_examples=60, deadline=None)
@given(p=st.floats(-2000, 2000), osr=st.integers(1, 500))
def test_counts_pa_round_trip(p, osr):
    assert float(counts_to_pa(pa_to_counts(p, MPXV7002, osr), osr, MPXV7002)) == pytest.approx(p, abs=1e-6)
    q = p * 100 + 150_000
    assert float(counts_to_pa(pa_to_counts(q, MPX4250D, osr), osr, MPX4250D)) == pytest.approx(q, abs=1e-4)


def test_datasheet_transfer_functions():
    # MPXV7002 at VS = 5 V: 2.5 V at 0 kPa, 1 V per kPa; MPX4250D: 0.2 V at 0, 4.8125 V at 250 kPa
    assert 5 * MPXV7002.ratio(0) == pytest.approx(2.5) and 5 * MPXV7002.ratio(1000) == pytest.approx(3.5)
    assert 5 * MPX4250D.ratio(0) == pytest.approx(0.2)
    assert 5 * MPX4250D.ratio(250_000) == pytest.approx(4.8125)


def test_simulated_raw_is_unbiased_and_status_flags_rails():
    rng = np.random.default_rng(3)
    p = np.array([300.0, -150.0, 0.0, 1200.0, 40_000.0])
    raw = simulate_raw(np.broadcast_to(p, (200, 5)), 100, rng)
    est = [counts_to_pa(raw[:, i], 100, tr).mean() for i, tr in enumerate((MPXV7002,) * 4 + (MPX4250D,))]
    assert np.allclose(est[:4], p[:4], atol=2.0) and abs(est[4] - p[4]) < 60
    assert channel_status(raw[0], 100, default_chain()) == "ok"
    ok = raw[0].copy()
    bad = ok.copy(); bad[3] = 0                       # a disconnected channel pulled to ground
    assert channel_status(bad, 100, default_chain()) == "rail:back_xneg"
    bad = ok.copy(); bad[1] = 1023 * 100
    assert channel_status(bad, 100, default_chain()) == "rail:front_zneg"
    bad = ok.copy(); bad[2] = int(pa_to_counts(2450.0, MPXV7002, 100))
    assert channel_status(bad, 100, default_chain()) == "range:back_xpos"
    bad = ok.copy(); bad[4] = 1024 * 100
    assert channel_status(bad, 100, default_chain()) == "invalid:urethra"


# ---------------------------------------------------------------- Boyle
@settings(max_examples=60, deadline=None)
@given(dp=st.floats(-2000, 2000), vt=st.floats(1e-7, 1e-4))
def test_boyle_round_trip_and_small_signal(dp, vt):
    dv = float(boyle_dV(dp, vt, P0))
    assert float(boyle_dp(dv, vt, P0)) == pytest.approx(dp, abs=1e-6)
    # first order: ΔV ≈ −V_T·ΔP/P0, error of order (ΔP/P0)²
    assert dv == pytest.approx(-vt * dp / P0, abs=vt * 2 * (dp / P0) ** 2 + 1e-18)


def test_boyle_equals_paper_eq7_scaled_by_loss_factor():
    vc, vt = 486e-9, 486e-9 + tube_volume_m3(12, 1.2e-3)
    dp = 250.0
    eq7 = (P0 * vc) / (P0 + dp) - vc                 # paper eq. (7) with V0 = V_cavity
    assert float(boyle_dV(dp, vt, P0)) == pytest.approx(eq7 * loss_factor(vc, vt - vc), rel=1e-12)
    with pytest.raises(UserError, match="dp"):
        boyle_dV(np.array([0.0, np.nan]), vt, P0)


def test_thermal_drift_is_about_340_Pa_per_K():
    assert thermal_dp_per_K(P0, 293.15) == pytest.approx(345.6, abs=0.1)
    assert thermal_dp_per_K(100_000, 298.0) == pytest.approx(340, rel=0.02)


# ---------------------------------------------------------------- tube lag
def _rc_ladder_mean_delay(length, d, vc, vd, n=400):
    """Mean delay at the far end of a discretised RC line (independent of the closed form)."""
    r = poiseuille_resistance(length, d) / n
    c_seg = tube_volume_m3(length, d) / P0 / n
    cap = np.full(n + 1, c_seg)
    cap[0], cap[-1] = c_seg / 2 + vc / P0, c_seg / 2 + vd / P0
    g = np.zeros((n + 1, n + 1))
    for i in range(n):
        g[i, i] += 1 / r; g[i + 1, i + 1] += 1 / r; g[i, i + 1] -= 1 / r; g[i + 1, i] -= 1 / r
    # step: charge Q = 1 placed in the cavity; x = p − p_f obeys C x' = −G x; ∫x dt = u, G u = C x(0)
    p_f = 1 / cap.sum()
    x0 = -p_f * np.ones(n + 1); x0[0] += 1 / cap[0]
    u = np.linalg.lstsq(g, cap * x0, rcond=None)[0]
    u -= (cap @ u) / cap.sum()                       # the deviation's total charge is zero
    return -u[-1] / p_f


@pytest.mark.parametrize("length,d,vd", [(12.0, 1.2e-3, 0.0), (5.0, 1.0e-3, 200e-9), (2.0, 2.0e-3, 0.0)])
def test_tube_time_constant_matches_rc_ladder(length, d, vd):
    tau = tube_time_constant_s(length, d, 486e-9, P0, v_dead_m3=vd)
    assert tau == pytest.approx(_rc_ladder_mean_delay(length, d, 486e-9, vd), rel=2e-3)


def test_tube_time_constant_paper_tube_and_bounds():
    tau = tube_time_constant_s(12.0, 1.2e-3, 486e-9)
    lumped = tube_time_constant_s(12.0, 1.2e-3, 486e-9, method="lumped")
    assert 0.1 <= tau <= 0.11 and 0.55 <= lumped <= 0.6
    # τ ∝ L² (R ∝ L, C ∝ L) and ∝ 1/d² (R ∝ 1/d⁴, C ∝ d²) while the tube dominates the volume
    assert tube_time_constant_s(24.0, 1.2e-3, 1e-12) / tube_time_constant_s(12.0, 1.2e-3, 1e-12) == pytest.approx(4, rel=1e-3)
    assert tube_time_constant_s(12.0, 2.4e-3, 1e-12) / tube_time_constant_s(12.0, 1.2e-3, 1e-12) == pytest.approx(0.25, rel=1e-3)


def test_first_order_lag_step_is_exact():
    dt, tau = 0.052, 0.102
    y = first_order_lag(np.ones(50), dt, tau, y0=0.0)
    t = dt * np.arange(1, 51)
    assert np.allclose(y, 1 - np.exp(-t / tau), atol=1e-12)
    x = np.ones((10, 4)) * [1, 2, 3, 4]
    assert np.allclose(first_order_lag(x, dt, tau), x)     # at rest stays at rest


# ---------------------------------------------------------------- drift
def test_drift_detector():
    rng = np.random.default_rng(5)
    t = np.arange(0, 60, 0.052)
    noise = rng.normal(0, 3, (t.size, 4))
    ramp = thermal_dp_per_K() * 0.5 / 60 * t                       # +0.5 K/min
    rep = detect_drift(t, noise + ramp[:, None])
    assert rep.drifting and rep.equivalent_K_per_min == pytest.approx(0.5, abs=0.1)
    # pushes that come back, opposite on opposite arms: no drift
    push = 300 * np.exp(-((t[:, None] - [10, 25, 40, 55]) ** 2) / 2.0) * [1, -1, 1, -1]
    assert not detect_drift(t, noise + push).drifting
    assert not detect_drift(t, noise).drifting


# ---------------------------------------------------------------- tare and measurement
def test_tare_accepts_rest_and_refuses_a_push():
    chain = default_chain()
    rng = np.random.default_rng(11)
    p = np.zeros((40, 5)); p[:, 4] = 20_000.0
    t = np.arange(40) * 0.052
    tare = tare_from_window(simulate_raw(p, 100, rng), 100, t, chain, p0_Pa=99_000.0)
    assert tare.p0_Pa == 99_000.0 and tare.n_samples == 40
    assert tare.offset_codes[:4] == pytest.approx(np.full(4, 511.5), abs=0.05)
    m = to_measurement(1.0, 1, 1.0, simulate_raw(np.array([100.0, 0, 0, 0, 20_000]), 100, rng), 100, chain, tare)
    assert m.dp[0] == pytest.approx(100.0, abs=3) and abs(m.p_urethra) < 300
    assert m.dV[0] == pytest.approx(float(boyle_dV(m.dp[0], chain.v_total_m3[0], 99_000.0)))
    pushed = p.copy(); pushed[:, 2] = np.linspace(0, 400, 40)          # a push during the window
    with pytest.raises(NotAtRestError, match="back_xpos"):
        tare_from_window(simulate_raw(pushed, 100, rng), 100, t, chain)
    railed = simulate_raw(p, 100, rng); railed[5, 1] = 0
    with pytest.raises(NotAtRestError, match="frame 5 is rail:front_zneg"):
        tare_from_window(railed, 100, t, chain)
    with pytest.raises(NotAtRestError, match="need at least"):
        tare_from_window(railed[:2], 100, t[:2], chain)


def test_measurement_status_and_nominal_tare():
    chain = default_chain()
    tare = nominal_tare(chain)
    raw = np.array([51150, 51150, 0, 51150, 4046])
    m = to_measurement(0.0, 3, 0.0, raw, 100, chain, tare)
    assert m.status == "rail:back_xpos" and m.dp.shape == (4,) and m.dV.shape == (4,)
    assert math.isfinite(m.dV[2])
    assert to_measurement(0.0, 3, 0.0, raw * 0 + 51150, 100, chain, tare).dp == pytest.approx(np.zeros(4))
    with pytest.raises(UserError, match="raw"):
        to_measurement(0.0, 3, 0.0, raw[:4], 100, chain, tare)


# ---------------------------------------------------------------- CLI
def test_cli_budget_writes_table_csv_and_png(tmp_path, capsys):
    from softphantom.cli import main

    assert main(["sensing", "budget", "--paper-rounding", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "1505.9" in out and "1588.3" in out and "11.29 Pa (paper eq. 2)" in out
    rows = list(csv.DictReader(open(tmp_path / "budget.csv")))
    assert [round(float(r["v_total_mm3"])) for r in rows] == [14086, 14058]
    png = (tmp_path / "budget.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert main(["sensing", "budget", "--tube-length-m", "-2"]) == 2
    assert "tube_length_m" in capsys.readouterr().err
