"""The reduced-order forward model (softphantom.fem.rom) and the atlas built with it
(``AtlasConfig.offline = "rom"``, softphantom.estimation.offline), on the coarse models. The
reduced atlas against the full one at off-grid loads, on the force and the displacement axis (its
key, provenance, checks and bounds), is ``benchmarks/bench_interpolants.py``'s (``make bench-quick``
runs its ``--quick`` checks)."""

from __future__ import annotations

import numpy as np
import pytest

from softphantom.estimation import AtlasConfig, EstimatorConfig, ForwardModel
from softphantom.fem.rom import ElementSet, ReducedModel, ecsw_weights, pod_basis

CFG = EstimatorConfig(contact="on-centre")


@pytest.fixture(scope="module")
def fwd(coarse_model):
    return ForwardModel(coarse_model, CFG)


def _basis(fwd, states):
    """Orthonormal basis (3N, r) of the given displacements, zero on the fixed DOFs."""
    fem = fwd.fem
    D = np.stack([x - fem.x_rest for x in states], axis=1)[fem.free_dofs]
    Vf, _ = pod_basis(D, 1e-20)
    V = np.zeros((fem.n_dof, Vf.shape[1]))
    V[fem.free_dofs] = Vf
    return V


@pytest.mark.parametrize("model_name", ["coarse_model", "coarse_p2_model"])
def test_galerkin_model_whose_basis_holds_the_solution_reaches_the_full_solve(model_name, request):
    """Every element at weight 1 and the full solution in the span: the reduced Newton lands on it
    (to the full solver's tolerance), so force, tangent and the pressure's follower load agree with
    the full model's. The tangent is checked against central differences of the reduced force."""
    model = request.getfixturevalue(model_name)
    fwd = ForwardModel(model, CFG)
    lam = np.array([0.2, 0.6, -0.15, 4e3])  # (twice this: the P2 model's chord iterations fail, Newton 3x longer)
    full = fwd.solve(lam)
    # with two more directions, the linear responses at rest to f_x and to (f_z, p_u)
    V = _basis(fwd, [full.x] + [fwd.rest.x + fwd.rest.U @ np.array(d) for d in ([1.0, 0, 0, 0], [0, 0, 1.0, 1e3])])
    rom = ReducedModel(fwd.fem, V, fwd.H_f, fwd.eq._ur_tris)
    sol = rom.solve(lam)
    x = rom.x(sol.q)
    scale = np.abs(full.x - fwd.fem.x_rest).max()
    assert np.abs(x - full.x).max() <= 1e-6 * scale
    assert np.allclose(fwd.eq.arm_volumes(x), full.V, rtol=0, atol=1e-6 * np.abs(full.V).max())
    q = 0.7 * sol.q
    _, K, _ = rom.residual(q, lam)
    eps = 1e-7 * np.linalg.norm(sol.q)
    for i in range(V.shape[1]):
        e = np.zeros(V.shape[1])
        e[i] = eps
        fd = (rom.residual(q + e, lam, False)[0] - rom.residual(q - e, lam, False)[0]) / (2 * eps)
        assert np.allclose(K[:, i], fd, rtol=0, atol=1e-5 * np.abs(K).max())


def test_rigid_motion_gives_zero_element_and_reduced_forces(fwd):
    fem = fwd.fem
    X = fem.x_rest.reshape(-1, 3)
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    moved = (X @ R.T + [0.002, -0.001, 0.003]).ravel()
    stretched = (X * [1.05, 1.0, 1.0]).ravel()
    es = ElementSet(fem, np.arange(len(fem.tets)))
    assert es.evaluate(moved[es.dofs], True)
    F_rigid, K_rigid = es.FE.copy(), es.KE.copy()
    assert es.evaluate(stretched[es.dofs], True)
    assert np.abs(F_rigid).max() <= 1e-9 * np.abs(es.FE).max()
    # the tangent of a rotated state is the rest tangent rotated: Kᵉ(Rx) = R Kᵉ(x) Rᵀ blockwise
    assert es.evaluate(fem.x_rest[es.dofs], True)
    Rb = np.kron(np.eye(fem.tets.shape[1]), R)
    assert np.allclose(K_rigid, Rb @ es.KE @ Rb.T, rtol=0, atol=1e-9 * np.abs(es.KE).max())
    assert es.evaluate(stretched[es.dofs], False)
    F_strain = es.FE.copy()
    d = moved - fem.x_rest  # the motion as the one basis vector (the fixed DOFs too: no supports here)
    rom = ReducedModel(fem, (d / np.linalg.norm(d))[:, None], fwd.H_f, fwd.eq._ur_tris)
    R_rigid, _, _ = rom.residual(np.array([np.linalg.norm(d)]), np.zeros(4), False)
    assert abs(R_rigid[0]) <= 1e-9 * np.abs(F_strain).max()


