"""The atlas build's solver path on the coarse mesh: the walk over a plane, the
Euler predictor and chord iterations from a kept factor, the factor kept and restored, a stalled
chord refactoring — each reaching the equilibrium a full Newton solve (``solve_static``) reaches."""

from __future__ import annotations

import numpy as np
import pytest

from softphantom.estimation import AtlasConfig, EstimatorConfig, ForwardModel
from softphantom.estimation.atlas.build import _inner, _plane_walk, _sweep
from softphantom.fem import SparseSolver, free_tangent, solve_static

CFG = EstimatorConfig(contact="on-centre")


@pytest.fixture(scope="module")
def fwd(coarse_model):
    return ForwardModel(coarse_model, CFG, exact_sensitivities=False)


def newton(fwd, lam):
    """The reference equilibrium: Newton with load stepping from rest."""
    sol = solve_static(fwd.fem, fwd.H_f @ lam[:3], [(fwd.eq._ur_tris, lam[3])], tol=1e-10)
    assert sol.converged
    return sol.x.reshape(-1)


def rel(x, ref, fwd):
    return float(np.abs(x - ref).max() / np.abs(ref - fwd.fem.x_rest).max())


@pytest.mark.parametrize("shape", [(7, 5, 2, 2), (5, 7, 1, 3), (4, 3, 0, 0), (3, 3, 2, 2)])
def test_plane_walk_visits_every_point_after_its_inner_neighbours(shape):
    ny, nz, j0, k0 = shape
    walk = _plane_walk(ny, nz, j0, k0)
    order = [p for p, _, _ in walk]
    assert sorted(order) == [(j, k) for j in range(ny) for k in range(nz)]
    seen = set()
    for p, parent, kids in walk:
        inner = _inner(p, (j0, k0))
        assert all(q in seen for q in inner)  # the skip rule can be decided
        assert (parent is None) == (p == (j0, k0)) and (parent is None or parent in inner)
        assert kids == sum(1 for _, q, _ in walk if q == p)
        seen.add(p)


def test_factor_at_solution_gives_the_newton_equilibrium_and_its_exact_tangent(fwd):
    lam = np.array([0.3, 1.2, -0.2, 2e3])
    lin = fwd.solve(lam, factor_at_solution=True)
    assert rel(lin.x, newton(fwd, lam), fwd) < 1e-6
    # the kept factor is the tangent at the equilibrium: the sensitivities are exact
    K = free_tangent(fwd.fem, lin.x, [(fwd.eq._ur_tris, lam[3])])
    U = lin.U[fwd.fem.free_dofs]
    B = K @ U
    exact = SparseSolver("splu").factorize(K).solve(B)
    assert np.abs(U - exact).max() <= 1e-8 * np.abs(exact).max()


def test_euler_predictor_and_chord_from_a_kept_factor_reach_the_newton_equilibrium(fwd):
    a = fwd.solve(np.array([0.0, 0.4, 0.0, 0.0]), factor_at_solution=True)
    kept = fwd.eq.keep()
    lam_b = np.array([0.05, 0.6, 0.1, 0.0])
    n0 = fwd.eq.factorizations
    b = fwd.eq.solve(a, lam_b)  # a one-step neighbour: no new factor needed
    assert fwd.eq.factorizations == n0 and not b.refactored
    assert rel(b.x, newton(fwd, lam_b), fwd) < 1e-6
    # elsewhere, then back: the restored factor is a's, untouched by the factorizations in between
    fwd.solve(np.array([0.5, -0.5, 0.5, 3e3]), factor_at_solution=True)
    fwd.eq.restore(kept)
    n0 = fwd.eq.factorizations
    b2 = fwd.eq.solve(a, lam_b)
    assert fwd.eq.factorizations == n0
    assert np.abs(b2.x - b.x).max() <= 1e-12 + 1e-9 * np.abs(b.x - fwd.fem.x_rest).max()


def test_a_stalled_chord_refactors_and_still_converges(fwd):
    # the factor at rest for a far load: the chord contracts too slowly, so the solver refactors
    fwd.eq.factorize(fwd.fem.x_rest.copy(), 0.0)
    lam = np.array([0.8, 2.5, -0.6, 0.0])
    lin = fwd.eq.solve(fwd.rest, lam)
    assert lin.refactored
    assert rel(lin.x, newton(fwd, lam), fwd) < 1e-6


