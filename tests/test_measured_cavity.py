"""A measured internal cavity (``[cavities.NAME] role = "measured"``): a sealed balloon inside the
body, read as one more volume channel (a differential transducer, Boyle's law), never loaded.

One coarse P1 phantom (the BIP's body and arms without fillets, 12 mm): the urethra actuated and a
4 mm ``ball`` measured next to the on-centre contact. Checked: the names and channels, Maxwell–Betti
reciprocity between the ball's sensing row and the FEM solved with the roles swapped, and the
refusals. A virtual push through the board and ``estimate`` that reads the ball, and ``calibrate``
fitting its transducer: tests/test_cavities_e2e.py (the ball beside a tumour balloon)."""

from __future__ import annotations

import functools
from types import SimpleNamespace

import numpy as np
import pytest

from softphantom.design import geometry as geo
from softphantom.records import ChannelLayout
from softphantom.design.params import ARM_NAMES, BIPDesign, design_from_dict, design_to_toml, load_design
from softphantom.errors import DesignError

AXES = BIPDesign().bulb.semi_axes_mm
BALL = {"shape": "ellipsoid", "center_mm": [8.0, -14.0, -6.0], "semi_axes_mm": [4.0, 4.0, 4.0],
        "inlet_mm": [round(float(x), 4) for x in geo.project_to_ellipsoid((1.0, -0.6, -0.6), AXES)],
        "role": "measured"}
COARSE = {"size_mm": 12.0, "surface_size_mm": 10.0, "arm_size_mm": 7.0, "cavity_segments": 18.0}
SENSING = (*ARM_NAMES, "ball")


def design_dict(role: str = "measured") -> dict:
    return {"urethra": {}, "arms": {n: {"junction_fillet_mm": 0.0} for n in ARM_NAMES},
            "cavities": {"ball": dict(BALL, role=role)}, "mesh": COARSE}


@functools.cache
def _model():
    from softphantom.design.model import build_model

    return build_model(design_from_dict(design_dict()), isolate=False)


@functools.cache
def _forward():
    from softphantom.estimation.forward import ForwardModel

    return ForwardModel(_model())


# --- names, channels, records (no mesh) ----------------------------------------------------------

