"""A phantom of N >= 3 sensing arms, named by its design: validated, meshed, solved and estimated
(refresh and atlas) with the arms' names and count taken from the design; the BIP's four arms keep
their files, ids and results."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from softphantom.design import BIPDesign, build_model
from softphantom.design.mesh import cavity_group_ids, region_ids
from softphantom.design.params import ARM_NAMES, design_from_dict, design_to_dict
from softphantom.errors import DesignError

THREE = {"arm_names": ["front_zpos", "front_zneg", "back_xpos"]}
FIVE = {"arm_names": [*ARM_NAMES, "top"], "arms": {"top": {"direction": [0.0, 0.6, 1.0], "cavity_volume_mm3": 486.0}}}


def test_the_bip_file_and_ids_are_unchanged():
    d = design_to_dict(BIPDesign())
    assert "arm_names" not in d and list(d["arms"]) == list(ARM_NAMES)
    assert region_ids() == {"bulb": 1, "arm_front_zpos": 2, "arm_front_zneg": 3, "arm_back_xpos": 4, "arm_back_xneg": 5}
    assert cavity_group_ids() == {"front_zpos": 11, "front_zneg": 12, "back_xpos": 13, "back_xneg": 14, "urethra": 15}
    # ids stay clear of the shell (6), the fixed and outer faces (21, 22) and the lesions (31…)
    ids = [*region_ids([f"a{i}" for i in range(12)]).values(), *cavity_group_ids([f"a{i}" for i in range(12)]).values()]
    assert len(set(ids)) == len(ids) and not set(ids) & {6, 21, 22, *range(31, 100)}


def test_a_design_of_three_or_five_named_arms_round_trips_through_its_file():
    for spec in (THREE, FIVE):
        d = design_from_dict(spec)
        assert list(d.arm_names) == spec["arm_names"] and d.cavity_names[-1] == "urethra"
        assert len(d.sensors.gains) == len(d.arms)  # the datasheet's, one per arm
        assert design_to_dict(d)["arm_names"] == spec["arm_names"]
        assert design_from_dict(design_to_dict(d)) == d
        assert d.region_groups()["arms"] == tuple(f"arm_{n}" for n in d.arm_names)


@pytest.mark.parametrize("spec, field", [
    ({"arm_names": ["front_zpos", "front_zneg"]}, "arms: 2 given"),
    ({"arm_names": ["front_zpos", "front_zneg", "front_zpos"]}, "arms.front_zpos: two arms"),
    ({"arm_names": ["front_zpos", "front_zneg", "urethra"]}, "arms.urethra: an arm's name"),
    ({"arm_names": [*ARM_NAMES, "top"]}, "arms.top.direction: missing"),
    ({"arms": {"top": {"direction": [0, 1, 0], "cavity_volume_mm3": 400.0}}}, "arms.top: not one of the design's arms"),
    ({"arm_names": "front_zpos"}, "arm_names: expected a list"),
    ({**THREE, "sensors": {"gains": [1.0, 1.1, 1.0, 1.0]}}, "sensors.gains: 4 given for 3 arms"),
])
def test_a_bad_arm_layout_is_one_line_naming_the_field(spec, field):
    with pytest.raises(DesignError) as e:
        design_from_dict(spec)
    assert str(e.value).startswith(field) and "\n" not in str(e.value), str(e.value)


@pytest.fixture(scope="module")
def models(five_arms_model):
    """The three- and five-arm designs meshed at 12 mm (linear), once for the module (the five-arm
    one once per run: conftest's ``five_arms_model``, test_live reads it too)."""
    return {3: build_model(design_from_dict(THREE), 12.0, isolate=False), 5: five_arms_model}


@pytest.mark.slow
@pytest.mark.parametrize("spec", [THREE, FIVE], ids=["3 arms", "5 arms"])
def test_n_arms_mesh_solve_and_the_estimators_recover_the_load(spec, models):
    from softphantom.estimation import AtlasConfig, Estimator, EstimatorConfig
    from softphantom.estimation.atlas.build import build_atlas
    from softphantom.estimation.atlas.estimator import AtlasEstimator
    from softphantom.estimation.observability import observability

    d = design_from_dict(spec)
    m = models[len(d.arms)]
    assert m.design.arm_names == d.arm_names
    n = len(d.arms)
    assert list(m.cavities) == [*d.arm_names, "urethra"] and len(m.regions) == n + 1
    assert all(m.cavity_volume(a) > 0 for a in d.arm_names)
    est = Estimator(m, EstimatorConfig(mode="sync"))
    assert est.arm_names == d.arm_names and est.rest.W.shape == (n, 4)
    lam = np.array([0.3, 2.0, -0.2, 0.0])
    lin = est.forward.solve(lam)
    assert lin.V.shape == (n,)
    sample = SimpleNamespace(t=0.0, dV=lin.V, p_urethra=0.0, status="ok")
    e = est.settle(sample)  # the refresh estimator's exact inverse: the load itself
    assert e.status == "ok" and np.allclose(e.force, lam[:3], atol=1e-5), e.force
    assert e.volume_meas.shape == (n,)
    bad = est.step(SimpleNamespace(t=0.1, dV=lin.V[:-1], p_urethra=0.0, status="ok"))
    assert bad.status == f"rejected:dV shape ({n - 1},)"
    # observability: the force block has full rank with any of these layouts
    o = observability(m, forward=est.forward, loaded=False)
    assert o.rest.J.shape == (n, 4) and o.rest.sv_force_mm3[-1] > 0.3 * o.rest.sv_force_mm3[0]
    if n == 5:  # the atlas estimator's compiled inverse on n rows: a small atlas, within its interpolation error
        acfg = AtlasConfig(force_min_N=(-1, -0.5, -1), force_max_N=(1, 2.5, 1), p_min_kPa=-2, p_max_kPa=2,
                           n_force=(3, 4, 3), n_pressure=2, linear_pressure=True)
        atlas = build_atlas(m, est.config, acfg, n_workers=1, processes=False)
        at = AtlasEstimator(m, EstimatorConfig(mode="sync"), atlas)
        assert at.atlas.cV.shape[-1] == n
        e = at.step(sample)
        assert e.status == "ok" and np.allclose(e.force, lam[:3], atol=0.05), e.force


def test_mesh_png_colours_and_lists_the_designs_own_arms_and_cavities(models, tmp_path, monkeypatch):
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_hex

    from softphantom.viz.mesh_view import model_colours, render_mesh_png

    model = models[5]
    figs = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig))
    render_mesh_png(model, tmp_path / "mesh.png")
    labels = [t.get_text() for t in figs[0].legends[0].get_texts()]
    assert labels[:len(model.regions)] == list(model.regions) and "arm_top" in labels
    assert [f"cavity {c}" for c in model.cavities] == labels[len(model.regions):len(model.regions) + len(model.cavities)]
    regions, cavities = model_colours(model)
    assert len(set(regions.values())) == len(regions) and "#bbbbbb" not in regions.values()  # grey: no colour
    assert len(set(cavities.values())) == len(cavities)
    # the whole view draws each cavity in its legend colour
    drawn = {to_hex(c.get_facecolor()[0]) for c in figs[0].axes[0].collections if len(c.get_facecolor())}
    assert set(cavities.values()) <= drawn
