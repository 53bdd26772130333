"""One channel layout, made by the design and written into every file's metadata: it round-trips
through every writer and reader for the BIP, a five-arm design and the liver, and the files of
the previous release (tests/fixtures/legacy, written before the layout was) still read."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from softphantom.design import BIPDesign, design_from_dict, load_design
from softphantom.errors import FileFormatError
from softphantom.pose import Pose6
from softphantom.records import ARM_NAMES, BIP_LAYOUT, LAYOUT_KEY, ChannelLayout, Estimate, Measurement
from softphantom.records.estimate import estimate_to_message, message_to_estimate
from softphantom.records.measurement import measurement_to_message
from softphantom.sensing.bench import BenchConfig
from softphantom.sensing.recording import Recorder, read_recording
from softphantom.estimation.stream import EstimateWriter
from softphantom.stream.recording import SessionRecorder, TOPIC_GEOMETRY, estimate_file_layout, read_estimate_csv
from softphantom.stream.recording import read_recording as read_session
from softphantom.viz.live.source import EstimateReplay, LiveGeometry, ellipsoid_geometry

REPO = Path(__file__).resolve().parents[1]
LEGACY = Path(__file__).parent / "fixtures" / "legacy"
FIVE = {"arm_names": [*ARM_NAMES, "top"], "arms": {"top": {"direction": [0.0, 0.6, 1.0], "cavity_volume_mm3": 486.0}}}


def _designs():
    return {"bip": BIPDesign(), "five": design_from_dict(FIVE), "liver": load_design(REPO / "examples/organs/liver.toml")}


@pytest.fixture(scope="module")
def designs():
    return _designs()


def test_the_design_makes_the_layout(designs):
    assert designs["bip"].channel_layout == BIP_LAYOUT
    assert designs["five"].channel_layout == ChannelLayout((*ARM_NAMES, "top"), (), ("urethra",))
    liver = designs["liver"].channel_layout
    assert liver.arms == ("caudal_front", "cranial_front", "right_back", "left_back")
    assert liver.actuated == ("tumour", "breathing") and liver.measured == ()


@pytest.mark.parametrize("bad, match", [
    ({"arms": ["a", "a"]}, r"channels: 'a' named twice"),
    ({"arms": []}, r"channels: no arm"),
    ({"arms": ["a"], "pumped": ["b"]}, r"channels: unknown key 'pumped'"),
    ({"arms": "abc"}, r"channels: arms must be a list of names"),
    ({"measured": ["a"]}, r"channels: no arms$"),
])
def test_a_bad_layout_in_a_file_is_a_one_line_error(bad, match):
    with pytest.raises(FileFormatError, match=match):
        ChannelLayout.from_dict(bad)


def _measurements(layout: ChannelLayout, n: int = 3):
    na, nc = len(layout.sensing), len(layout.actuated)
    for i in range(n):
        pres = {c: 1000.0 * (k + 1) * i for k, c in enumerate(layout.actuated)}
        yield Measurement(0.01 * i, i, 0.01 * i, np.full(na + nc, 51200 + i), 100,
                          np.arange(1, na + 1) * 10.0 * (i + 1), np.arange(1, na + 1) * 1e-9 * (i + 1),
                          pres.get("urethra", float("nan")), "ok", None if layout.actuated == ("urethra",) else pres)


def _estimate(layout: ChannelLayout, i: int, targets) -> Estimate:
    n = len(layout.sensing)
    pres = {c: 500.0 * (k + 1) * i for k, c in enumerate(layout.actuated)}
    return Estimate(t=0.01 * i, force=np.array([0.1, 1.0 * i, -0.2]), p_urethra=pres.get("urethra", float("nan")),
                    pose=Pose6(np.array([0.0, 0.001 * i, 0.0]), np.zeros(3)),
                    target_shift={k: np.array([0.0, 0.0005 * i, 0.0]) for k in targets},
                    volume_pred=np.arange(1, n + 1) * 1e-9 * i, volume_meas=np.arange(1, n + 1) * 2e-9 * i,
                    cond_W=10.0, qp_status="optimal", step_time=0.002,
                    pressures_Pa=None if layout.actuated == ("urethra",) else pres, layout=layout)


@pytest.mark.parametrize("name", ["bip", "five", "liver", "measured"])
def test_the_layout_round_trips_through_every_writer_and_reader(tmp_path, designs, name):
    if name == "measured":  # the liver's tumour read as an arm is (a differential transducer)
        layout = ChannelLayout(designs["liver"].arm_names, ("tumour",), ("breathing",))
    else:
        layout = designs[name].channel_layout
    targets = ["apex", "base"]
    # the sensing recording: its metadata's layout, its columns, its values
    bench = BenchConfig(cavity_volumes_m3=(500e-9,) * len(layout.sensing), gains=(1.0,) * len(layout.sensing),
                        layout=layout)
    chain = bench.chain()
    assert chain.layout == layout and chain.names == layout.channels
    ms = list(_measurements(layout))
    with Recorder(tmp_path / "r.csv", {"bench": bench.to_meta(), "chain": chain.summary()}, layout=layout) as rec:
        for m in ms:
            rec.write(m)
    meta = json.loads((tmp_path / "r.csv").read_text().splitlines()[0][2:])
    assert meta[LAYOUT_KEY] == layout.to_dict()
    r = read_recording(tmp_path / "r.csv")
    assert r.layout == layout and BenchConfig.from_meta(r.meta).layout == layout
    np.testing.assert_allclose(r.dV, [m.dV for m in ms], atol=1e-15)
    np.testing.assert_allclose(r.pressures, [list(m.cavity_pressures.values()) for m in ms], atol=1e-3)
    # the estimate file
    es = [_estimate(layout, i, targets) for i in range(3)]
    with EstimateWriter(tmp_path / "e.csv", targets, {"kind": "softphantom-estimate"}, layout) as w:
        for e in es:
            w.write(e)
    fmeta, rows = read_estimate_csv(tmp_path / "e.csv")
    back = estimate_file_layout(tmp_path / "e.csv", fmeta, rows[0])
    assert back == layout and fmeta[LAYOUT_KEY] == layout.to_dict()
    got = message_to_estimate(rows[2], back)
    np.testing.assert_allclose(got.volume_meas, es[2].volume_meas, rtol=1e-9)
    assert got.cavity_pressures == pytest.approx(es[2].cavity_pressures)
    # the session recording (MCAP), with the live geometry message
    geo = LiveGeometry(**{**ellipsoid_geometry(subdivisions=0).__dict__, "layout": layout})
    with SessionRecorder(tmp_path / "s.mcap", layout=layout) as rec:
        rec.write(TOPIC_GEOMETRY, geo.to_json())
        for i, (e, m) in enumerate(zip(es, ms)):
            rec.write_estimate(estimate_to_message(e, i, 0.0))
            rec.write_sensors(measurement_to_message(m, layout))
    s = read_session(tmp_path / "s.mcap")
    assert s.layout == layout and json.loads(s.metadata[LAYOUT_KEY]) == layout.to_dict()
    assert LiveGeometry.from_json(s.geometry).layout == layout
    assert s.sensors[1][f"dV_{layout.sensing[-1]}_mm3"] == pytest.approx(len(layout.sensing) * 2.0)
    # the replays of both files give the live view the same layout
    assert EstimateReplay(tmp_path / "s.mcap", speed=0).layout == layout
    assert EstimateReplay(tmp_path / "e.csv", speed=0).layout == layout


def test_the_model_fem_and_solver_carry_the_design_layout(designs):
    from softphantom.design.model import PhantomModel

    # the layout of a model is its design's; the FEM refuses one naming a cavity it has no wall for
    from softphantom.fem.model import build_fem
    from softphantom.errors import MeshError

    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    with pytest.raises(MeshError, match="channel 'front_zpos' has no cavity wall"):
        build_fem(X, np.array([[0, 1, 2, 3]]), cavities={}, layout=BIP_LAYOUT)
    assert PhantomModel.layout.fget(SimpleNamespace(design=designs["liver"])) == designs["liver"].channel_layout


@pytest.mark.parametrize("tag", ["bip", "liver"])
def test_files_of_the_previous_release_still_read(tag):
    """Written by main before the layout (tests/fixtures/legacy/README.md): read as it read them."""
    want = json.loads((LEGACY / "expected.json").read_text())
    r = read_recording(LEGACY / f"recording_{tag}.csv")
    w = want[f"recording_{tag}.csv"]
    assert LAYOUT_KEY not in r.meta
    assert (list(r.arm_names), list(r.cavity_names)) == (w["arms"], w["cavities"])
    np.testing.assert_allclose(r.dV * 1e9, w["dV_mm3"], atol=1e-6)
    np.testing.assert_allclose(r.pressures / 1e3, w["pressures_kPa"], atol=1e-6)
    b = BenchConfig.from_meta(r.meta)
    assert (list(b.arm_names), list(b.cavity_names)) == (w["bench_arms"], w["bench_cavities"])
    meta, rows = read_estimate_csv(LEGACY / f"estimate_{tag}.csv")
    w = want[f"estimate_{tag}.csv"]
    layout = estimate_file_layout(LEGACY / f"estimate_{tag}.csv", meta, rows[0])
    assert (list(layout.sensing), list(layout.actuated)) == (w["arms"], w["cavities"])
    np.testing.assert_allclose([message_to_estimate(m, layout).volume_meas * 1e9 for m in rows],
                               w["volume_meas_mm3"], atol=1e-6)
    s = read_session(LEGACY / f"session_{tag}.mcap")
    w = want[f"session_{tag}.mcap"]
    assert (list(s.arm_names), list(s.cavity_names), len(s.estimates), len(s.sensors)) == (
        w["arms"], w["cavities"], w["n_estimates"], w["n_sensors"])
    assert EstimateReplay(LEGACY / f"session_{tag}.mcap", speed=0).layout == s.layout
    assert EstimateReplay(LEGACY / f"estimate_{tag}.csv", speed=0).layout == layout
