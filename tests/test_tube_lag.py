"""The tube as a distributed RC line, its simulation, the lag compensation and the τ fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from softphantom.errors import UserError
from softphantom.sensing.bench import BenchConfig
from softphantom.sensing.pneumatics import poiseuille_resistance, tube_time_constant_s, tube_volume_m3
from softphantom.sensing.tube import TubeLine

P0 = 101_325.0
PAPER = (12.0, 1.2e-3, 486e-9)


def ladder400_step(length, d, vc, t, n=400, vd=0.0):
    """Far-end response of a 400-segment RC ladder to a unit step of the equilibrium pressure
    (charge C_tot put into the cavity at t = 0), by the matrix exponential (independent of the
    modal code under test)."""
    r = poiseuille_resistance(length, d) / n
    c = tube_volume_m3(length, d) / P0 / n
    cap = np.full(n + 1, c)
    cap[0], cap[-1] = c / 2 + vc / P0, c / 2 + vd / P0
    g = np.zeros((n + 1, n + 1))
    i = np.arange(n)
    g[i, i] += 1 / r; g[i + 1, i + 1] += 1 / r; g[i, i + 1] -= 1 / r; g[i + 1, i] -= 1 / r
    M = -g / cap[:, None]
    p0 = np.zeros(n + 1)
    p0[0] = cap.sum() / cap[0]
    dt = t[1] - t[0]
    E = expm(M * dt)
    out, p = [], p0
    for _ in t:
        out.append(p[-1])
        p = E @ p
    return np.array(out)


def test_closed_form_transfer_and_cascade_match_the_ladder():
    line = TubeLine.of(*PAPER)
    assert line.elmore_s == pytest.approx(tube_time_constant_s(*PAPER), rel=1e-12)
    # H(s) of the closed form against the 400-segment ladder solved in the frequency domain
    n = 400
    cap, lap = line.ladder(n)
    for f in (0.5, 3.0, 12.0):
        s = 2j * np.pi * f
        rhs = np.zeros(n + 1)
        rhs[0] = 1.0
        p = np.linalg.solve(s * np.diag(cap) + lap, rhs)
        assert line.transfer(s) == pytest.approx(p[-1] * s * line.c_total, rel=2e-4)
    # the cascade's time constants sum to the Elmore delay (the tail ∝ Σ 1/k²)
    tau = line.stages(300)
    assert tau.sum() == pytest.approx(line.elmore_s, rel=3e-3)
    assert np.all(np.diff(tau) < 0)
    assert line.reduced(2).sum() == pytest.approx(line.elmore_s, rel=1e-12)


def test_virtual_ladder_step_within_a_tenth_of_a_percent_of_the_400_segment_ladder():
    line = TubeLine.of(*PAPER)
    dt = 1e-3
    t = np.arange(0, 0.6, dt)
    ref = ladder400_step(*PAPER, t)
    x = np.ones(len(t) + 1)
    x[0] = 0.0  # at rest, then the equilibrium pressure ramps to 1 within the first 1 ms step
    got = line.ladder_response(x, dt)[1:]
    # got[k] is at (k + 1)·dt after an input ramp centred on dt/2: the reference at k·dt + dt/2
    ref_half = np.interp(t + dt / 2, t, ref)
    assert np.max(np.abs(got - ref_half)) < 1e-3
    assert got[-1] == pytest.approx(1.0, abs=1e-3)


def _push(t, t0=1.0, rise=1.2, hold=0.8, fall=1.0):
    s = np.clip((t - t0) / rise, 0, 1)
    f = np.clip((t - t0 - rise - hold) / fall, 0, 1)
    return (0.5 - 0.5 * np.cos(np.pi * s)) * (1 - (0.5 - 0.5 * np.cos(np.pi * f)))


def _compensate(comp, t, y):
    return np.array([comp.filter(tk, np.array([yk]))[0] for tk, yk in zip(t, y)])


def _one_arm():
    from softphantom.estimation.lag import LagCompensator, TubeModel

    line = TubeLine.of(*PAPER)
    red = line.reduced(2)
    return LagCompensator(TubeModel((float(red.sum()),), (tuple(red),)), [1.0], P0), line


def test_compensation_removes_most_of_the_lag_of_a_push_through_the_400_segment_ladder():
    comp, line = _one_arm()
    dtg, fr = 1e-3, 1 / 19.2
    tg = np.arange(0, 6.0, dtg)
    p_eq = 300.0 * _push(tg)
    step = ladder400_step(*PAPER, np.arange(0, 1.0, dtg))
    impulse = np.diff(np.append(0.0, step))
    p_d = np.convolve(p_eq, impulse)[:len(tg)]  # the line, independent of the compensator's model
    tf = np.arange(0.013, 5.9, fr)
    y = np.interp(tf, tg, p_d) + np.random.default_rng(0).normal(0, 0.3, len(tf))
    truth = np.interp(tf, tg, p_eq)
    before = np.sqrt(np.mean((y - truth) ** 2))
    after = np.sqrt(np.mean((_compensate(comp, tf, y) - truth) ** 2))
    assert after < 0.3 * before


def _through_the_400_segment_ladder(p_eq_of_t, duration_s, noise_Pa=0.3, seed=0):
    """(frame times, transducer readings, cavity pressure) of a 19.2 Hz board behind the paper's
    tube, the line simulated by the 400-segment ladder (not the compensator's model)."""
    dtg, fr = 1e-3, 1 / 19.2
    tg = np.arange(0, duration_s, dtg)
    p_eq = p_eq_of_t(tg)
    step = ladder400_step(*PAPER, np.arange(0, 1.0, dtg))
    p_d = np.convolve(p_eq, np.diff(np.append(0.0, step)))[:len(tg)]
    tf = np.arange(0.5 * fr, duration_s - 0.1, fr)
    y = np.interp(tf, tg, p_d) + np.random.default_rng(seed).normal(0, noise_Pa, len(tf))
    return tf, y, np.interp(tf, tg, p_eq)


def _pushes(t):
    """Three pushes as ``push-on-centre`` makes them (cosine ramps, 1.0–1.2 s), 100 Pa at most."""
    return 100.0 * (_push(t, 2.0, 1.2, 0.8, 1.0) - 0.6 * _push(t, 5.5, 1.0, 0.6, 1.2)
                    + 0.8 * _push(t, 9.0, 1.2, 0.8, 1.2))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compensated_pushes_follow_the_cavity_without_overshoot(seed):
    # the cavity pressure of now, from four arms' readings through the distributed line: within
    # 1.5 % RMS of the peak over the pushes, and no more than 4.5 % off on the holds and after each
    # push (a quiet filter left behind by the ramps and switched back in would overshoot there by 6-7 %)
    from softphantom.estimation.lag import LagCompensator, TubeModel

    red = TubeLine.of(*PAPER).reduced(2)
    comp = LagCompensator(TubeModel((float(red.sum()),) * 4, (tuple(red),) * 4), [1.0] * 4, P0)
    runs = [_through_the_400_segment_ladder(_pushes, 13.0, seed=10 * seed + a) for a in range(4)]
    tf, truth = runs[0][0], runs[0][2]
    y = np.column_stack([r[1] for r in runs])
    err = np.array([comp.filter(tk, yk) for tk, yk in zip(tf, y)]) - truth[:, None]
    assert np.sqrt(np.mean(err[tf > 1.5] ** 2)) < 1.5
    settled = ((tf > 3.2) & (tf < 4.0)) | ((tf > 4.2) & (tf < 5.4)) | ((tf > 7.1) & (tf < 7.8)) | \
        ((tf > 8.3) & (tf < 8.9)) | ((tf > 10.2) & (tf < 11.0)) | (tf > 12.2)
    assert np.max(np.abs(err[settled])) < 4.5


def test_the_half_point_of_a_step_comes_within_30_ms():
    # a 100 Pa step of the cavity pressure at 6.0 s (10 ms rise; the first frame after it 37 ms
    # after its middle): the compensated reading passes 50 Pa within 30 ms of the cavity, the
    # transducer's own reading 70-80 ms after
    comp, _ = _one_arm()
    tf, y, truth = _through_the_400_segment_ladder(lambda t: 100.0 * _push(t, 6.0, 0.01, 2.5, 0.01), 9.0)
    out = _compensate(comp, tf, y)

    def half(v):
        i = int(np.argmax((tf > 5.9) & (v >= 50.0)))
        return tf[i - 1] + (50.0 - v[i - 1]) / (v[i] - v[i - 1]) * (tf[i] - tf[i - 1])

    assert half(y) - 6.005 > 0.06
    assert half(out) - 6.005 < 0.030


@pytest.mark.parametrize("arms", [4, 1])
def test_noise_at_rest_is_the_quiet_levels_and_a_constant_stays_constant(arms):
    # white noise at rest comes out × the quiet level's noise gain, plus what the chance rises of
    # the level add: within 10 % of it with the BIP's four arms, under 1.5 × with a single arm
    from softphantom.estimation.lag import DEFAULT_NOISE_GAIN, LagCompensator, TubeModel

    red = TubeLine.of(*PAPER).reduced(2)
    comp = LagCompensator(TubeModel((float(red.sum()),) * arms, (tuple(red),) * arms), [1.0] * arms, P0)
    fr = 1 / 19.2
    t = np.arange(0, 200.0, fr)
    y = np.random.default_rng(1).normal(0, 1.0, (len(t), arms))
    out = np.array([comp.filter(tk, yk) for tk, yk in zip(t, y)])
    assert comp.noise_gain(fr)[0] == pytest.approx(DEFAULT_NOISE_GAIN, rel=0.01)
    ratio = np.std(out[100:]) / np.std(y[100:])
    if arms == 4:
        assert ratio == pytest.approx(DEFAULT_NOISE_GAIN, rel=0.1)
    else:
        assert DEFAULT_NOISE_GAIN * 0.9 < ratio < 1.5
    comp.reset()
    assert np.allclose([comp.filter(tk, np.full(arms, 42.0)) for tk in t[:200]], 42.0)


def test_gap_in_the_board_clock_restarts_the_filter():
    comp, _ = _one_arm()
    comp.filter(0.0, np.array([1.0]))
    comp.filter(0.05, np.array([1.0]))
    assert comp.filter(5.0, np.array([7.0]))[0] == 7.0  # after the gap: at rest at the reading
    assert comp.restarts == 1


def test_lag_compensation_default_threshold_missing_tube_and_unphysical_tau():
    from softphantom.estimation.lag import lag_compensation

    comp, meta, warn = lag_compensation(None, BenchConfig())
    assert comp is not None and meta["lag_compensation"] == "model" and warn is None
    assert meta["tube_tau_ms"][3] == pytest.approx(tube_time_constant_s(*PAPER) * 1e3, rel=1e-3)
    comp, meta, _ = lag_compensation(None, BenchConfig(tube_length_m=3.0))  # τ ≈ 7 ms: off by default
    assert comp is None and meta["lag_compensation"] == "off"
    assert lag_compensation("model", BenchConfig(tube_length_m=3.0))[0] is not None
    assert lag_compensation("off", BenchConfig())[0] is None
    comp, meta, warn = lag_compensation(None, BenchConfig(), tube_missing="tube_length_m", source="replay:r.csv")
    assert comp is None and warn.startswith("warning: lag compensation off: replay:r.csv has no tube_length_m")
    with pytest.raises(UserError, match=r"tube τ of front_zpos: 100 ms \(calibrated\) is outside .* 1.2 m × 1.2 mm"):
        lag_compensation(None, BenchConfig(tube_length_m=1.2, tube_tau_s=(0.1,) * 4))
    with pytest.raises(UserError, match=r"beyond any bench's"):
        lag_compensation(None, BenchConfig(tube_length_m=120.0))
    with pytest.raises(UserError, match="--lag-compensation"):
        lag_compensation("kalman", BenchConfig())


def test_bench_keeps_a_calibrated_tau_in_its_metadata():
    b = BenchConfig(tube_tau_s=(0.11, 0.11, 0.1, 0.1))
    assert BenchConfig.from_meta({"bench": b.to_meta()}).tube_tau_s == pytest.approx(b.tube_tau_s)
    with pytest.raises(UserError, match="tube time constants"):
        BenchConfig(tube_tau_s=(0.1,))


def test_replay_without_tube_settings_names_the_missing_one(tmp_path):
    from softphantom.sensing.bench import open_replay
    from softphantom.sensing.recording import read_recording

    src = tmp_path / "r.csv"
    _write_min_recording(src, bench={"arm_cavity_mm3": [514, 514, 486, 486], "tube_id_mm": 1.2})
    rec = read_recording(src)
    assert "tube_length_m" not in rec.meta["bench"]
    opened = open_replay(str(src))
    assert opened.meta["tube_missing"] == "tube_length_m"
    opened.source.close()
    opened = open_replay(str(src), options={"tube_length_m": 12.0})
    assert "tube_missing" not in opened.meta
    opened.source.close()


def _write_min_recording(path, bench):
    """A short recording at rest whose metadata ``bench`` entry is ``bench``."""
    import json

    from softphantom.sensing import Measurement
    from softphantom.sensing.chain import nominal_tare
    from softphantom.sensing.recording import Recorder

    b = BenchConfig()
    chain = b.chain()
    tare = nominal_tare(chain, P0)
    raw = np.round((np.asarray(tare.offset_codes) + 0.5) * 25).astype(int)
    with Recorder(path, {"bench": b.to_meta(), "tare": tare.to_dict(), "chain": chain.summary()},
                  layout=chain.layout) as rec:
        for k in range(10):
            rec.write(Measurement(k * 0.013, k, k * 0.013, raw, 25, np.zeros(4), np.zeros(4), 0.0))
    lines = path.read_text().splitlines(keepends=True)
    meta = json.loads(lines[0][2:])
    meta["bench"] = bench
    path.write_text("# " + json.dumps(meta) + "\n" + "".join(lines[1:]))


def test_calibrate_fits_each_tubes_tau_from_a_known_load_step():
    from softphantom.calibration.session import Session
    from softphantom.calibration.tube import fit_tube_tau

    vc = np.array([514e-9, 514e-9, 486e-9, 486e-9])
    true_factor = np.array([1.0, 1.2, 0.8, 1.0])  # the arms' real delays / the stated tube's
    fr = 1 / 19.2
    t = np.arange(0, 12.0, fr)
    force = np.zeros((len(t), 3))
    force[t >= 4.0, 1] = 2.0      # a 200 g weight hung on, then off
    force[t >= 8.0, 1] = 0.0
    rng = np.random.default_rng(3)
    dp = np.zeros((len(t), 4))
    for i in range(4):
        line = TubeLine.of(12.0, 1.2e-3, vc[i])
        line = TubeLine(line.r * true_factor[i], line.c_cavity, line.c_tube, line.c_dead)
        dp[:, i] = (80.0 - 20 * i) * line.ladder_response(force[:, 1], fr, 200) + rng.normal(0, 0.3, len(t))
    se = Session("s1", t, dp, np.zeros(len(t)), t, np.zeros((len(t), 6)), np.zeros(3), P0, 12.0, 1.2e-3, vc,
                 known_t=t, known_force=force)
    fit = fit_tube_tau(se)
    assert fit.tau_s / fit.nominal_s == pytest.approx(true_factor, rel=0.05)
    assert np.all(fit.sd_s < 0.05 * fit.tau_s)
    assert fit_tube_tau(Session("s2", t, dp, np.zeros(len(t)), t, np.zeros((len(t), 6)), np.zeros(3), P0, 12.0,
                                1.2e-3, vc)) is None  # without known loads: nothing to fit


def test_estimate_refuses_an_unknown_lag_compensation_in_one_line(tmp_path, capsys):
    from softphantom.cli import main

    rc = main(["estimate", "--model", str(tmp_path), "--source", "virtual:needle-insertion", "--out",
               str(tmp_path / "e.csv"), "--lag-compensation", "kalman"])
    err = capsys.readouterr().err
    assert rc == 2 and "--lag-compensation: expected off or model, got 'kalman'" in err
    assert not (tmp_path / "e.csv").exists()