def test_ecsw_weights_reproduce_the_training_forces_to_their_tolerance(fwd):
    loads = [np.array(v) for v in ([0.5, 1.0, 0.0, 0.0], [-0.8, 2.0, 0.5, 5e3], [0.0, -0.5, -0.6, 2e4])]
    states = [fwd.solve(lam).x for lam in loads]
    V = _basis(fwd, states + [fwd.rest.x + fwd.rest.U @ np.array([0, 1.0, 0, 0])])
    tol = 1e-3
    idx, w, err = ecsw_weights(fwd.fem, V, states, tol=tol)
    assert err <= tol and len(idx) < len(fwd.fem.tets) and (w > 0).all()
    full = ReducedModel(fwd.fem, V, fwd.H_f, fwd.eq._ur_tris)
    hyper = ReducedModel(fwd.fem, V, fwd.H_f, fwd.eq._ur_tris, idx, w)
    for x in states:
        q = V.T @ (x - fwd.fem.x_rest)
        f_full = full.residual(q, np.zeros(4), False)[0]  # the internal force alone (no load)
        f_hyper = hyper.residual(q, np.zeros(4), False)[0]
        assert np.linalg.norm(f_hyper - f_full) <= tol * np.linalg.norm(f_full) * (1 + 1e-9)
    # not a trivially satisfied tolerance: uniform weights on the same set miss it
    uni = ReducedModel(fwd.fem, V, fwd.H_f, fwd.eq._ur_tris, idx, np.full(len(idx), len(fwd.fem.tets) / len(idx)))
    q = V.T @ (states[1] - fwd.fem.x_rest)
    f_full = full.residual(q, np.zeros(4), False)[0]
    assert np.linalg.norm(uni.residual(q, np.zeros(4), False)[0] - f_full) > tol * np.linalg.norm(f_full)


def test_nnls_stopped_at_its_tolerance_agrees_with_scipy_and_stops_early():
    """Against scipy's Lawson–Hanson: where the exact optimum has a residual, the tolerance-stopped
    solver reaches the same residual; where a fit within tol exists it stops there with fewer
    columns than the exact solve keeps, each group within tol."""
    from scipy.optimize import nnls

    from softphantom.fem.rom import nnls_to_tolerance

    rng = np.random.default_rng(3)
    A = rng.normal(size=(60, 25))
    b = rng.normal(size=60)  # not reachable: the optimum's residual is what both must find
    x_ref, r_ref = nnls(A, b)
    x, _ = nnls_to_tolerance(A, b, np.zeros(60, int), 1e-12, batch=0.0)
    assert (x >= 0).all() and abs(np.linalg.norm(A @ x - b) - r_ref) <= 1e-9 * r_ref
    np.testing.assert_allclose(x, x_ref, atol=1e-8)
    # ECSW's shape: b the sum of all columns; three groups of rows
    A = np.abs(rng.normal(size=(90, 400))) + np.linspace(0, 1, 400)
    b = A.sum(axis=1)
    groups = np.repeat(np.arange(3), 30)
    x, err = nnls_to_tolerance(A, b, groups, 1e-3)
    per_group = [np.linalg.norm((A @ x - b)[groups == g]) / np.linalg.norm(b[groups == g]) for g in range(3)]
    assert err <= 1e-3 and max(per_group) == pytest.approx(err) and (x >= 0).all()
    assert (x > 0).sum() < (nnls(A, b, maxiter=4000)[0] > 0).sum()


def test_atlas_build_refuses_an_unknown_offline_stage_in_one_line(coarse_model_dir, capsys):
    from softphantom.cli import main

    assert main(["atlas", "build", "--model", str(coarse_model_dir), "--offline", "fast"]) == 2
    err = capsys.readouterr().err
    assert "--offline: full or rom, got 'fast'" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(Exception, match="atlas offline: one of full, rom, got 'fast'"):
        AtlasConfig(offline="fast")
