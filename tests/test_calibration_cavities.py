"""softphantom calibrate reads the pressure of every internal cavity, not only the urethra's: on a
three-arm phantom whose one internal cavity is a balloon (no urethra), the recorded balloon
pressure loads the keyframe solves, so a stiffer cast body and a high-reading transducer are
recovered from pushes and one inflation; the same recording with the balloon's channel zeroed
(what a fit reading the urethra alone saw) gives a body stiffness several per cent off. A recording
whose channels are not the model's is refused in one line naming both lists."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from softphantom.calibration import CalibrationInputError, FitOptions, SessionSpec, calibrate, load_session
from softphantom.records import LAYOUT_KEY, ChannelLayout

from test_calibration import GAIN_TRUE

BULB_TRUE = 1.3  # the cast body is 30 % stiffer than the datasheet (the arms are as designed)
P_BALLOON_KPA = 60.0
BODY = {"law": "neo-hookean", "E_kPa": 142.0, "nu": 0.45, "density_kg_m3": 1070.0}
# the BIP's body with three of its arms and, instead of the urethra, a 7 mL balloon
DESIGN = {"arm_names": ["front_zpos", "front_zneg", "back_xpos"], "targets": {"t": [8.0, -18.0, 0.0]},
          "cavities": {"balloon": {"shape": "ellipsoid", "center_mm": [0.0, 2.0, 0.0],
                                   "semi_axes_mm": [14.0, 10.0, 12.0], "inlet_mm": [0.0, 25.0, 0.0]}},
          "materials": {"body": BODY, "body_truth": dict(BODY, E_kPa=BULB_TRUE * BODY["E_kPa"])},
          "region_materials": {"bulb": "body", "arms": "body"},
          "mesh": {"size_mm": 12.0, "surface_size_mm": 10.0, "arm_size_mm": 7.0, "cavity_segments": 12.0}}


def _push(start_s: float, force_N) -> dict:
    return {"point": "on-centre", "start_s": start_s, "rise_s": 0.6, "hold_s": 0.5, "fall_s": 0.6, "force_N": force_N}


# three pushes, then the balloon inflated with the phantom untouched (events may not overlap)
SCENARIO = {"name": "pushes-and-balloon", "duration_s": 9.6, "rest_s": 1.0,
            "push": [_push(1.1, [0.3, 1.5, -0.2]), _push(2.9, [1.2, 0.2, 0.3]), _push(4.7, [-0.2, 0.3, 1.2])],
            "inflate": [{"cavity": "balloon", "p_kPa": P_BALLOON_KPA, "start_s": 6.5, "rise_s": 0.6, "hold_s": 1.2,
                         "fall_s": 0.6}]}


def _edited(src: Path, dst: Path, rename: dict[str, str] | None = None, zero: str | None = None) -> Path:
    """A copy of recording ``src`` with header columns renamed (old -> new; the channels of its
    metadata's layout with them) and column ``zero``'s values set to 0."""
    lines = src.read_text().splitlines()
    names = {a[4:]: b[4:] for a, b in (rename or {}).items() if a.startswith("raw_")}
    meta = json.loads(lines[0][2:])
    meta[LAYOUT_KEY] = {k: [names.get(n, n) for n in v] for k, v in meta[LAYOUT_KEY].items()}
    lines[0] = "# " + json.dumps(meta)
    header = lines[1].split(",")
    rows = [ln.split(",") for ln in lines[2:]]
    if zero is not None:
        j = header.index(zero)
        for r in rows:
            r[j] = "0"
    header = [(rename or {}).get(c, c) for c in header]
    dst.write_text("\n".join([lines[0], ",".join(header)] + [",".join(r) for r in rows]) + "\n")
    return dst


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> dict[str, Path]:
    """The model directory and a virtual session of it whose truth has a stiffer body and a
    high-reading back_xpos transducer, on 2 m tubes (an arm reads ≈ 36 Pa per mm³, so the
    balloon's few tenths of a mm³ are well above the noise)."""
    import tomli_w

    from softphantom.design import build_model, load_model, save_model
    from softphantom.design.params import design_from_dict
    from softphantom.virtual.board import BoardConfig
    from softphantom.virtual.run import VirtualConfig, simulate, write_run
    from softphantom.virtual.tracker import TrackerConfig
    from softphantom.virtual.truth import TruthConfig

    base = tmp_path_factory.mktemp("balloon")
    save_model(build_model(design_from_dict(DESIGN), isolate=False), base / "model")
    model = load_model(base / "model")
    assert model.design.internal_cavity_names == ("balloon",)
    truth_design = design_from_dict({**DESIGN, "region_materials": {"bulb": "body_truth", "arms": "body"}})
    truth_mesh = dataclasses.replace(model, design=truth_design)  # the same mesh, the truth's materials
    (base / "scenario.toml").write_text(tomli_w.dumps(SCENARIO))
    cfg = VirtualConfig(TruthConfig(levels=2, law="model"),
                        BoardConfig(seed=3, gains=(1.0, 1.0, GAIN_TRUE, 1.0), tube_length_m=2.0), TrackerConfig(seed=3))
    write_run(simulate(base / "scenario.toml", model, cfg, truth_mesh=truth_mesh), base / "run")
    return {"model": base / "model", "run": base / "run"}


def _spec(run: Path, recording: Path) -> SessionSpec:
    return SessionSpec(recording, run / "tracker_motive.csv", "on-centre", run / "truth.csv")


# the body's stiffness and one gain are fitted; the rest is the design's (the existing test's set-up)
FIX = ("stiffness_arms_factor", "tube_volume_factor", "gain_front_zpos", "gain_front_zneg")


@pytest.mark.slow
def test_the_balloon_pressure_loads_the_fit(session, tmp_path, monkeypatch):
    import softphantom.calibration.run as run_mod
    from softphantom.calibration.report import _cavities_line, calibration_dict

    run = session["run"]
    cal = calibrate(session["model"], [_spec(run, run / "recording.csv")], options=FitOptions(fix=FIX),
                    in_process=True, max_keyframes=4)
    p = cal.parameters()
    assert p["stiffness_bulb_factor"] == pytest.approx(BULB_TRUE, rel=0.02)  # 1.304
    assert p["gain_back_xpos"] == pytest.approx(GAIN_TRUE, rel=0.03)  # 1.092
    i = cal.fit.names.index("stiffness_bulb_factor")
    assert cal.fit.ci95[i, 0] < BULB_TRUE < cal.fit.ci95[i, 1]
    # the balloon's pressure chose a keyframe and loaded its solve
    fr = cal.frames
    assert fr.cavity_names == ("balloon",) and fr.cavity_pressures_Pa.max() > 0.9 * P_BALLOON_KPA * 1e3
    assert np.all(cal.fitting.rmse("calibrated") < 0.3)  # mm and degrees, forces from the pressures alone
    assert calibration_dict(cal)["internal_cavities"] == ["balloon"]
    shown = re.search(r"in the keyframe solves \(largest\): balloon ([\d.]+) kPa", _cavities_line(cal))
    assert shown and float(shown[1]) == pytest.approx(fr.cavity_pressures_Pa.max() / 1e3, rel=1e-2)

    # the balloon's channel zeroed: its inflation is then an unexplained change of the arms' volumes
    # and poses (1.197 on this seed). The pose checks do not change the fit: skipped for time.
    monkeypatch.setattr(run_mod, "_pose_errors",
                        lambda prob, *a, **k: (np.zeros((len(prob.frames), 6)), np.zeros((len(prob.frames), 3))))
    zeroed = _edited(run / "recording.csv", tmp_path / "zeroed.csv", zero="p_balloon_kPa")
    blind = calibrate(session["model"], [_spec(run, zeroed)], options=FitOptions(fix=FIX), in_process=True,
                      max_keyframes=4).parameters()["stiffness_bulb_factor"]
    assert abs(blind / BULB_TRUE - 1) > 0.04
    assert abs(blind / BULB_TRUE - 1) > 5 * abs(p["stiffness_bulb_factor"] / BULB_TRUE - 1)


def test_a_recording_of_other_channels_is_refused_in_one_line(session, tmp_path, capsys):
    from softphantom.cli import main

    run, model = session["run"], session["model"]
    urethra = _edited(run / "recording.csv", tmp_path / "urethra.csv",
                      {"raw_balloon": "raw_urethra", "p_balloon_kPa": "p_urethra_kPa"})  # a BIP-like board
    with pytest.raises(CalibrationInputError, match=r"pressure channels p_urethra_kPa are not the model's internal "
                                                    r"cavities' \(p_balloon_kPa\)$"):
        load_session(urethra, run / "truth.csv", (0, 0, 0), layout=ChannelLayout(tuple(DESIGN["arm_names"]), (), ("balloon",)))
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["calibrate", "--model", str(model), "--recording", str(urethra), "--truth", str(run / "truth.csv"),
                 "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert not out.exists() and "\n" not in err and "p_urethra_kPa" in err and "p_balloon_kPa" in err
    # an arm of another name: the arm lists, in order
    other = _edited(run / "recording.csv", tmp_path / "arm.csv",
                    {f"{k}_back_xpos{u}": f"{k}_back_xneg{u}" for k, u in (("raw", ""), ("dp", "_kPa"), ("dV", "_mm3"))})
    with pytest.raises(CalibrationInputError, match=r"arm channels front_zpos, front_zneg, back_xneg are not the "
                                                    r"model's \(front_zpos, front_zneg, back_xpos\)$"):
        load_session(other, run / "truth.csv", (0, 0, 0), layout=ChannelLayout(("front_zpos", "front_zneg", "back_xpos"), (), ("balloon",)))
