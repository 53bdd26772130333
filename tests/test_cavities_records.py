"""Internal cavities after the estimator: the board reads a pressure channel per internal cavity
(an MPX4250D each, after the arms'), the records name them (``raw_<cavity>``, ``p_<cavity>_kPa``),
the virtual phantom inflates the one a scenario names, and estimate, evaluate and live take any
M >= 0. A two-cavity phantom (the urethra and a tumour balloon) and one without any run end to end
on the coarse 12 mm P1 models of tests/test_cavities.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softphantom.errors import UserError

from test_cavities import _model

PUSH_N = (0.3, 2.0, -0.2)
P_TUMOUR_KPA = 20.0
# a push, then the tumour balloon inflated: the phantom's force is zero while it is
TWO = {"name": "push-and-tumour", "duration_s": 5.0, "rest_s": 1.0,
       "push": [{"point": "on-centre", "start_s": 1.1, "rise_s": 0.6, "hold_s": 0.5, "fall_s": 0.6,
                 "force_N": list(PUSH_N)}],
       "inflate": [{"cavity": "tumour", "p_kPa": P_TUMOUR_KPA, "start_s": 2.9, "rise_s": 0.6, "hold_s": 0.7,
                    "fall_s": 0.6}]}
PUSH_ONLY = {"name": "push", "duration_s": 3.0, "rest_s": 1.0, "push": TWO["push"]}
HOLD_S = (3.65, 4.15)  # the tumour at its peak pressure
PUSH_HOLD_S = (1.85, 2.15)


@pytest.fixture(scope="module")
def models():
    # test_cavities' cache: meshed once when both files run in one process
    return {"two": _model("two"), "none": _model("none")}


def _write_scenario(path, d: dict):
    import tomli_w

    path.write_text(tomli_w.dumps(d))
    return path


def _run_estimate_evaluate(tmp_path, capsys, model, scenario: dict, board: str):
    """``virtual run`` (its summary on screen and its files checked) → ``estimate --estimator
    refresh`` from its recording → ``evaluate``: the run directory, the estimate file and the evaluation.
    ``board``: the board's OSR and frame rate as printed (6 channels a frame at OSR 200: 8.0 Hz, 4: 12.0 Hz)."""
    from softphantom.cli import main
    from softphantom.design import save_model
    from softphantom.evaluation import evaluate, read_estimate, read_truth

    save_model(model, tmp_path / "model")
    sc = _write_scenario(tmp_path / "sc.toml", scenario)
    run = tmp_path / "run"
    assert main(["virtual", "run", "--scenario", str(sc), "--model", str(tmp_path / "model"), "--out", str(run),
                 "--truth-order", "1", "--truth-mesh-scale", "1", "--osr", "200"]) == 0
    # its summary on screen and in virtual.json, and the recording's JSON header line
    text = capsys.readouterr().out
    assert "truth:" in text and f"board: {board}," in text and "tracker: 120 Hz" in text
    meta = json.loads((run / "virtual.json").read_text())
    assert meta["board"]["osr"] == 200 and meta["truth"]["events"][0]["force_N"] == scenario["push"][0]["force_N"]
    assert meta["truth"]["truth_mesh"]["element_order"] == 1 and "P1" in text
    assert (run / "recording.csv").read_text().startswith("# {")
    est = tmp_path / "estimate.csv"
    assert main(["estimate", "--model", str(tmp_path / "model"), "--source", f"replay:{run / 'recording.csv'}",
                 "--out", str(est), "--estimator", "refresh"]) == 0
    assert main(["evaluate", "--estimate", str(est), "--truth", str(run / "truth.csv"),
                 "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "report.html").is_file()
    return run, est, evaluate(read_truth(run / "truth.csv"), read_estimate(est))


def _header(path) -> tuple[dict, list[str]]:
    lines = path.read_text().splitlines()
    return json.loads(lines[0][2:]), lines[1].split(",")


@pytest.mark.slow
def test_two_cavities_end_to_end(tmp_path, capsys, models):
    from softphantom.evaluation.files import read_table
    from softphantom.records.names import estimate_columns, measurement_columns
    from softphantom.sensing.chain import MPX4250D
    from softphantom.sensing.recording import read_recording

    model = models["two"]
    arms = model.design.arm_names
    run, est, ev = _run_estimate_evaluate(tmp_path, capsys, model, TWO, "OSR 200, 8.0 Hz")
    # the board: the four arms, then the urethra's and the tumour's transducers
    meta, cols = _header(run / "recording.csv")
    assert tuple(cols) == measurement_columns(model.layout)
    assert cols[4:10] == [*(f"raw_{a}" for a in arms), "raw_urethra", "raw_tumour"]
    assert meta["channels"]["actuated"] == ["urethra", "tumour"]
    assert meta["chain"]["transducers"] == ["MPXV7002"] * 4 + ["MPX4250D"] * 2
    _, truth_cols = _header(run / "truth.csv")
    assert {"p_urethra_kPa", "p_tumour_kPa", "dV_tumour_mm3"} <= set(truth_cols)
    summary = json.loads((run / "virtual.json").read_text())["truth"]["events"]
    assert summary[1]["cavity"] == "tumour" and summary[1]["p_kPa"] == P_TUMOUR_KPA
    # the recorded tumour pressure is the scenario's: tared at rest, within 2 codes of the MPX4250D
    # (0.265 kPa a code; the mean of 200 readings a frame), the urethra's stays at 0
    rec = read_recording(run / "recording.csv")
    assert rec.cavity_names == ("urethra", "tumour") and rec.pressures.shape == (len(rec), 2)
    code_kPa = 1.0 / (1024 * MPX4250D.k1_per_kPa)
    hold = (rec.t > HOLD_S[0]) & (rec.t < HOLD_S[1])
    push = (rec.t > PUSH_HOLD_S[0]) & (rec.t < PUSH_HOLD_S[1])
    assert np.abs(rec.pressures[hold, 1] / 1e3 - P_TUMOUR_KPA).max() < 2 * code_kPa
    assert np.abs(rec.pressures[push | hold, 0]).max() / 1e3 < 2 * code_kPa
    assert np.abs(rec.pressures[push, 1]).max() / 1e3 < 2 * code_kPa
    assert np.isnan(rec.p_urethra).sum() == 0 and np.array_equal(rec.p_urethra, rec.pressures[:, 0])
    # the estimate file: a pressure column per cavity after the force, the measured pressures
    tab = read_table(est).columns
    assert list(tab) == estimate_columns(list(model.targets), model.layout)
    sel = (tab["t_s"] > HOLD_S[0]) & (tab["t_s"] < HOLD_S[1])
    assert np.abs(tab["p_tumour_kPa"][sel] - P_TUMOUR_KPA).max() < 2 * code_kPa
    # the force, through the noisy chain (the truth on the estimator's own mesh). The
    # tumour's 20 kPa moves the arm cavities as a push would; taken as a known load it leaves
    # the force at zero while it is inflated (the bound: 10 % of the 2 N push, the issue's |F| goal)
    force = {f.name: f for f in ev.force}
    assert force["|force|"].rmse < 0.1 * np.linalg.norm(PUSH_N), force["|force|"].rmse
    f_est = np.column_stack([tab[f"force_{a}_N"] for a in "xyz"])
    assert np.linalg.norm(f_est[sel], axis=1).max() < 0.1 * np.linalg.norm(PUSH_N)
    # live over the estimate file (the estimator ran above): the session recording's /estimate
    # names both cavities; the page is told them (its pressure plot)
    from softphantom.cli import main
    from softphantom.sources import open_source
    from softphantom.stream.recording import read_recording as read_mcap
    from softphantom.viz.live import LiveConfig, LiveSession

    mcap = tmp_path / "live.mcap"
    assert main(["live", "--source", f"replay:{est}", "--model", str(tmp_path / "model"), "--speed", "0",
                 "--no-stream", "--http-port", "0", "--record", str(mcap)]) == 0
    r = read_mcap(mcap)
    assert r.cavity_names == ("urethra", "tumour") and json.loads(r.metadata["channels"])["actuated"] == ["urethra", "tumour"]
    assert len(r.estimates) == len(tab["t_s"])
    assert [k for k in r.estimates[0] if k.startswith("p_")] == ["p_urethra_kPa", "p_tumour_kPa"]
    held = [e for e in r.estimates if HOLD_S[0] < e["t_s"] < HOLD_S[1]]
    assert held and all(abs(e["p_tumour_kPa"] - P_TUMOUR_KPA) < 2 * code_kPa for e in held)
    rp = open_source(f"replay:{est}", model=tmp_path / "model", speed=0).source
    assert rp.cavity_names == ("urethra", "tumour")
    with LiveSession(rp, LiveConfig(http_port=0, stream_port=None)) as s:
        assert s.state_json()["cavities"] == ["urethra", "tumour"]


@pytest.mark.slow
def test_no_internal_cavity_records_arms_only_and_estimates(tmp_path, capsys, models):
    from softphantom.evaluation.files import read_table
    from softphantom.records.names import estimate_columns, measurement_columns

    model = models["none"]
    arms = model.design.arm_names
    run, est, ev = _run_estimate_evaluate(tmp_path, capsys, model, PUSH_ONLY, "OSR 200, 12.0 Hz")
    meta, cols = _header(run / "recording.csv")
    assert tuple(cols) == measurement_columns(model.layout) and not [c for c in cols if c.startswith("p_")]
    assert meta["channels"]["actuated"] == [] and meta["chain"]["transducers"] == ["MPXV7002"] * 4
    _, truth_cols = _header(run / "truth.csv")
    assert not [c for c in truth_cols if c.startswith("p_") and c.endswith("_kPa")]
    assert list(read_table(est).columns) == estimate_columns(list(model.targets), model.layout)
    force = {f.name: f for f in ev.force}
    assert force["|force|"].rmse < 0.1 * np.linalg.norm(PUSH_N), force["|force|"].rmse


def test_scenario_cavity_refusals(models):
    from softphantom.virtual.scenario import ScenarioError, scenario_from_dict
    from softphantom.virtual.truth import solve_truth

    two, none = models["two"], models["none"]
    unnamed = {**TWO, "inflate": [{k: v for k, v in TWO["inflate"][0].items() if k != "cavity"}]}
    with pytest.raises(ScenarioError, match=r"^s\.toml: inflate\.cavity: missing; this model has several internal "
                                            r"cavities \(urethra, tumour\): name one$"):
        solve_truth(scenario_from_dict(unnamed, "s.toml"), two)
    bad = {**TWO, "inflate": [{**TWO["inflate"][0], "cavity": "bladder"}]}
    with pytest.raises(ScenarioError, match=r"^s\.toml: inflate\.cavity bladder: not an internal cavity of this "
                                            r"model \(urethra, tumour\)$"):
        solve_truth(scenario_from_dict(bad, "s.toml"), two)
    with pytest.raises(ScenarioError, match=r"^s\.toml: inflate\.cavity: missing; this model has no internal "
                                            r"cavity to inflate$"):
        solve_truth(scenario_from_dict(unnamed, "s.toml"), none)
    # the BIP's keys are synonyms; the design's only cavity is the default
    old = scenario_from_dict({**PUSH_ONLY, "push": [], "inflate": [
        {"p_urethra_kPa": 30.0, "max_p_urethra_kPa": 40.0, "start_s": 1.2, "rise_s": 0.8}]}, "o.toml")
    assert old.events[0].p_kPa == 30.0 and old.events[0].max_p_kPa == 40.0
    assert old.check_cavities(["channel"]).events[0].cavity == "channel"
    for keys, match in (({"p_kPa": 30.0, "p_urethra_kPa": 30.0}, "give p_kPa or its synonym p_urethra_kPa, not both"),
                        ({"p_kPa": 50.0, "max_p_kPa": 40.0}, "p_kPa = 50 kPa is above max_p_kPa 40")):
        with pytest.raises(ScenarioError, match=match) as e:
            scenario_from_dict({**PUSH_ONLY, "push": [], "inflate": [{"start_s": 2, "rise_s": 1, **keys}]}, "o.toml")
        assert "\n" not in str(e.value)


def test_board_channels_and_records_per_cavity(models):
    """The bench, chain, measurement, recording row and estimate message of a two-cavity and a
    cavity-free design; the BIP's unchanged."""
    from softphantom.records import Estimate, measurement_to_message, message_to_estimate
    from softphantom.records.estimate import estimate_to_message, marker_estimate
    from softphantom.records.measurement import SourceEvent
    from softphantom.sensing.bench import BenchConfig
    from softphantom.sensing.chain import nominal_tare, pa_to_counts, to_measurement

    two = BenchConfig.from_model(models["two"])
    chain = two.chain()
    assert chain.names == (*models["two"].design.arm_names, "urethra", "tumour") and chain.n_channels == 6
    assert chain.cavity_names == ("urethra", "tumour") and [t.name for t in chain.transducers[4:]] == ["MPX4250D"] * 2
    assert BenchConfig.from_meta({"bench": two.to_meta(), **two.layout.to_meta()}).cavity_names == ("urethra", "tumour")
    none = BenchConfig.from_model(models["none"])
    assert none.chain().n_channels == 4 and none.layout.actuated == ()
    # 30 kPa on the tumour's transducer, nothing elsewhere
    raw = np.array([pa_to_counts(0.0, t, 100) for t in chain.transducers])
    raw[5] = pa_to_counts(30e3, chain.transducers[5], 100)
    m = to_measurement(1.0, 1, 1.0, np.round(raw).astype(int), 100, chain, nominal_tare(chain))
    assert m.pressures_Pa["tumour"] == pytest.approx(30e3, abs=150) and abs(m.p_urethra) < 150
    msg = measurement_to_message(m, chain.layout)
    assert list(msg)[-3:] == ["p_urethra_kPa", "p_tumour_kPa", "status"] and "raw_tumour" in msg
    # an estimate of a two-cavity model: its message and file row name both, and read back
    e = Estimate(1.0, np.array([0.0, 1.0, 0.0]), 100.0, marker_estimate(SourceEvent(0, "x"), [], chain.layout).pose,
                 {}, np.zeros(4), np.zeros(4), 1.0, "optimal", 0.0, extra={"pressures_Pa": {"urethra": 100.0,
                                                                                         "tumour": 2e3}},
                 layout=chain.layout)
    em = estimate_to_message(e)
    assert [k for k in em if k.startswith("p_")] == ["p_urethra_kPa", "p_tumour_kPa"] and em["p_tumour_kPa"] == 2.0
    back = message_to_estimate(em)
    assert back.cavity_names == ("urethra", "tumour") and back.pressures_Pa["tumour"] == pytest.approx(2e3)
    assert message_to_estimate(estimate_to_message(marker_estimate(SourceEvent(0, "x"), [], none.layout))
                               ).cavity_names == ()


def test_a_recording_of_other_cavities_is_refused_in_one_line(tmp_path, models):
    from softphantom.sensing.bench import BenchConfig, open_replay
    from softphantom.sensing.recording import Recorder

    path = tmp_path / "r.csv"
    bench = BenchConfig.from_model(models["two"])
    with Recorder(path, {"bench": bench.to_meta(), "chain": bench.chain().summary()}, layout=bench.layout):
        pass
    with pytest.raises(UserError, match=r"^--source replay:\S+: its channels \(front_zpos, front_zneg, back_xpos, "
                                        r"back_xneg, urethra, tumour\) are not the model's \(front_zpos, front_zneg, "
                                        r"back_xpos, back_xneg\)$"):
        open_replay(str(path), models["none"])


def test_the_firmware_reads_the_arms_and_each_cavity(tmp_path, models, monkeypatch):
    """The firmware built for N + M = 6 channels (``make N_CHANNELS=6``) and run in simavr as the
    virtual board of the two-cavity phantom: its frames carry six sums and the tumour's pressure
    comes through its own channel; a board without the inputs is refused naming both counts."""
    from softphantom.sensing.chain import MPX4250D
    from softphantom.virtual import VirtualConfig, scenario_from_dict, simulate
    from softphantom.virtual import firmware_sim

    with pytest.raises(UserError, match=r"^--mcu uno: the Arduino UNO has 6 analog inputs \(A0-A5\), the design needs "
                                        r"7 channels \(5 arms and 2 internal cavities: urethra, tumour\); --mcu mega "
                                        r"has 16$"):
        firmware_sim.check_board("uno", 7, ("urethra", "tumour"))
    if why := firmware_sim.simavr_missing():
        pytest.skip(why)
    harness, elf = firmware_sim.build(tmp_path / "fw", n_channels=6, cavity_names=("urethra", "tumour"))
    assert (tmp_path / "fw" / "config").read_text().split()[2] == "N_CHANNELS=6"
    sc = scenario_from_dict({"name": "tumour", "duration_s": 2.0, "rest_s": 0.6, "inflate": [
        {"cavity": "tumour", "p_kPa": P_TUMOUR_KPA, "start_s": 0.7, "rise_s": 0.4, "hold_s": 0.4, "fall_s": 0.4}]})
    cfg = VirtualConfig.seeded(seed=1, osr=25, order=1, board_kind="firmware")
    monkeypatch.setattr(firmware_sim, "build", lambda *a, **k: (harness, elf))  # the one built above
    run = simulate(sc, models["two"], cfg, truth_mesh=models["two"])
    ms = [m for m in run.source() if m.osr == 25]
    assert run.chain.n_channels == 6 and all(m.raw.shape == (6,) for m in ms)
    held = [m.pressures_Pa["tumour"] for m in ms if 1.2 < m.t < 1.4]
    # tared at rest; one code of the MPX4250D at N = 25 plus the noise of a window
    assert held and np.abs(np.array(held) / 1e3 - P_TUMOUR_KPA).max() < 2 / (1024 * MPX4250D.k1_per_kPa)