def test_mixed_control_lands_on_the_patch_displacement_at_the_newton_equilibrium_of_its_force(fwd):
    """Bordered chord iterations (f_x an unknown fixed by the patch's x-displacement): the state
    they reach is the force-controlled Newton equilibrium at the f_x they report, and its patch
    displacement is the target; a target beyond the start's in ū needs a larger f_x."""
    from softphantom.estimation.atlas.build import x_patch
    from softphantom.estimation.linearization import PatchControl

    h = x_patch(fwd)
    a = fwd.solve(np.array([0.0, 0.8, -0.2, 1e3]))
    u_a = float(h @ (a.x - fwd.fem.x_rest))
    du = float(h @ a.U[:, 0]) * 0.3  # ū of about 0.3 N more f_x (a grid step)
    for target in (u_a + du, u_a - du):
        ctl = PatchControl(h, fwd.fem.x_rest, target, 1e-9 * abs(du))
        lin = fwd.eq.solve(a, np.array([0.0, 0.9, -0.1, 1e3]), control=ctl)
        assert abs(ctl.gap(lin.x)) <= 1e-9 * abs(du)
        assert (lin.lam[0] > 0) == (target > u_a)
        assert np.allclose(lin.lam[1:], [0.9, -0.1, 1e3])
        x = newton(fwd, lin.lam)
        assert rel(lin.x, x, fwd) < 1e-6
        assert abs(float(h @ (x - fwd.fem.x_rest)) - target) <= 1e-6 * abs(du)


def test_a_failing_mixed_control_solve_falls_back_to_force_controlled_trials(fwd, monkeypatch):
    """Where the bordered chord iterations get nowhere (and so do their halved steps), the point
    is still solved at its patch displacement, by force-controlled trials."""
    import softphantom.estimation.linearization as L
    from softphantom.estimation.atlas.build import _solve_ux, x_patch

    chord = L.EquilibriumSolver._chord

    def fail_mixed(self, x, lam, r, rn, ref, its, limit, control=None):
        if control is not None:
            return x, lam, r, rn, ref, its + 1, np.inf, False
        return chord(self, x, lam, r, rn, ref, its, limit, control)

    monkeypatch.setattr(L.EquilibriumSolver, "_chord", fail_mixed)
    h = x_patch(fwd)
    a = fwd.solve(np.array([0.0, 0.8, -0.2, 1e3]))
    du = float(h @ a.U[:, 0]) * 0.3
    target = float(h @ (a.x - fwd.fem.x_rest)) + du
    lin, n = _solve_ux(fwd, h, a.lam.copy(), target, a, (0.0, 1.0), 1e-6 * du)
    assert n >= 2  # trials, not one mixed-control solve
    assert abs(float(h @ (lin.x - fwd.fem.x_rest)) - target) <= 1e-6 * du
    assert rel(lin.x, newton(fwd, lin.lam), fwd) < 1e-6


def test_mixed_control_may_lower_f_x_within_its_range_where_the_trials_may_not(fwd):
    """A fold (f_x falling along the line, the quadratic model's snap-through) is for the mixed-control
    solve alone: its f_x may lie anywhere in ``fx_range``, below the trials' bracket."""
    from softphantom.estimation.atlas.build import _solve_ux, x_patch

    h = x_patch(fwd)
    a = fwd.solve(np.array([0.0, 0.8, -0.2, 1e3]))
    du = float(h @ a.U[:, 0]) * 0.2
    target = float(h @ (a.x - fwd.fem.x_rest)) - du  # behind the start: f_x below a's
    lin, n = _solve_ux(fwd, h, a.lam.copy(), target, a, (0.0, 1.0), 1e-6 * du, fx_range=(-1.0, 1.0))
    assert n == 1 and -1.0 < lin.lam[0] < 0.0
    assert abs(float(h @ (lin.x - fwd.fem.x_rest)) - target) <= 1e-6 * du