def test_names_channels_and_columns(tmp_path):
    from softphantom.estimation.atlas.build import check_atlas_cavities
    from softphantom.records.names import measurement_columns
    from softphantom.sensing.bench import BenchConfig
    from softphantom.sensing.chain import nominal_tare, pa_to_counts, to_measurement
    from softphantom.sensing.measurement import P0_STANDARD_PA
    from softphantom.sensing.pneumatics import tube_volume_m3
    from softphantom.virtual.demo import design_scenarios

    d = design_from_dict(design_dict())
    assert d.internal_cavity_names == ("urethra", "ball") and d.measured_cavity_names == ("ball",)
    assert d.sensing_names == SENSING and d.pressure_names == ("urethra",)
    assert d.cavity_names == (*ARM_NAMES, "urethra", "ball")  # the mesh's cavities: file order
    assert d.sensors.gains == (1.0,) * 5 and d.sensing_volumes_mm3()[-1] == pytest.approx(4 / 3 * np.pi * 64)
    path = tmp_path / "d.toml"
    path.write_text(design_to_toml(d))
    assert load_design(path) == d and 'role = "measured"' in path.read_text()
    with pytest.raises(DesignError, match=r"^sensors\.gains: 4 given for 5 volume channels \(one per volume "
                                          r"channel, in the sensor order: .*, back_xneg, ball\)$"):
        design_from_dict({**design_dict(), "sensors": {"gains": [1.0, 1.1, 1.0, 1.0]}})

    # the board: the ball on a differential transducer after the arms, then the urethra's MPX4250D
    bench = BenchConfig.from_model(SimpleNamespace(design=d))
    chain = bench.chain()
    assert chain.names == (*SENSING, "urethra") and chain.arm_names == SENSING and chain.cavity_names == ("urethra",)
    assert [t.name for t in chain.transducers] == ["MPXV7002"] * 5 + ["MPX4250D"]
    meta = bench.to_meta()
    assert bench.layout == ChannelLayout(ARM_NAMES, ("ball",), ("urethra",)) == d.channel_layout
    assert meta["arm_cavity_mm3"][-1] == pytest.approx(268.082573, abs=1e-6)
    assert BenchConfig.from_meta({"bench": meta, **bench.layout.to_meta()}).layout == bench.layout
    cols = measurement_columns(chain.layout)
    assert {"raw_ball", "dp_ball_kPa", "dV_ball_mm3", "p_urethra_kPa"} <= set(cols) and "p_ball_kPa" not in cols
    # +400 Pa at the ball's transducer: ΔV by Boyle over the ball and its 12 m × 1.2 mm tube
    raw = np.array([pa_to_counts(0.0, t, 100) for t in chain.transducers])
    raw[4] = pa_to_counts(400.0, chain.transducers[4], 100)
    m = to_measurement(0.0, 0, 0.0, np.round(raw).astype(int), 100, chain, nominal_tare(chain))
    v_total = 4 / 3 * np.pi * 64e-9 + tube_volume_m3(12.0, 1.2e-3)
    assert m.dp[4] == pytest.approx(400.0, abs=5.0) and m.dV.shape == (5,)
    assert m.dV[4] == pytest.approx(v_total * (P0_STANDARD_PA / (P0_STANDARD_PA + m.dp[4]) - 1.0), rel=1e-12)
    assert m.pressures_Pa is None and abs(m.p_urethra) < 150.0

    # the same cavity actuated: a pressure channel after the urethra's, a load
    a = design_from_dict(design_dict("actuated"))
    assert a.sensing_names == ARM_NAMES and a.pressure_names == ("urethra", "ball")
    achain = BenchConfig.from_model(SimpleNamespace(design=a)).chain()
    assert achain.names == (*ARM_NAMES, "urethra", "ball") and achain.transducers[-1].name == "MPX4250D"
    assert "p_ball_kPa" in measurement_columns(achain.layout)
    # the demo inflates the actuated cavities only; the atlas's own pressure axis is the first
    # actuated one's (a second one's levels make a stack: tests/test_atlas_stack.py)
    assert [s.name for s in design_scenarios(d) if s.name.startswith("inflate")] == ["inflate-urethra"]
    assert check_atlas_cavities(SimpleNamespace(layout=d.channel_layout)) == "urethra"
    assert check_atlas_cavities(SimpleNamespace(layout=a.channel_layout)) == "urethra"


# --- reciprocity --------------------------------------------------------------------------------

