"""The atlas of a design with two actuated internal cavities: a stack of 4-D atlases over the
second pressure's levels (``AtlasConfig.further_min_kPa``, ``AtlasStack``), against independent
full solves (``ForwardModel.solve`` of the whole λ) at held-out loads off the level nodes; exact
at a level node; stored one file per level by key; resumed from its kept tasks; the estimator on
it recovers the force from both measured pressures.

The model is the BIP with a tumour balloon beside its urethra (tests/test_cavities.py), coarser, its
cavities ordered (tumour, urethra): p_1 the tumour's (the atlas's own pressure axis), p_2 the
urethra's (the levels). The arms feel the urethra's pressure ≈ 5e-3 mm³/kPa each, 15× the
tumour's: over 0–40 kPa, ignoring p_2 costs a force error several times the interpolation's.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import numpy as np
import pytest
from test_cavities import TUMOUR

from softphantom.design.model import build_model
from softphantom.design.params import design_from_dict
from softphantom.errors import UserError
from softphantom.estimation import AtlasConfig, EstimatorConfig
from softphantom.estimation.atlas.build import build_atlas, check_atlas_cavities
from softphantom.estimation.atlas.catalogue import load_or_build
from softphantom.estimation.atlas.estimator import AtlasEstimator
from softphantom.estimation.atlas.map import AtlasStack, MixedPiece, lagrange_weights
from softphantom.estimation.atlas.catalogue import atlas_key
from softphantom.estimation.atlas.store import atlas_path
from softphantom.estimation.forward import ForwardModel
from softphantom.records import ChannelLayout

MESH = {"size_mm": 12.0, "surface_size_mm": 12.0, "arm_size_mm": 9.0, "cavity_segments": 12.0}
CFG = EstimatorConfig(mode="sync")
# 3 × 3 × 3 force points, p_1 (tumour) on its tangent line at 4 kPa, p_2 (urethra) at 0, 20, 40 kPa:
# 81 solves, 13 CPU-s
ACFG = AtlasConfig(force_min_N=(-0.4, 0.4, -0.4), force_max_N=(0.4, 1.6, 0.4), p_min_kPa=-2.0, p_max_kPa=10.0,
                   n_force=(3, 3, 3), n_pressure=2, linear_pressure=True, further_min_kPa=(0.0,),
                   further_max_kPa=(40.0,), n_further=3)
# held-out loads strictly inside, both pressures non-zero, p_2 off the levels
LOADS = [np.array(v) for v in ([0.21, 1.3, -0.27, 6e3, 33.7e3], [-0.23, 0.7, 0.18, -1e3, 12.3e3],
                               [0.05, 1.1, 0.31, 3e3, 26.2e3])]
# measured at these loads: volumes within 0.010 mm³ (0.083–0.31 with p_2 ignored), points 0.013 mm,
# field 0.017 mm, the estimated force 0.0023 N (0.007–0.021 N with p_2 ignored); about twice that as
# the bounds. Of the volumes' error the levels' own part (p_2 between levels, at a force node) is 0.006 mm³.
VOL_TOL_MM3, PTS_TOL_MM, F_TOL_N, LEVELS_TOL_MM3 = 0.02, 0.025, 0.005, 0.012


@functools.cache
def _model():
    return build_model(design_from_dict({"urethra": {}, "cavities": {"tumour": TUMOUR},
                                         "cavity_names": ["tumour", "urethra"], "mesh": MESH}), isolate=False)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The stack built with its tasks kept in a model directory (not yet saved), and the full solves."""
    d = tmp_path_factory.mktemp("stack_model")
    m = _model()
    fwd = ForwardModel(m, CFG)
    st = build_atlas(m, CFG, ACFG, n_workers=1, processes=False, fwd=fwd, cache_dir=d)
    return SimpleNamespace(model=m, fwd=fwd, stack=st, dir=d, lins=[fwd.solve(lam) for lam in LOADS])