@pytest.mark.slow
def test_sweep_matches_independent_solves(coarse_model, fwd):
    acfg = AtlasConfig(force_min_N=(-0.5, -0.3, -0.5), force_max_N=(0.5, 1.6, 0.5), p_min_kPa=-1.0, p_max_kPa=4.0,
                       n_force=(3, 4, 3), n_pressure=2)
    i, l, V, P, X, solved, err, cpu, deriv, FX, Q, n = _sweep(coarse_model, CFG, acfg, 2, 1)
    assert solved.all() and err == "" and cpu > 0 and deriv is None and np.all(FX == acfg.axes()[0][2]) and np.all(Q == FX)
    assert n == solved.size  # one solve a point on a force axis
    ax = acfg.axes()
    for j, k in [(0, 0), (3, 2), (2, 1)]:
        lam = np.array([ax[0][2], ax[1][j], ax[2][k], ax[3][1]])
        x = newton(fwd, lam)
        assert rel(X[j, k] + fwd.fem.x_rest, x, fwd) < 1e-6
        assert np.allclose(V[j, k], fwd.eq.arm_volumes(x), rtol=1e-6, atol=1e-6 * np.abs(V).max())


def test_continuation_steps_between_grid_points_stop_early_and_the_last_converges(fwd, monkeypatch):
    # a 2.4 N step is taken in 3 steps: the first two only start the next (the atlas's VIA_TOL),
    # the last converges to the configured tol and is the Newton equilibrium
    import softphantom.estimation.linearization as L

    seen = []
    solve = L.EquilibriumSolver.solve
    monkeypatch.setattr(L.EquilibriumSolver, "solve",
                        lambda self, start, lam, *a, **k: seen.append(k.get("tol")) or solve(self, start, lam, *a, **k))
    lam = np.array([0.1, 2.4, -0.1, 0.0])
    out = []
    monkeypatch.setattr(fwd.eq, "linearize", lambda *a, _l=fwd.eq.linearize, **k: out.append(_l(*a, **k)) or out[-1])
    lin = fwd.solve(lam, via_tol=1e-3)
    assert seen == [1e-3, 1e-3, None]
    assert all(CFG.tol < o.residual <= 1e-3 for o in out[:2])  # stopped early (the chord's rate is > 1e-5)
    assert lin.residual <= CFG.tol and rel(lin.x, newton(fwd, lam), fwd) < 1e-6


def test_a_failing_chord_falls_back_to_newton_and_reaches_the_equilibrium(fwd, monkeypatch):
    import softphantom.estimation.linearization as L

    def fail(self, x, lam, r, rn, ref, its, limit, control=None):  # as if the chord iterations got nowhere
        return x, lam, r, rn, ref, its + 1, np.inf, False

    monkeypatch.setattr(L.EquilibriumSolver, "_chord", fail)
    lam = np.array([0.2, 0.9, 0.1, 1e3])
    lin = fwd.solve(lam)
    assert lin.refactored and lin.residual <= CFG.tol
    assert rel(lin.x, newton(fwd, lam), fwd) < 1e-6


@pytest.mark.slow
def test_linear_pressure_axis_is_the_tangent_line_through_converged_middle_solves(coarse_model, fwd):
    from softphantom.estimation import build_atlas

    lin = AtlasConfig(force_min_N=(-0.3, -0.3, -0.3), force_max_N=(0.3, 0.9, 0.3), p_min_kPa=-1.0, p_max_kPa=1.0,
                      n_force=(3, 3, 3), n_pressure=2, linear_pressure=True, x_control="force")
    at = build_atlas(coarse_model, CFG, lin, n_workers=1, processes=False)
    assert at.solves == 27 and lin.n_solves == 27 and at.solved.all()
    ax = lin.axes()
    for f in [(ax[0][0], ax[1][1], ax[2][2]), (ax[0][2], ax[1][2], ax[2][0])]:
        mid = fwd.solve(np.array([*f, 0.0]))
        # exact at the middle (a converged solve)...
        assert np.allclose(at.volumes(np.array([*f, 0.0]))[0], mid.V, rtol=0, atol=1e-6 * np.abs(mid.V).max())
        # ...with the pressure slope of converged solves (central difference: O(δ²) off)
        d = 100.0
        hi, lo = fwd.solve(np.array([*f, d]), mid).V, fwd.solve(np.array([*f, -d]), mid).V
        slope = (at.volumes(np.array([*f, 1e3]))[0] - at.volumes(np.array([*f, -1e3]))[0]) / 2e3
        assert np.allclose(slope, (hi - lo) / (2 * d), rtol=1e-3, atol=1e-4 * np.abs(slope).max())
    with pytest.raises(Exception, match="linear_pressure needs n_pressure 2"):
        AtlasConfig(n_pressure=3, linear_pressure=True, x_control="force")
    with pytest.raises(Exception, match="linear_pressure needs x_control 'force'"):
        AtlasConfig(n_pressure=2, linear_pressure=True, x_control="displacement")


