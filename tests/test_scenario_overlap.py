"""Scenarios whose events overlap in time (a *group*: a push while a balloon inflates) and repeated
events (breathing), on the virtual phantom.

One scenario is solved once, on the coarse two-cavity model's own mesh (the BIP with a ``tumour``
balloon beside its urethra, 12 mm P1, ``tests/test_cavities.py``) with a P1 truth: the tumour
inflated to 40 kPa three times in a row, while a 3 N push on-centre ramps up, holds and
releases. Its group's interpolated truth is checked against direct Newton solves of the summed
load and its repeat against itself one period later. The estimator during a push while a balloon
is inflated, end to end: tests/test_cavities_e2e.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.fem import cavity_volume, fem_from_phantom, force_actuator, probe_matrix, solve_static
from softphantom.virtual import ScenarioError, TruthConfig, load_scenario, scenario_from_dict
from softphantom.virtual import truth as truth_mod
from softphantom.virtual.truth import _patch_radius, pchip_rows, solve_truth, truth_laws

P_KPA = 40.0
FORCE_N = [0.3, 3.0, -0.3]
SCENARIO = {
    "name": "push-while-inflating",
    "duration_s": 7.75,
    "rest_s": 1.5,
    # back to back as breathing: 1.5-3.25, 3.25-5, 5-6.75 s; the push 2-7.5 s, at its peak from 3.25 to 6.75 s
    "inflate": [{"cavity": "tumour", "p_kPa": P_KPA, "start_s": 1.5, "rise_s": 0.75, "hold_s": 0.25,
                 "fall_s": 0.75, "repeat": 3, "period_s": 1.75}],
    "push": [{"point": "on-centre", "start_s": 2.0, "rise_s": 1.25, "hold_s": 3.5, "fall_s": 0.75,
              "force_N": FORCE_N}],
}
LEVELS = 3


@pytest.fixture(scope="module")
def solved(two_cavities_model):
    """(scenario, model, truth, Newton solves the truth took)."""
    model = two_cavities_model
    sc = scenario_from_dict(SCENARIO, "overlap.toml")
    calls = []

    def counting(*a, **k):
        calls.append(1)
        return solve_static(*a, **k)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(truth_mod, "solve_static", counting)
        tr = solve_truth(sc, model, TruthConfig(order=1, levels=LEVELS), truth_mesh=model)
    return sc, model, tr, len(calls)


class Direct:
    """Independent solves of the truth's problem (its mesh, laws, patch) at given loads."""

    def __init__(self, sc, model):
        self.fem = fem_from_phantom(model, truth_laws(model, "neo-hookean"))
        pt = model.p_ext["on-centre"]
        self.H = force_actuator(self.fem, pt, radius=_patch_radius(self.fem, pt, sc.patch_radius_mm * 1e-3))
        self.P = probe_matrix(self.fem, np.array([model.markers[k] for k in model.markers]))
        self.rest = self.P @ self.fem.x_rest.reshape(-1, 3)
        self.tumour = self.fem.cavities["tumour"]
        self.V0 = cavity_volume(self.fem.x_rest.reshape(-1, 3), self.tumour)

    def solve(self, s_push: float, s_inflate: float) -> tuple[np.ndarray, float]:
        """Marker positions (k, 3) m and the tumour's volume change (m³)."""
        f = self.H @ (s_push * np.asarray(FORCE_N)) if s_push else None
        p = {"tumour": s_inflate * P_KPA * 1e3} if s_inflate else None
        sol = solve_static(self.fem, f, pressures=p, tol=1e-10)
        assert sol.converged
        x = sol.x.reshape(-1, 3)
        return self.P @ x, cavity_volume(x, self.tumour) - self.V0


