"""The Hermite atlas axis (``AtlasConfig.hermite_axis``): the confluent Chebyshev fit, the exact
derivative every grid solve gives along that axis, and the atlas it makes against converged forward
solves at held-out loads, beside Lagrange atlases of as many points and of about twice as many."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from softphantom.errors import UserError
from softphantom.estimation import AtlasConfig, EstimatorConfig, ForwardModel, build_atlas
from softphantom.estimation.atlas_basis import cheb_basis, lobatto, to_chebyshev
from softphantom.estimation.atlas_map import Atlas
from softphantom.estimation.atlas_store import describe

CFG = EstimatorConfig(contact="on-centre")
# f_y over a range where the map bends (three Lagrange points miss it), the other axes short
BASE = AtlasConfig(force_min_N=(-0.3, -0.3, -0.3), force_max_N=(0.3, 3.0, 0.3), p_min_kPa=0.0, p_max_kPa=2.0,
                   n_force=(3, 3, 3), n_pressure=2)


def _f(a, b, c, d):
    """Degree 7 in b (n = 4 Hermite points determine it), < 3 in a and c, < 2 in d."""
    return (b ** 7 - 2 * b ** 4 + b) * (1 + a - a * a) + c * c * b ** 5 + d * (b ** 6 - c)


def _df_db(a, b, c, d):
    return (7 * b ** 6 - 8 * b ** 3 + 1) * (1 + a - a * a) + 5 * c * c * b ** 4 + 6 * d * b ** 5


def test_hermite_fit_reproduces_a_polynomial_of_degree_2n_minus_1_along_its_axis():
    shape = (3, 4, 3, 2)
    g = np.meshgrid(*[lobatto(n) for n in shape], indexing="ij")
    c = to_chebyshev(_f(*g)[..., None], shape, hermite=(1, _df_db(*g)[..., None]))
    assert c.shape == (3, 8, 3, 2, 1)  # 2n terms along the Hermite axis
    for x in [(0.3, -0.7, 0.45, -0.2), (-0.9, 0.55, -0.1, 0.8)]:
        b = [cheb_basis(t, n)[0] for t, n in zip(x, c.shape[:4])]
        assert np.einsum("i,j,k,l,ijkl->", *b, c[..., 0]) == pytest.approx(_f(*x), abs=1e-12)
    # the values alone (Lagrange, 4 points) do not: the derivatives carry the degree
    lag = to_chebyshev(_f(*g)[..., None], shape)
    b = [cheb_basis(t, n)[0] for t, n in zip((0.3, -0.7, 0.45, -0.2), shape)]
    assert abs(np.einsum("i,j,k,l,ijkl->", *b, lag[..., 0]) - _f(0.3, -0.7, 0.45, -0.2)) > 1e-2
    # a displacement axis: Hermite along the first axis, each line through its own points
    rng = np.random.default_rng(3)
    t0 = g[1].copy()
    t0[1:-1] += rng.uniform(-0.05, 0.05, t0[1:-1].shape)
    swap = (1, 0, 2, 3)  # the Hermite variable first
    vals = _f(*[x.transpose(swap) for x in (g[0], t0, g[2], g[3])])[..., None]
    ders = _df_db(*[x.transpose(swap) for x in (g[0], t0, g[2], g[3])])[..., None]
    c = to_chebyshev(vals, (4, 3, 3, 2), t0.transpose(swap), hermite=(0, ders))
    assert c.shape == (8, 3, 3, 2, 1)
    x = (0.3, -0.7, 0.45, -0.2)
    b = [cheb_basis(t, n)[0] for t, n in zip((x[1], x[0], x[2], x[3]), c.shape[:4])]
    assert np.einsum("i,j,k,l,ijkl->", *b, c[..., 0]) == pytest.approx(_f(*x), abs=1e-12)


def test_the_kernels_evaluate_the_longer_hermite_axis_from_the_coefficients_shape():
    # an atlas whose f_y coefficients are twice its points: the compiled kernels (value and
    # Jacobian) agree with the numpy reference, which reads every coefficient
    cfg = dataclasses.replace(BASE, n_force=(3, 4, 3), hermite_axis=1)
    assert cfg.shape == (3, 4, 3, 2) and cfg.coef_shape == (3, 8, 3, 2)
    rng = np.random.default_rng(5)
    z = np.zeros
    cV = rng.normal(size=(*cfg.coef_shape, 4)) * 0.5 ** np.arange(8)[None, :, None, None, None]
    cP = rng.normal(size=(*cfg.coef_shape, 2, 3))
    at = Atlas(key="ab" * 32, config=cfg, cV=cV, cP=cP, cF=z((*cfg.coef_shape, 1)), modes=z((6, 1)), x_rest=z(6),
               build_s=0.0, solves=72, field_rms_m=0.0, solved=np.ones(cfg.shape, bool))
    lam = np.array([0.1, 2.2, -0.15, 700.0])
    V, J = at.volumes(lam)
    Vr, Jr = at.volumes_reference(lam)
    assert np.allclose(V, Vr, rtol=1e-12, atol=1e-12) and np.allclose(J, Jr, rtol=1e-12, atol=1e-12)
    assert np.allclose(at.points(lam).ravel(), at.value_reference(cP.reshape(*cfg.coef_shape, 6), lam), atol=1e-12)
    assert dict(describe(at))["grid"].endswith("first axis force, Hermite along f_y (8 terms)")


def test_the_hermite_axis_is_in_the_key_only_when_set_and_needs_a_force_axis():
    assert "hermite_axis" not in AtlasConfig().as_dict()  # an atlas without it keeps its key
    assert AtlasConfig(hermite_axis=0).as_dict()["hermite_axis"] == 0
    # the default stretch of f_x counts the polynomial's terms: 5 Hermite points are 10
    assert AtlasConfig(n_force=(5, 9, 4), hermite_axis=0).cluster_N[0] > 0
    assert AtlasConfig(n_force=(5, 9, 4)).cluster_N[0] == 0
    assert AtlasConfig(n_force=(11, 2, 4), hermite_axis=1).shape == (11, 2, 4, 3)
    for kw, msg in [({"hermite_axis": 4}, "hermite_axis: None or an axis index 0..3"),
                    ({"hermite_axis": 1, "x_control": "displacement"},
                     "hermite_axis needs x_control 'force' or axis 0"),
                    ({"hermite_axis": 0, "offline": "rom"}, "hermite_axis needs offline 'full'"),
                    ({"hermite_axis": 1, "n_force": (2, 9, 4)},
                     r"n_force: each must be an integer in 3..15 \(2..15 on")]:
        with pytest.raises(UserError, match=msg):
            AtlasConfig(**kw)


@pytest.fixture(scope="module")
def fwd(coarse_model):
    return ForwardModel(coarse_model, CFG)


def _build(model, cfg):
    return build_atlas(model, CFG, cfg, n_workers=1, processes=False)


@pytest.mark.slow
def test_the_exact_derivative_along_the_axis_is_the_solves_at_every_grid_point(coarse_model, fwd):
    # on a stretched f_x axis (the chain rule through asinh): the atlas's ∂/∂f_x at a grid point
    # is the converged solve's sensitivity there, which a Lagrange fit only approximates
    cfg = dataclasses.replace(BASE, force_max_N=(0.3, 1.0, 0.3), force_cluster_N=(0.1, 0.0, 0.0), hermite_axis=0)
    at = _build(coarse_model, cfg)
    lag = _build(coarse_model, dataclasses.replace(cfg, hermite_axis=None))
    ax = cfg.axes()
    for idx in [(1, 2, 0, 1), (2, 1, 1, 0)]:
        lam = np.array([a[i] for a, i in zip(ax, idx)])
        lin = fwd.solve(lam)  # exact sensitivities: the forward model's own GMRES/factor at the solution
        scale = np.abs(lin.W[:, 0]).max()
        V, J = at.volumes(lam)
        assert np.allclose(V, lin.V, rtol=0, atol=1e-6 * np.abs(lin.V).max())
        assert np.allclose(J[:, 0], lin.W[:, 0], rtol=0, atol=1e-5 * scale)
        assert np.abs(lag.volumes(lam)[1][:, 0] - lin.W[:, 0]).max() > 1e-3 * scale
        dP = (at.points(lam + [1e-4, 0, 0, 0]) - at.points(lam - [1e-4, 0, 0, 0])) / 2e-4
        assert np.allclose(dP, lin.sub_U[:, :, 0], rtol=0, atol=1e-4 * np.abs(lin.sub_U[:, :, 0]).max())


@pytest.mark.slow
def test_a_hermite_axis_of_n_points_is_as_good_as_a_lagrange_axis_of_2n_minus_1(coarse_model, fwd):
    # held-out loads off the grid along f_y, on grid points of the other axes (where every fit is
    # exact): the error is the f_y interpolation's, against converged solves
    rng = np.random.default_rng(11)
    ax = BASE.axes()
    held = [fwd.solve(np.array([ax[0][rng.integers(3)], f_y, ax[2][rng.integers(3)], ax[3][rng.integers(2)]]))
            for f_y in rng.uniform(-0.2, 2.9, 6)]

    def errors(cfg):
        at = _build(coarse_model, cfg)
        return np.array([max(np.abs(at.volumes(h.lam)[0] - h.V).max() for h in held),
                         max(np.abs(at.points(h.lam) - h.sub_x).max() for h in held),
                         max(np.abs(at.nodes(h.lam) - h.x.reshape(-1, 3)).max() for h in held)])

    h3 = errors(dataclasses.replace(BASE, hermite_axis=1))
    l3 = errors(BASE)
    l5 = errors(dataclasses.replace(BASE, n_force=(3, 5, 3)))
    # measured: volumes 0.0009 / 0.0007 / 0.067 mm³, points 0.0007 / 0.0005 / 0.054 mm; the field
    # 0.025 / 0.023 / 0.058 mm, where the POD truncation (FIELD_RTOL) bounds all three
    assert np.all(h3 <= 1.5 * l5), (h3, l5)
    assert np.all(h3[:2] <= 0.05 * l3[:2]), (h3, l3)
    assert h3[2] <= 0.5 * l3[2], (h3, l3)


@pytest.mark.slow
def test_a_hermite_displacement_axis_beats_a_lagrange_one_of_2n_minus_1_points(coarse_model, fwd):
    # along the patch displacement q over ±1.5 N of f_x (the arm pair's step at f_x = 0 inside),
    # held-out f_x on grid points of the other axes, through the atlas's own coords(force)
    base = dataclasses.replace(BASE, force_min_N=(-1.5, -0.3, -0.3), force_max_N=(1.5, 1.5, 0.3),
                               x_control="displacement")
    rng = np.random.default_rng(7)
    ax = base.axes()
    held = [fwd.solve(np.array([f_x, ax[1][rng.integers(3)], ax[2][rng.integers(3)], ax[3][rng.integers(2)]]))
            for f_x in rng.uniform(-1.4, 1.4, 6)]

    def errors(cfg):
        at = _build(coarse_model, cfg)
        lams = [at.coords(h.lam[:3], h.lam[3]) for h in held]
        assert all(np.allclose(at.forces(lam), h.lam[:3], atol=1e-9) for lam, h in zip(lams, held))
        return np.array([max(np.abs(at.volumes(lam)[0] - h.V).max() for lam, h in zip(lams, held)),
                         max(np.abs(at.points(lam) - h.sub_x).max() for lam, h in zip(lams, held))])

    h3 = errors(dataclasses.replace(base, hermite_axis=0))
    l3 = errors(base)
    l5 = errors(dataclasses.replace(base, n_force=(5, 3, 3)))
    # measured: volumes 0.011 / 0.018 / 0.20 mm³, points 0.007 / 0.026 / 0.31 mm (H3 / L5 / L3)
    assert np.all(h3 <= l5), (h3, l5)
    assert np.all(h3 <= 0.1 * l3), (h3, l3)
