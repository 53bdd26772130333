"""The Hermite atlas axis (``AtlasConfig.hermite_axis``): the confluent Chebyshev fit (exact on
polynomials of degree 2n − 1) and the exact derivative every grid solve gives along that axis. The
atlas it makes against converged forward solves at held-out loads, beside its Lagrange twin, is
``benchmarks/bench_interpolants.py``'s (``make bench`` runs its ``--quick`` checks)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from softphantom.errors import UserError
from softphantom.estimation import AtlasConfig, EstimatorConfig, ForwardModel, build_atlas
from softphantom.estimation.atlas.basis import cheb_basis, lobatto, to_chebyshev
from softphantom.estimation.atlas.map import Atlas
from softphantom.estimation.atlas.store import describe

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


def test_the_hermite_axis_is_in_the_key_only_when_set_and_needs_full_solves():
    assert "hermite_axis" not in AtlasConfig().as_dict()  # an atlas without it keeps its key
    assert AtlasConfig(hermite_axis=0).as_dict()["hermite_axis"] == 0
    # the default stretch of f_x counts the polynomial's terms: 5 Hermite points are 10
    assert AtlasConfig(n_force=(5, 9, 4), hermite_axis=0).cluster_N[0] > 0
    assert AtlasConfig(n_force=(5, 9, 4)).cluster_N[0] == 0
    assert AtlasConfig(n_force=(11, 2, 4), hermite_axis=1).shape == (11, 2, 4, 3)
    assert AtlasConfig(n_pressure=2, hermite_axis=3, x_control="displacement").coef_shape == (11, 9, 4, 4)
    for kw, msg in [({"hermite_axis": 4}, "hermite_axis: None or an axis index 0..3"),
                    ({"hermite_axis": 0, "offline": "rom"}, "hermite_axis needs offline 'full'"),
                    ({"hermite_axis": 1, "n_force": (2, 9, 4)},
                     r"n_force: each must be an integer in 3..15 \(2..15 on")]:
        with pytest.raises(UserError, match=msg):
            AtlasConfig(**kw)


@pytest.fixture(scope="module")
def fwd(coarse_model):
    return ForwardModel(coarse_model, CFG)


def _bench():
    """benchmarks/bench_interpolants.py as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[1] / "benchmarks" / "bench_interpolants.py"
    spec = importlib.util.spec_from_file_location("bench_interpolants", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _build(model, cfg, **kw):
    return build_atlas(model, CFG, cfg, n_workers=1, processes=False, **kw)


@pytest.fixture(scope="module")
def h3(coarse_model):
    """BASE with f_y Hermite (3 points, 6 terms)."""
    return _build(coarse_model, dataclasses.replace(BASE, hermite_axis=1))


def _lagrange_twin(at):
    """The Lagrange atlas of the grid solves that made the Hermite atlas ``at`` (the benchmark's, which
    compares the two at held-out solves)."""
    return _bench().lagrange_twin(at)


@pytest.mark.slow
def test_the_exact_derivative_along_the_axis_is_the_solves_at_every_grid_point(h3, fwd):
    # the atlas's ∂/∂f_y at a grid point is the converged solve's sensitivity there, which a
    # Lagrange fit only approximates
    ax = BASE.axes()
    l3 = _lagrange_twin(h3)
    for idx in [(1, 2, 0, 1), (2, 1, 1, 0)]:
        lam = np.array([a[i] for a, i in zip(ax, idx)])
        lin = fwd.solve(lam)  # exact sensitivities: the forward model's own GMRES/factor at the solution
        scale = np.abs(lin.W[:, 1]).max()
        V, J = h3.volumes(lam)
        assert np.allclose(V, lin.V, rtol=0, atol=1e-6 * np.abs(lin.V).max())
        assert np.allclose(J[:, 1], lin.W[:, 1], rtol=0, atol=1e-5 * scale)
        assert np.abs(l3.volumes(lam)[1][:, 1] - lin.W[:, 1]).max() > 1e-3 * scale
        dP = (h3.points(lam + [0, 1e-4, 0, 0]) - h3.points(lam - [0, 1e-4, 0, 0])) / 2e-4
        assert np.allclose(dP, lin.sub_U[:, :, 1], rtol=0, atol=1e-4 * np.abs(lin.sub_U[:, :, 1]).max())


def test_the_derivative_along_a_stretched_axis_goes_through_the_stretch(coarse_model, fwd, monkeypatch):
    # a map with known derivatives in place of the FEM (as test_atlas's stand-ins): on f_x stretched
    # by asinh the Hermite atlas's values and ∂/∂f_x at every grid point are the map's (the chain
    # rule through the stretch, to the Chebyshev variable and back); a Lagrange atlas's ∂/∂f_x is not
    from types import SimpleNamespace

    rng = np.random.default_rng(13)
    A = rng.normal(size=(4, 4)) * np.array([1e-9, 1e-9, 1e-9, 1e-12])  # m³ per N, m³ per Pa
    B = rng.normal(size=(fwd.fem.n_dof, 4)) * np.array([1e-4, 1e-4, 1e-4, 1e-7])
    c = rng.normal(size=4) * 1e-9  # m³: a step in f_x 0.1 N wide (the arm pair's, in miniature)
    bend = rng.normal(size=fwd.fem.n_dof) * 1e-4

    def volumes(lam):
        return A @ lam + c * np.tanh(lam[0] / 0.1)

    def x_of(lam):
        return fwd.fem.x_rest + B @ lam + bend * np.tanh(lam[0] / 0.1)

    def exact_column(lin, a):  # ∂/∂f_x
        assert a == 0
        s = 1 / 0.1 / np.cosh(lin.lam[0] / 0.1) ** 2
        dx = B[:, 0] + bend * s
        return A[:, 0] + c * s, fwd.probe @ dx.reshape(-1, 3), dx

    class Stepped:  # stands in for the FEM
        def __init__(self, model, config, **kw):
            self.probe, self.fem = fwd.probe, fwd.fem
            self.eq = SimpleNamespace(keep=lambda: None, restore=lambda kept: None, exact_column=exact_column,
                                      arm_names=fwd.eq.arm_names)

        def solve(self, lam, start=None, factor_at_solution=False, via_tol=None):
            lam = np.asarray(lam, float)
            x = x_of(lam)
            return SimpleNamespace(V=volumes(lam), x=x, sub_x=fwd.probe @ x.reshape(-1, 3), lam=lam)

    cfg = dataclasses.replace(BASE, force_min_N=(-0.3, -0.3, -0.3), force_max_N=(0.5, 1.0, 0.3),
                              force_cluster_N=(0.1, 0.0, 0.0), hermite_axis=0)
    # in the module whose solves this build_atlas runs (the doctest collection may import a second copy)
    monkeypatch.setitem(build_atlas.__globals__["_sweep"].__globals__, "ForwardModel", Stepped)
    at = _build(coarse_model, cfg, fwd=fwd)
    lag = _build(coarse_model, dataclasses.replace(cfg, hermite_axis=None), fwd=fwd)
    worst_lag = 0.0
    for lam in np.stack(np.meshgrid(*cfg.axes(), indexing="ij"), axis=-1).reshape(-1, 4):
        dV, dP, _ = exact_column(SimpleNamespace(lam=lam), 0)
        V, J = at.volumes(lam)
        assert np.allclose(V, volumes(lam), rtol=0, atol=1e-9 * np.abs(c).max())
        assert np.allclose(J[:, 0], dV, rtol=0, atol=1e-9 * np.abs(dV).max()), lam
        worst_lag = max(worst_lag, np.abs(lag.volumes(lam)[1][:, 0] - dV).max() / np.abs(dV).max())
        fd = (at.points(lam + [1e-6, 0, 0, 0]) - at.points(lam - [1e-6, 0, 0, 0])) / 2e-6
        assert np.allclose(fd, dP, rtol=0, atol=1e-5 * np.abs(dP).max())
    assert worst_lag > 0.05, worst_lag


@pytest.mark.slow
def test_a_displacement_atlas_derivative_along_another_load_is_at_fixed_q(coarse_model, fwd, axis=3):
    # the Hermite data along p_u (the load whose vector moves with the state; f_z passes the same
    # check) of a displacement atlas: at an inner grid point, the atlas's
    # ∂/∂λ_a at fixed q against central differences of mixed-control solves at λ_a ± ε, each at the
    # patch displacement its own faces put that q at (q mixes the faces' ū, which move with λ_a)
    from softphantom.estimation.atlas.build import _solve_ux, x_patch

    cfg = dataclasses.replace(BASE, force_min_N=(-0.6, -0.3, -0.3), force_max_N=(0.6, 1.5, 0.3),
                              n_force=(3, 3, 2 if axis == 2 else 3), x_control="displacement", hermite_axis=axis)
    at = _build(coarse_model, cfg)
    ax, h = cfg.axes(), x_patch(fwd)
    i, j, k, l = 1, 2, 1, 0
    lam = np.array([at.q_nodes[i, j, k, l], ax[1][j], ax[2][k], ax[3][l]])
    t = (lam[0] - ax[0][0]) / (ax[0][-1] - ax[0][0])
    eps = 1e-3 if axis == 2 else 1.0  # N, Pa
    V, fx = [], []
    for sgn in (1, -1):
        lo, hi = (np.array([f, *lam[1:]]) for f in (ax[0][0], ax[0][-1]))
        lo[axis] += sgn * eps
        hi[axis] += sgn * eps
        u0, u1 = (float(h @ (fwd.solve(q).x - fwd.fem.x_rest)) for q in (lo, hi))
        start = fwd.solve(np.array([at.forces(lam)[0], *lo[1:]]))
        lin, _ = _solve_ux(fwd, h, start.lam.copy(), u0 + t * (u1 - u0), start, (ax[0][0], ax[0][-1]),
                           1e-9 * abs(u1 - u0))
        V.append(lin.V)
        fx.append(lin.lam[0])
    fd = (V[0] - V[1]) / (2 * eps)
    J = at.volumes(lam)[1][:, axis]
    assert np.allclose(J, fd, rtol=0, atol=1e-4 * np.abs(fd).max()), (J, fd)
    dfx = (fx[0] - fx[1]) / (2 * eps)
    step = np.eye(4)[axis] * eps
    dfx_atlas = (at.forces(lam + step)[0] - at.forces(lam - step)[0]) / (2 * eps)
    assert abs(dfx_atlas - dfx) <= 1e-3 * abs(dfx), (dfx_atlas, dfx)