def test_pchip_rows_is_scipys_pchip_row_by_row():
    from scipy.interpolate import PchipInterpolator

    rng = np.random.default_rng(0)
    x = np.array([0.0, 0.2, 0.7, 1.0])
    Y = rng.normal(size=(50, 4, 2))
    Y[:5, :, 0] = np.cumsum(np.abs(Y[:5, :, 0]), axis=1)  # some monotone rows, some not
    q = rng.uniform(-0.1, 1.1, 50)
    want = np.array([PchipInterpolator(x, Y[n], axis=0)(np.clip(q[n], 0, 1)) for n in range(50)])
    assert np.allclose(pchip_rows(x, Y, q), want, rtol=1e-12, atol=1e-12)
    assert np.allclose(pchip_rows(x[[0, -1]], Y[:, [0, -1]], q),  # two nodes: linear, as scipy
                       [PchipInterpolator(x[[0, -1]], Y[n, [0, -1]], axis=0)(np.clip(q[n], 0, 1)) for n in range(50)])


def test_the_group_is_the_direct_solve_of_the_summed_load(solved):
    sc, model, tr, _ = solved
    assert sc.groups == ((0, 1),) and [e.kind for e in sc.events] == ["inflate", "push"]
    (g,) = tr.groups
    d = Direct(sc, model)
    e_in, e_push = tr.scenario.events
    k = tr.model.design.cavity_names.index("tumour")

    def check(t):
        """The group's truth at ``t`` against direct solves at its levels (``a`` inflation, ``b``
        push): its errors in the markers (m) and the tumour's ΔV (m³); the cross term in ΔV (what
        adding the two events' own solves misses) and the markers' shift."""
        a, b = float(e_in.level(t)), float(e_push.level(t))
        s = tr.sample([t])
        (mk, dv), (mk_p, dv_p), (mk_i, dv_i) = d.solve(b, a), d.solve(b, 0.0), d.solve(0.0, a)
        assert abs(dv_i - dv) < 0.02 * dv  # the tumour's ΔV is its inflation's, mostly
        return (np.abs(s.markers[0] - mk).max(), abs(s.dV[0, k] - dv), abs(dv_p + dv_i - dv),
                np.abs(mk - d.rest).max())

    # both at their peaks (4.125 s: the second inflation's hold, the push's): a keyframe of the grid
    assert e_in.level(4.125) == 1.0 and e_push.level(4.125) == 1.0
    s = tr.sample([4.125])
    assert np.allclose(s.force[0], FORCE_N) and s.pressures[0, list(s.cavity_names).index("tumour")] == P_KPA * 1e3
    err_mk, err_dv, cross, shift = check(4.125)
    assert shift > 6e-3  # millimetres of motion
    # the push squeezes the pressurized balloon: measured 1.25 of 145 mm³ ...
    assert 0.002 * 145e-9 < cross < 0.02 * 145e-9
    assert err_dv < 1e-3 * cross and err_mk < 1e-8  # ... the group's truth is the direct solve, not the sum
    # off the grid, both mid-ramp (2.8 s: the first inflation's release at 0.65, the push's rise at
    # 0.71), measured: ΔV off by 0.0025 mm³ (the cross term 0.42), the markers by 12 µm of 5.3 mm
    # (PCHIP on thirds of the push: the push alone at 0.71 is off by 11.8 µm)
    assert 0.6 < e_in.level(2.8) < 0.7 and 0.65 < e_push.level(2.8) < 0.75
    err_mk, err_dv, cross, shift = check(2.8)
    assert err_dv < 0.05 * cross and err_mk < 5e-3 * shift, (err_dv, cross, err_mk, shift)


