"""Internal cavities after the estimator: the board reads a pressure channel per internal cavity
(an MPX4250D each, after the arms'), the records name them (``raw_<cavity>``, ``p_<cavity>_kPa``),
the virtual phantom inflates the one a scenario names, and estimate, evaluate and live take any
M >= 0. A phantom without any internal cavity runs end to end here, on the coarse 12 mm P1 model of
tests/test_cavities.py; one with two actuated cavities (and a measured one) in
tests/test_cavities_e2e.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softphantom.errors import UserError

PUSH_N = (0.3, 2.0, -0.2)
P_TUMOUR_KPA = 20.0
# a push, then the tumour balloon inflated (the refusals below take it apart)
TWO = {"name": "push-and-tumour", "duration_s": 5.0, "rest_s": 1.0,
       "push": [{"point": "on-centre", "start_s": 1.1, "rise_s": 0.6, "hold_s": 0.5, "fall_s": 0.6,
                 "force_N": list(PUSH_N)}],
       "inflate": [{"cavity": "tumour", "p_kPa": P_TUMOUR_KPA, "start_s": 2.9, "rise_s": 0.6, "hold_s": 0.7,
                    "fall_s": 0.6}]}
PUSH_ONLY = {"name": "push", "duration_s": 3.0, "rest_s": 1.0, "push": TWO["push"]}


@pytest.fixture(scope="module")
def models(two_cavities_model, no_cavities_model):
    # test_cavities' designs, meshed once per run (conftest)
    return {"two": two_cavities_model, "none": no_cavities_model}


def _header(path) -> tuple[dict, list[str]]:
    lines = path.read_text().splitlines()
    return json.loads(lines[0][2:]), lines[1].split(",")


@pytest.mark.slow
def test_no_internal_cavity_records_arms_only_and_estimates(tmp_path, models):
    """A cavity-free phantom through the board, ``estimate --estimator refresh`` and ``evaluate``:
    the arms alone on the board, no pressure column anywhere, the push found. The truth is solved
    on the model's own mesh through the API (``virtual run``'s own command line, summary and
    re-meshed truth: tests/test_cavities_e2e.py)."""
    from softphantom.cli import main
    from softphantom.design import save_model
    from softphantom.evaluation import evaluate, read_estimate, read_truth
    from softphantom.evaluation.files import read_table
    from softphantom.records.names import estimate_columns, measurement_columns
    from softphantom.virtual import VirtualConfig, scenario_from_dict, simulate, write_run

    model = models["none"]
    arms = model.design.arm_names
    # the seed and settings of ``virtual run --truth-order 1 --truth-mesh-scale 1 --osr 200``
    run = simulate(scenario_from_dict(PUSH_ONLY, "push.toml"), model,
                   VirtualConfig.seeded(seed=0, osr=200, order=1, mesh_scale=1.0), truth_mesh=model)
    assert run.chain.n_channels == 4 and f"{run.rate_Hz:.1f}" == "12.0"  # 4 channels a frame at OSR 200
    paths = write_run(run, tmp_path / "run")
    meta, cols = _header(paths["recording"])
    assert tuple(cols) == measurement_columns(model.layout) and not [c for c in cols if c.startswith("p_")]
    assert meta["channels"]["actuated"] == [] and meta["chain"]["transducers"] == ["MPXV7002"] * 4
    _, truth_cols = _header(paths["truth"])
    assert not [c for c in truth_cols if c.startswith("p_") and c.endswith("_kPa")]
    save_model(model, tmp_path / "model")
    est = tmp_path / "estimate.csv"
    assert main(["estimate", "--model", str(tmp_path / "model"), "--source", f"replay:{paths['recording']}",
                 "--out", str(est), "--estimator", "refresh"]) == 0
    assert main(["evaluate", "--estimate", str(est), "--truth", str(paths["truth"]),
                 "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "report.html").is_file()
    assert list(read_table(est).columns) == estimate_columns(list(model.targets), model.layout)
    ev = evaluate(read_truth(paths["truth"]), read_estimate(est))
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