def test_the_stack_config_levels_and_refusals():
    assert [c.held_kPa for c in ACFG.levels()] == [(0.0,), (20.0,), (40.0,)]
    assert ACFG.n_solves == 3 * 27 and len(ACFG.pieces()) == 3
    # an atlas of one pressure keeps the fields (and so the cache key) it had before stacks
    assert set(AtlasConfig().as_dict()) == {"force_min_N", "force_max_N", "p_min_kPa", "p_max_kPa", "n_force",
                                            "n_pressure", "linear_pressure", "force_cluster_N", "x_control"}
    assert "held_kPa" in ACFG.levels()[1].as_dict() and "further_min_kPa" not in ACFG.levels()[1].as_dict()
    two = AtlasConfig(n_further=(3, 5), further_min_kPa=(0, -1), further_max_kPa=(20, 5))
    assert len(two.levels()) == 15 and two.levels()[5].held_kPa == (10.0, -1.0)  # C order: the last fastest
    assert AtlasConfig(p_max_kPa=25).for_cavities(2).further_max_kPa == (25.0,)
    for kw, msg in (({"further_min_kPa": (0,), "further_max_kPa": (0,)}, "one range min < max"),
                    ({"further_min_kPa": (0,), "further_max_kPa": (9,), "n_further": 0}, "n_further: an integer"),
                    ({"further_min_kPa": (0,), "further_max_kPa": (9,), "held_kPa": (1,)}, "not both"),
                    ({"further_min_kPa": (0,), "further_max_kPa": (9,), "x_control": "displacement"},
                     "x_control 'displacement'")):
        with pytest.raises(UserError, match=msg):
            AtlasConfig(**kw)
    with pytest.raises(UserError, match=r"^atlas further_min_kPa: one per actuated cavity after the first \(2\), "
                                        r"got 1$"):
        ACFG.for_cavities(3)


def test_the_levels_interpolate_the_second_pressure():
    # Lagrange on the Lobatto levels: exact for a quadratic in p_2, a unit vector at a node
    nodes = ACFG.further_axes()[0]
    f = lambda p: 3.0 - 2e-4 * p + 5e-9 * p ** 2  # noqa: E731
    for p in (4.3e3, 13.7e3, 40e3):
        assert lagrange_weights(p, nodes) @ f(nodes) == pytest.approx(f(p), rel=1e-12)
    assert lagrange_weights(20e3, nodes).tolist() == [0.0, 1.0, 0.0]


@pytest.mark.slow
def test_the_stack_matches_full_solves_off_its_levels(built):
    st, fwd = built.stack, built.fwd
    assert isinstance(st, AtlasStack) and [lv.config.held_kPa for lv in st.levels] == [(0.0,), (20.0,), (40.0,)]
    assert all(lv.key == atlas_key(fwd.model, fwd.config, c) for lv, c in zip(st.levels, ACFG.levels()))
    assert len(set(st.key)) == 3 and st.unsolved == 0
    for lam, lin in zip(LOADS, built.lins):
        V, J = st.volumes(lam)
        assert isinstance(st.piece(lam), MixedPiece) and J.shape == (4, 4)
        assert np.abs(V - lin.V).max() * 1e9 < VOL_TOL_MM3
        assert np.abs(st.points(lam) - lin.sub_x).max() * 1e3 < PTS_TOL_MM
        assert np.abs(st.nodes(lam).ravel() - lin.x).max() * 1e3 < 1.2 * PTS_TOL_MM
        # without p_2 (the level at 0 kPa) the volumes miss by the urethra's share
        miss = np.abs(st.volumes(np.r_[lam[:4], 0.0])[0] - lin.V).max() * 1e9
        assert miss > 3 * VOL_TOL_MM3, miss
    # the levels' own part of the error: p_2 between levels at a node of every level's force axes
    # and p_1 at its tangent line's point, where each level is exact
    node = np.array([0.0, 0.4, 0.0, 4e3, 33.7e3])
    assert np.abs(st.volumes(node)[0] - fwd.solve(node).V).max() * 1e9 < LEVELS_TOL_MM3


@pytest.mark.slow
def test_at_a_level_node_the_stack_is_that_level(built):
    st = built.stack
    lam = np.array([0.21, 1.3, -0.27, 6e3, 20e3])
    assert st.piece(lam) is st.levels[1]
    V, J = st.volumes(lam)
    V1, J1 = st.levels[1].volumes(lam[:4])
    assert np.array_equal(V, V1) and np.array_equal(J, J1)
    assert np.array_equal(st.points(lam), st.levels[1].points(lam[:4]))
    # and the mixture itself, weights (0, 1, 0), is that level's polynomial to the bit
    mixed = MixedPiece([(0.0, st.levels[0]), (1.0, st.levels[1]), (0.0, st.levels[2])])
    assert np.array_equal(mixed.volumes(lam[:4])[0], V1)