def test_the_measured_row_obeys_maxwell_betti_reciprocity():
    """At rest, the ball's sensing row of the estimator's W equals what the FEM gives with the roles
    swapped: ∂V_ball/∂p_urethra = ∂V_urethra/∂p_ball and ∂V_ball/∂f = H_fᵀ ∂x/∂p_ball (the contact
    patch's displacement under unit pressure in the ball). The swapped side is Newton's solve at
    ±100 Pa in the ball (central difference: 1.2e-6 relative measured; one-sided, the geometric
    non-linearity shows at 1.1e-3), and the equilibrium solver with the ball as the load."""
    from softphantom.estimation.linearization import EquilibriumSolver
    from softphantom.fem import cavity_volume, solve_static

    fwd = _forward()
    assert fwd.eq.arm_names == SENSING and fwd.eq.pressure_names == ("urethra",)
    W = fwd.rest.W  # rows: the arms, then the ball; columns f_x, f_y, f_z, p_urethra
    fem, H = fwd.fem, fwd.H_f
    x0 = fem.x_rest.reshape(-1)
    p = 100.0
    dvu, du = [], []
    for s in (1.0, -1.0):
        x = solve_static(fem, None, pressures={"ball": s * p}, tol=1e-10).x.reshape(-1)
        dvu.append(cavity_volume(x, fem.cavities["urethra"]) - cavity_volume(x0, fem.cavities["urethra"]))
        du.append(H.T @ (x - x0))
    assert W[4, 3] > 0 and (dvu[0] - dvu[1]) / (2 * p) == pytest.approx(W[4, 3], rel=1e-5)
    assert np.abs(W[4, :3]).max() > 0.5e-9  # m³/N: the ball sees the push (0.7..1.1 mm³/N)
    np.testing.assert_allclose((du[0] - du[1]) / (2 * p), W[4, :3], rtol=1e-5)
    # the one-sided difference at 100 Pa: the linear regime's reciprocity to a few 1e-3
    assert dvu[0] / p == pytest.approx(W[4, 3], rel=3e-3)
    # the estimator's own solver with the roles swapped: the urethra a row, the ball the load
    swap = EquilibriumSolver(fem, H, fwd.probe, layout=ChannelLayout(ARM_NAMES, ("urethra",), ("ball",)))
    assert swap.arm_names == (*ARM_NAMES, "urethra")
    r = swap.rest()
    assert r.W[4, 3] == pytest.approx(W[4, 3], rel=1e-9)
    np.testing.assert_allclose(H.T @ r.U[:, 3], W[4, :3], rtol=1e-9)
    np.testing.assert_allclose(r.W[:4, :3], W[:4, :3], rtol=1e-9)  # the arms' rows: the force alone
    # the design report's observability: five rows, the ball named among them, one pressure load
    from softphantom.estimation.observability import observability, observability_md

    obs = observability(_model(), forward=fwd, loaded=False)
    assert obs.rest.J.shape == (5, 4) and obs.measured_names == ("ball",) and obs.pressure_names == ("urethra",)
    assert "sensitivity of the volume channels (the arms and the measured ball) to the loads" in observability_md(obs)


# --- refusals -----------------------------------------------------------------------------------

def test_refusals(tmp_path, capsys):
    import tomli_w

    from softphantom.cli import main
    from softphantom.design import save_model
    from softphantom.virtual.scenario import ScenarioError, scenario_from_dict
    from softphantom.virtual.truth import solve_truth

    for data, match in (({"urethra": {"role": "measured"}}, r"^urethra\.role = 'measured': the \[urethra\] is "
                                                             r"actuated .* a \[cavities\.NAME\] table"),
                        ({**design_dict(), "cavities": {"ball": dict(BALL, role="read")}},
                         r"^cavities\.ball\.role: 'read' is not one of actuated, measured$")):
        with pytest.raises(DesignError, match=match) as exc:
            design_from_dict(data)
        assert "\n" not in str(exc.value)
    (tmp_path / "u.toml").write_text('[urethra]\nrole = "measured"\n')
    assert main(["design", "--config", str(tmp_path / "u.toml"), "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "urethra.role" in err, err

    model = _model()
    save_model(model, tmp_path / "m")
    assert main(["simulate", "--model", str(tmp_path / "m"), "--pressure-kPa", "ball=5", "--out",
                 str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--pressure-kPa ball: a measured cavity" in err and "urethra" in err, err

    inflate = {"name": "blow", "duration_s": 3.0, "rest_s": 1.0,
               "inflate": [{"cavity": "ball", "p_kPa": 5.0, "start_s": 1.1, "rise_s": 0.6}]}
    with pytest.raises(ScenarioError, match=r"^s\.toml: inflate\.cavity ball: a measured cavity \(read as a volume, "
                                            r"never loaded\); the actuated ones: urethra$"):
        solve_truth(scenario_from_dict(inflate, "s.toml"), model)
    (tmp_path / "s.toml").write_text(tomli_w.dumps(inflate))
    assert main(["virtual", "run", "--scenario", str(tmp_path / "s.toml"), "--model", str(tmp_path / "m"),
                 "--out", str(tmp_path / "v"), "--truth-order", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "inflate.cavity ball: a measured cavity" in err, err