def test_line_predictor_error_falls_with_the_fourth_power_of_the_step():
    """The cubic Hermite through two points with their derivatives, evaluated one step beyond:
    halving the step divides the error by ≈ 16 (the secant's by ≈ 4); with one point it is the
    tangent line (≈ 4)."""
    from softphantom.estimation.atlas.build import LinePredictor

    def path(u):  # (f_x, x, df_x/du, dx/du)
        return np.exp(u), np.array([np.sin(u), np.cos(2 * u)]), np.exp(u), np.array([np.cos(u), -2 * np.sin(2 * u)])

    def errors(H):
        p, one = LinePredictor(), LinePredictor()
        for u in (0.3 - H, 0.3):
            f, x, df, dx = path(u)
            p.add(u, x, f, dx, df)
        one.add(0.3, x, f, dx, df)
        f_c, x_c, _, _ = path(0.3 + H)
        secant = 2 * path(0.3)[1] - path(0.3 - H)[1]
        out = []
        for pred in (p, one):
            fp, xp = pred(0.3 + H)
            out.append(max(abs(fp - f_c), np.abs(xp - x_c).max()))
        return out + [np.abs(secant - x_c).max()]

    coarse, fine = errors(0.2), errors(0.1)
    hermite, tangent, secant = (c / f for c, f in zip(coarse, fine))
    assert 12 < hermite < 20 and 3 < tangent < 5 and 3 < secant < 5
    assert fine[0] < fine[2] / 20  # at a step like a line's, far nearer than the secant


def test_the_line_predictor_starts_a_mixed_control_solve_nearer_and_it_lands_on_the_same_equilibrium(fwd):
    """Along a line at fixed (f_y, f_z, p_u): two solved points with their exact ū-derivatives
    (:func:`_line_knot`) predict the third's state an order of magnitude nearer than the secant
    through them, and the mixed-control solve started there reaches the secant-started one's."""
    from softphantom.estimation.atlas.build import LinePredictor, _line_knot, x_patch
    from softphantom.estimation.linearization import PatchControl

    h = x_patch(fwd)
    lam = np.array([-0.5, 0.9, -0.2, 1e3])
    a = fwd.solve(lam)
    du = float(h @ a.U[:, 0]) * 0.3  # about 0.3 N of f_x a step
    u_a = float(h @ (a.x - fwd.fem.x_rest))
    b = fwd.eq.solve(a, lam, control=PatchControl(h, fwd.fem.x_rest, u_a + du, 1e-10 * du))
    path = LinePredictor()
    for p in (a, b):
        _line_knot(fwd, h, p, path)
    target = u_a + 2 * du
    c = fwd.eq.solve(b, lam, control=PatchControl(h, fwd.fem.x_rest, target, 1e-10 * du, prev=a))  # the secant's
    pred = PatchControl(h, fwd.fem.x_rest, target, 1e-10 * du, predictor=path).predict(b, lam)
    secant = PatchControl(h, fwd.fem.x_rest, target, 1e-10 * du, prev=a).predict(b, lam)
    err = [np.abs(x - c.x).max() for x in (pred[1], secant[1])]
    assert err[0] < err[1] / 10
    assert abs(pred[0] - c.lam[0]) < abs(secant[0] - c.lam[0]) / 10
    d = fwd.eq.solve(b, lam, control=PatchControl(h, fwd.fem.x_rest, target, 1e-10 * du, predictor=path))
    assert rel(d.x, c.x, fwd) < 1e-6 and abs(d.lam[0] - c.lam[0]) < 1e-6