def test_a_repeat_repeats_exactly_and_costs_no_solve(solved):
    sc, model, tr, n_solves = solved
    e_in = sc.events[0]
    assert e_in.starts_s == (1.5, 3.25, 5.0) and e_in.end_s == 6.75
    # the inflation's three occurrences and the push's ramp: 2 L keyframes, L² for the group
    assert n_solves == 2 * LEVELS + LEVELS**2
    assert [len(et.s) - 1 for et in tr.events] == [LEVELS, LEVELS] and tr.groups[0].solves == LEVELS**2
    # one period apart while the push holds (3.25-6.75 s): the same state, to the bit (dyadic times)
    t = np.arange(3.25, 5.0 + 1e-9, 1 / 64)
    a, b = tr.sample(t), tr.sample(t + 1.75)
    for k in ("force", "pressures", "dV", "markers", "targets"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert np.ptp(a.pressures[:, 1]) == P_KPA * 1e3  # the whole inflation cycle was compared
    # after the last breath the push acts alone (its own truth), then both rest
    after = tr.sample([7.0, 7.625])
    assert after.pressures.max() == 0.0 and np.allclose(after.force[0], e_push_level(sc, 7.0) * np.array(FORCE_N))
    push = tr.events[1]
    assert np.array_equal(after.markers[0], push._interp(push.markers, np.atleast_1d(e_push_level(sc, 7.0)))[0])
    assert np.array_equal(after.markers[1], tr.rest_markers)
    summ = tr.summary()
    assert summ["events"][0]["repeat"] == 3 and summ["events"][0]["period_s"] == 1.75
    (grp,) = summ["groups"]
    assert grp["events"] == ["inflate tumour at 1.5 s", "push at 2 s"] and grp["keyframes"] == LEVELS**2
    assert grp["p_kPa"] == {"tumour": P_KPA} and grp["force_N"] == FORCE_N


def e_push_level(sc, t: float) -> float:
    return float(sc.events[1].level(t))


@pytest.mark.parametrize("events, words", [
    ({"push": [{"start_s": 2, "rise_s": 2, "force_N": [0, 1, 0]}, {"start_s": 3, "rise_s": 2, "force_N": [1, 0, 0]}],
      "inflate": [{"p_kPa": 10, "start_s": 4, "rise_s": 1}]},
     ["three events act at once (push at 2 s, push at 3 s, inflate at 4 s): at most two may overlap"]),
    ({"push": [{"start_s": 2, "rise_s": 2, "force_N": [0, 1, 0]}],
      "inflate": [{"target": "near_urethra", "start_s": 3, "rise_s": 2}]},
     ["inflate.target_shift_mm", "near_urethra", "cannot overlap", "push at 2 s", "p_kPa"]),
    ({"inflate": [{"p_kPa": 10, "start_s": 2, "rise_s": 1, "repeat": 3}]}, ["inflate[0]", "repeat = 3 needs period_s"]),
    ({"push": [{"start_s": 2, "rise_s": 1, "hold_s": 1, "force_N": [0, 1, 0], "repeat": 2, "period_s": 2.5}]},
     ["push[0]", "period_s = 2.5 s is shorter than the event", "3 s"]),
    ({"push": [{"start_s": 2, "rise_s": 1, "force_N": [0, 1, 0], "repeat": 0}]}, ["push[0].repeat = 0", ">= 1"]),
    ({"inflate": [{"p_kPa": 10, "start_s": 2, "rise_s": 1, "repeat": 9, "period_s": 2}]},
     ["inflate.repeat", "ends at 20 s, after duration_s 12"]),
])
def test_refusals_are_one_line(tmp_path, capsys, events, words):
    import tomli_w

    p = tmp_path / "bad.toml"
    p.write_bytes(tomli_w.dumps({"name": "x", "duration_s": 12.0, **events}).encode())
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"{p}: ")
    for w in words:
        assert w in msg, (w, msg)
    assert main(["virtual", "run", "--scenario", str(p), "--model", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err


def test_two_overlapping_events_without_repeats_load_as_before():
    """Non-overlapping scenarios are unchanged (no groups); two pushes at once are a group."""
    one = load_scenario("push-on-centre")
    assert one.groups == () and all(e.repeat == 1 and e.period_s is None for e in one.events)
    two = scenario_from_dict({"name": "x", "duration_s": 9, "push": [
        {"start_s": 2, "rise_s": 1, "force_N": [0, 1, 0]}, {"start_s": 3, "rise_s": 1, "force_N": [0, 1, 0]}]}, "x")
    assert two.groups == ((0, 1),)
    touching = scenario_from_dict({"name": "x", "duration_s": 9, "push": [
        {"start_s": 2, "rise_s": 1, "force_N": [0, 1, 0]}, {"start_s": 4, "rise_s": 1, "force_N": [0, 1, 0]}]}, "x")
    assert touching.groups == ()
