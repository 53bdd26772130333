"""Observability of the loads from the arm volumes (softphantom.estimation.observability) at the
coarse mesh: the sensitivity against finite differences of full non-linear solves, the default
design observable, a coplanar arm layout refused, the sweep's objective maximized (the design
report's table: test_design_cli.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.design import BIPDesign, build_model
from softphantom.errors import DesignError
from softphantom.estimation import ForwardModel
from softphantom.estimation.observability import (
    REFUSE_RATIO,
    WARN_COUNTS,
    check_layout,
    count_volume_mm3,
    envelope_ranges,
    layout_problem,
    layout_warnings,
    observability,
)
from softphantom.estimation.types import ARM_NAMES
from softphantom.fem import cavity_volume, solve_static

COARSE_MM = 12.0
# every arm and the contact point (on the −y axis) in the plane z = 0, the urethra centred on it:
# each arm volume is an even function of f_z
COPLANAR = """
[urethra]
center_mm = [0.0, 0.0, 0.0]
inlet_mm = [0.0, 25.0, 0.0]
[arms.front_zpos]
direction = [1.0, -0.6, 0.0]
[arms.front_zneg]
direction = [-1.0, -0.6, 0.0]
"""


def _coplanar() -> BIPDesign:
    d = BIPDesign()
    dirs = {"front_zpos": (1.0, -0.6, 0.0), "front_zneg": (-1.0, -0.6, 0.0)}
    arms = tuple(dataclasses.replace(a, direction=dirs.get(a.name, a.direction)) for a in d.arms)
    return dataclasses.replace(d, arms=arms, cavities=(dataclasses.replace(
        d.urethra, center_mm=(0.0, 0.0, 0.0), inlet_mm=(0.0, 25.0, 0.0)),))


@pytest.fixture(scope="module")
def forward(coarse_model):
    return ForwardModel(coarse_model)


def _volumes_mm3(fm: ForwardModel, lam) -> np.ndarray:
    """Arm volumes (mm³) of the full Newton solve (fem.solve_static, not the estimator's solver)."""
    fem = fm.fem
    sol = solve_static(fem, fm.H_f @ np.asarray(lam[:3], float), [(fem.cavities["urethra"], float(lam[3]))], tol=1e-10)
    assert sol.converged
    x = sol.x.reshape(-1)
    return np.array([cavity_volume(x, fem.cavities[a]) for a in ARM_NAMES]) * 1e9


@pytest.mark.parametrize("at", [(0.0, 0.0, 0.0, 0.0), (0.5, 2.0, -0.5, 10e3)])
def test_sensitivity_is_the_central_difference_of_full_solves(coarse_model, forward, at):
    """J (mm³/N, mm³/kPa) from the linearization against central differences of converged
    non-linear volumes; the singular values are those of J scaled by the envelope's ranges and the
    weakest step is the one whose volume change is the smallest singular value."""
    at = np.array(at)
    obs = observability(coarse_model, forward, loaded=False)
    st = obs.rest
    if at.any():
        from softphantom.estimation.observability import observed_state

        st = observed_state(forward.solve(at), obs.ranges)
    h = np.array([0.02, 0.02, 0.02, 200.0])  # N, N, N, Pa
    fd = np.empty((4, 4))
    for j in range(4):
        e = np.zeros(4)
        e[j] = h[j]
        fd[:, j] = (_volumes_mm3(forward, at + e) - _volumes_mm3(forward, at - e)) / (2 * h[j])
    fd[:, 3] *= 1e3  # per kPa
    for j in range(4):
        assert np.linalg.norm(st.J[:, j] - fd[:, j]) < 3e-4 * np.linalg.norm(fd[:, j]), j  # O(h²): 6e-5 measured
    assert st.lam.tolist() == pytest.approx((at / [1, 1, 1, 1e3]).tolist())
    assert np.linalg.svd(fd * obs.ranges, compute_uv=False) == pytest.approx(st.sv_mm3, rel=5e-3)
    assert np.linalg.norm(st.J @ st.weakest) == pytest.approx(st.sv_mm3[-1], rel=1e-9)
    assert np.linalg.norm(st.J[:, :3] @ st.weakest_force) == pytest.approx(st.sv_force_mm3[-1], rel=1e-9)
    assert np.linalg.norm(st.weakest / obs.ranges) == pytest.approx(1.0)


def test_default_design_is_observable(coarse_model, forward):
    """Every singular value positive, at rest and over the envelope; the force's weakest direction
    well above the refusal ratio and the warning's counts; one count from the sensing budget."""
    obs = observability(coarse_model, forward)
    # eq. 1–2: one count is 4 kPa over 2^10·√100 levels at the transducer, V_T·δp/P0 in volume (the
    # larger cavity + 12 m of 1.2 mm tube)
    v_total = 514.0 + np.pi / 4 * 1.2**2 * 12_000
    assert obs.count_mm3 == pytest.approx(v_total * 4000 / (2**10 * 10) / 101_325, rel=1e-9)
    assert len(obs.loaded) == 8 and not obs.failed
    for s in obs.states:
        assert s.sv_mm3[-1] > 0 and s.sv_force_mm3[-1] > WARN_COUNTS * obs.count_mm3
        assert np.all(np.diff(s.sv_mm3) <= 0) and s.cond == pytest.approx(s.sv_mm3[0] / s.sv_mm3[-1])
    r = obs.rest
    assert r.sv_force_mm3[-1] / r.sv_force_mm3[0] > 2 * REFUSE_RATIO
    assert abs(r.weakest[3]) == pytest.approx(obs.ranges[3], rel=0.01)  # the arms see the urethra least
    assert layout_problem(obs) == "" and layout_warnings(obs) == []


@pytest.mark.slow
def test_coplanar_arms_are_refused_unless_forced(tmp_path, capsys):
    """All arms and the contact point in z = 0: f_z is seen only through the mesh's asymmetry;
    `design` refuses it in one line naming the arms, exit 2, nothing written; --force keeps it
    with the reason as a warning."""
    model = build_model(_coplanar(), COARSE_MM, isolate=False)
    obs = observability(model, loaded=False)
    r = obs.rest
    assert r.sv_force_mm3[-1] / r.sv_force_mm3[0] < REFUSE_RATIO
    assert abs(r.weakest_force[2]) > 0.95 * np.linalg.norm(r.weakest_force)  # the force along z
    with pytest.raises(DesignError, match=r"^arms: the layout cannot see a force step"):
        check_layout(obs)
    assert check_layout(obs, force=True)[0] == layout_problem(obs)
    cfg = tmp_path / "coplanar.toml"
    cfg.write_text(COPLANAR)
    assert main(["design", "--config", str(cfg), "--out", str(tmp_path / "o"), "--mesh-size-mm", "12", "--no-png"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err and "arms:" in err and "f_z +4.00 N" in err
    assert not (tmp_path / "o").exists()


def test_count_and_ranges():
    """One count of each arm: the same volume for both cavity sizes (V_cavity·LF = V_total)."""
    assert count_volume_mm3([514.0]) == pytest.approx(count_volume_mm3([486.0]), rel=0.01)
    assert envelope_ranges().tolist() == pytest.approx([4.0, 6.2, 4.0, 42.0])


def test_sweep_optimize_maximizes_the_smallest_singular_value(tmp_path, monkeypatch, capsys):
    """`--objective obs_sv_min_mm3` is maximized: with a stand-in evaluation whose value peaks
    inside the box, the best candidate is the largest value seen and reported as itself."""
    import softphantom.study.optimize as opt
    from softphantom.study import sweep_config_from_dict
    from softphantom.study.run import SweepRun

    def fake(client, variants, out, label=""):
        rows = [{"status": "ok", "range_min_N": 10.0, "silicone_mL": 100.0,
                 "p.sensing.tube_length_m": v.params["sensing.tube_length_m"],
                 "obs_sv_min_mm3": 10.0 - (v.params["sensing.tube_length_m"] - 4.0) ** 2} for v in variants]
        return SweepRun(rows, 0, len(rows), None)

    monkeypatch.setattr(opt, "evaluate_variants", fake)
    cfg = sweep_config_from_dict({"parameters": {"sensing.tube_length_m": {"min": 0.5, "max": 12.0}},
                                  "optimize": {"maxiter": 2, "popsize": 5, "seed": 2, "objective": "obs_sv_min_mm3"}})
    res = opt.optimize(cfg, None, tmp_path)
    assert res.value == max(r["obs_sv_min_mm3"] for r in res.rows) == res.row["obs_sv_min_mm3"]
    assert res.value > 0
    good = tmp_path / "s.toml"
    good.write_text("[sweep]\nmethod = 'grid'\n")
    for extra, where in ((["--optimize", "--objective", "cond"], "--objective: 'cond' is not one of"),
                         (["--objective", "obs_sv_min_mm3"], "--objective: only with --optimize")):
        assert main(["sweep", "--config", str(good), "--out", str(tmp_path / "o"), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and where in err