@pytest.mark.slow
def test_the_estimator_recovers_the_force_from_both_pressures(built):
    est = AtlasEstimator(built.model, CFG, built.stack)
    assert est.cavity == "tumour" and est.cavities == ("tumour", "urethra") and est.lam.shape == (5,)

    def sample(lin, p1, p2, t=0.0):
        return SimpleNamespace(t=t, dV=lin.V, p_urethra=p2, pressures_Pa={"tumour": p1, "urethra": p2}, status="ok")

    worst, worst_ignored = 0.0, 0.0
    for lam, lin in zip(LOADS, built.lins):
        est.reset()
        e = est.step(sample(lin, lam[3], lam[4]))
        assert e.status == "ok" and e.in_envelope
        assert e.pressures_Pa == {"tumour": lam[3], "urethra": lam[4]}
        assert np.allclose(est.lam, [*e.force, lam[3], lam[4]])
        worst = max(worst, np.abs(e.force - lam[:3]).max())
        ref = est.step_reference(sample(lin, lam[3], lam[4]))
        assert np.allclose(ref.force, e.force, atol=1e-9)
        est.reset()
        ignored = est.step(sample(lin, lam[3], 0.0))  # p_2 taken as 0
        worst_ignored = max(worst_ignored, np.abs(ignored.force - lam[:3]).max())
    assert worst < F_TOL_N, worst
    assert worst_ignored > 4 * worst and worst_ignored > F_TOL_N, (worst, worst_ignored)
    # a second pressure beyond the levels' range: clamped to it, outside the envelope
    off = est.step(sample(built.lins[0], LOADS[0][3], 45e3))
    assert off.status == "ok" and not off.in_envelope and off.pressures_Pa["urethra"] == 45e3


@pytest.mark.slow
def test_the_stack_is_stored_per_level_and_resumes(built, monkeypatch):
    import softphantom.estimation.atlas.build as build_mod

    m, fwd, d = built.model, built.fwd, built.dir
    # the tasks kept by the fixture's build: built again, nothing is solved
    again = build_atlas(m, CFG, ACFG, n_workers=1, processes=False, fwd=fwd, cache_dir=d)
    for a, b in zip(again.levels, built.stack.levels):
        assert a.provenance["build"]["kept_tasks"] == a.provenance["build"]["tasks"] == 9  # the levels' graph
        assert np.array_equal(a.cV, b.cV)
    # saved one file per level, named by the level's key; loaded back without a build
    st = load_or_build(m, CFG, ACFG, cache_dir=d, fwd=fwd, n_workers=1)
    assert sorted(p.name for p in (d / "atlas").glob("*.npz")) == sorted(
        atlas_path(d, atlas_key(fwd.model, fwd.config, c)).name for c in ACFG.levels())
    monkeypatch.setattr(build_mod, "build_atlas", lambda *a, **k: pytest.fail("built"))
    back = load_or_build(m, CFG, ACFG, cache_dir=d, fwd=fwd)
    assert isinstance(back, AtlasStack) and back.key == st.key
    lam = LOADS[0]
    assert np.allclose(back.volumes(lam)[0], built.stack.volumes(lam)[0], rtol=0, atol=1e-15)


@pytest.mark.slow
def test_an_atlas_and_a_model_of_other_pressures_are_refused(built):
    with pytest.raises(UserError, match=r"^atlas of 1 internal pressure, the model has 2 actuated cavities "
                                        r"\(tumour, urethra\); rebuild it$"):
        AtlasEstimator(built.model, CFG, built.stack.levels[0])
    none = SimpleNamespace(layout=ChannelLayout(("a", "b", "c")))  # no actuated cavity
    with pytest.raises(UserError, match=r"^cavities: the atlas tabulates at least one internal pressure; this design "
                                        r"has 0: use --estimator refresh$"):
        check_atlas_cavities(none)


@pytest.mark.slow
def test_one_level_holds_a_pressure_that_stays_near_it(built):
    # n_further 1: the level at the range's middle, the atlas constant in p_2 across the range
    # (the demo's cavities that stay at rest)
    one = AtlasConfig(**{**ACFG.__dict__, "further_min_kPa": (10.0,), "further_max_kPa": (30.0,), "n_further": 1})
    assert [c.held_kPa for c in one.levels()] == [(20.0,)] and one.n_solves == 27
    st = AtlasStack(one, (built.stack.levels[1],))
    est = AtlasEstimator(built.model, CFG, st)
    lin = built.lins[0]
    e = []
    for p2 in (20e3, 26e3, 31e3):
        est.reset()
        e.append(est.step(SimpleNamespace(t=0.0, dV=lin.V, p_urethra=p2, pressures_Pa={"tumour": 6e3, "urethra": p2},
                                          status="ok")))
    assert np.array_equal(e[0].force, e[1].force) and e[0].in_envelope and e[1].in_envelope
    assert not e[2].in_envelope


@pytest.mark.slow
def test_the_held_out_check_takes_a_stack(built):
    # `softphantom atlas check`'s rows at (3 + M)-loads: the map and its inverse against full solves
    from softphantom.estimation.atlas.check import check_held_out, held_out_loads

    c = ACFG
    L = held_out_loads(np.r_[c.lower, 0.0], np.r_[c.upper, 40e3], 2, seed=3)
    assert L.shape == (2, 5)
    res = check_held_out(built.model, CFG, built.stack, L)
    w = res.worst()
    assert len(res.loads) + res.skipped == 2 and not res.failed
    assert w["dV_mm3"] < VOL_TOL_MM3 and w["points_mm"] < PTS_TOL_MM and w["force_N"] < 3 * F_TOL_N, w
