"""Element-level truths of the co-rotational FEM: patch test, rigid-motion invariance, tangent and
volume gradient against finite differences, actuators, inversion."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import scipy.sparse as sp

from softphantom.fem import (
    ElementInversionError,
    Material,
    SparseSolver,
    available_solvers,
    build_fem,
    cavity_volume,
    cavity_volume_gradient,
    force_actuator,
    free_tangent,
    internal_force,
    linear_internal_force,
    pressure_load,
    pressure_load_tangent,
    solve_static,
    tangent_stiffness,
)
from softphantom.errors import UserError
from softphantom.fem.meshes import box_mesh

MAT = Material(E_Pa=1.0e5, nu=0.45, density_kg_m3=1000.0)


def rot(axis, deg):
    """The rotation by ``deg`` about ``axis`` (scipy's, independent of the FEM)."""
    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


@pytest.fixture(scope="module")
def cube():
    X, T = box_mesh((0.02, 0.02, 0.02), (3, 3, 3))
    return X, T


def boundary_nodes(X):
    lo, hi = X.min(0), X.max(0)
    return np.flatnonzero(np.any(np.isclose(X, lo) | np.isclose(X, hi), axis=1))


def test_rigid_motion_gives_zero_internal_force_linear_does_not(cube):
    X, T = cube
    fem = build_fem(X, T, MAT)
    scale = float(np.abs(tangent_stiffness(fem, X) @ (0.01 * X.reshape(-1))).max())  # 1 % strain
    for R, t in [(np.eye(3), [0.01, -0.02, 0.005]), (rot([1, 2, 3], 60), [0.003, 0.0, -0.01])]:
        x = X @ R.T + t
        f = internal_force(fem, x)
        assert np.abs(f).max() < 1e-10 * scale
    # A linear (small-strain) model reports large spurious forces under the 60° rotation
    f_lin = linear_internal_force(fem, X @ rot([1, 2, 3], 60).T)
    assert np.abs(f_lin).max() > 10 * scale


def test_patch_test_reproduces_linear_field(cube):
    X, T = cube
    bnd = boundary_nodes(X)
    fem = build_fem(X, T, MAT, fixed_nodes=bnd)
    # A homogeneous deformation (3 % stretch/shear, then a 40° rotation) imposed on the boundary
    A = rot([0, 1, 1], 40) @ (np.eye(3) + np.array([[0.03, 0.01, 0], [0, -0.02, 0.015], [0.005, 0, 0.01]]))
    exact = X @ A.T + [0.001, 0.002, -0.001]
    x0 = X @ rot([0, 1, 1], 40).T  # interior starts rigidly rotated (else it would be inverted)
    x0[bnd] = exact[bnd]
    sol = solve_static(fem, x0=x0, tol=1e-12, solver="splu")
    assert sol.converged
    interior = np.setdiff1d(np.arange(len(X)), bnd)
    assert interior.size > 0
    assert np.abs(sol.x[interior] - exact[interior]).max() < 1e-12 * np.abs(exact).max() * 1e3
    # and the stress is uniform: nodal forces vanish on the interior nodes
    f = internal_force(fem, exact).reshape(-1, 3)
    assert np.abs(f[interior]).max() < 1e-9 * np.abs(f).max()


@pytest.mark.parametrize("consistent", [True, False])
def test_tangent_against_finite_differences(cube, consistent):
    X, T = cube
    fem = build_fem(X, T, MAT)
    rng = np.random.default_rng(0)
    # large rotation + ~5 % random strain
    x = (X @ rot([1, -1, 2], 50).T + 0.0005 * rng.standard_normal(X.shape)).reshape(-1)
    K = tangent_stiffness(fem, x, consistent=consistent)
    v = rng.standard_normal(x.size)
    h = 1e-7
    fd = (internal_force(fem, x + h * v) - internal_force(fem, x - h * v)) / (2 * h)
    err = np.linalg.norm(K @ v - fd) / np.linalg.norm(fd)
    if consistent:
        assert err < 1e-6  # exact Hessian of the corotated energy: FD round-off only
        assert abs(K - K.T).max() < 1e-9 * abs(K).max()
    else:
        # R K0 Rᵀ misses the rotation-derivative term, an error of the order of the strain
        assert 1e-3 < err < 0.3


def test_newton_converges_quadratically():
    X, T = box_mesh((0.06, 0.01, 0.01), (12, 2, 2))
    fem = build_fem(X, T, MAT, fixed_nodes=np.flatnonzero(X[:, 0] < 1e-9))
    tip = np.flatnonzero(X[:, 0] > 0.06 - 1e-9)
    f = np.zeros(fem.n_dof)
    f[3 * tip + 2] = -0.1 / tip.size  # tip deflection ~ a third of the length: large rotation
    sol = solve_static(fem, f, tol=1e-10, solver="splu")
    assert sol.converged and -sol.u[tip, 2].mean() > 0.015
    # Newton from a nearby state: residuals fall quadratically (log-ratio of successive residuals
    # ~ 2, where a fixed or approximate tangent gives ~ 1)
    x = sol.x.reshape(-1) + 1e-5 * np.sin(np.arange(fem.n_dof))
    x[fem.fixed_dofs] = fem.x_rest[fem.fixed_dofs]
    res = []
    for _ in range(5):
        r = (internal_force(fem, x) - f)[fem.free_dofs]
        res.append(np.linalg.norm(r))
        x[fem.free_dofs] -= SparseSolver("splu").factorize(free_tangent(fem, x)).solve(r)
    rates = [np.log(res[i + 2] / res[i + 1]) / np.log(res[i + 1] / res[i]) for i in range(3)]
    assert res[-1] < 1e-11 * res[0], res
    assert max(rates) > 1.8, (res, rates)


def sphere_surface(n=12):
    """Closed, outward-oriented triangulation of a unit UV sphere."""
    th = np.linspace(0, np.pi, n + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    P = [[0, 0, 1.0]]
    P += [[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)] for t in th for p in ph]
    P += [[0, 0, -1.0]]
    P = np.array(P)
    m = 2 * n
    tri = []
    ring = lambda i, j: 1 + i * m + (j % m)  # noqa: E731
    for j in range(m):
        tri.append([0, ring(0, j), ring(0, j + 1)])
        tri.append([len(P) - 1, ring(n - 2, j + 1), ring(n - 2, j)])
    for i in range(n - 2):
        for j in range(m):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            tri += [[a, c, b], [b, c, d]]
    return P, np.array(tri)


def test_cavity_volume_gradient_and_pressure_identity():
    P, tri = sphere_surface()
    rng = np.random.default_rng(1)
    x = (P * 0.01 + 0.0005 * rng.standard_normal(P.shape) + [0.03, -0.02, 0.01]).reshape(-1)
    V = cavity_volume(x, tri)
    assert 0.9 * 4 / 3 * np.pi * 1e-6 < V < 4 / 3 * np.pi * 1e-6  # inscribed polyhedron, 1 cm radius
    # translation invariance and the orientation convention (normals out of the air: V > 0)
    assert cavity_volume(x + 0.1, tri) == pytest.approx(V, rel=1e-12)
    assert cavity_volume(x, tri[:, ::-1]) == pytest.approx(-V, rel=1e-12)
    g = cavity_volume_gradient(x, tri, len(P))
    v = rng.standard_normal(x.size)
    # Φ is cubic in x: the central difference's only truncation term is h²/6·Φ'''[v,v,v], which the
    # Richardson combination of steps h and 2h cancels exactly
    def cd(h):
        return (cavity_volume(x + h * v, tri) - cavity_volume(x - h * v, tri)) / (2 * h)

    h = 1e-5
    fd = (4 * cd(h) - cd(2 * h)) / 3
    assert g @ v == pytest.approx(fd, rel=1e-8)
    # on a closed surface the pressure load per unit pressure equals ∂Φ/∂x
    pl = pressure_load(x, tri, len(P))
    assert np.abs(pl - g).max() < 1e-12 * np.abs(g).max()
    # and its tangent is the (symmetric) Hessian of Φ (the load is quadratic in x: central
    # differences are exact up to round-off)
    Kp = pressure_load_tangent(x, tri, len(P))
    fd2 = (pressure_load(x + h * v, tri, len(P)) - pressure_load(x - h * v, tri, len(P))) / (2 * h)
    assert np.linalg.norm(Kp @ v - fd2) < 1e-7 * np.linalg.norm(fd2)
    assert abs(Kp - Kp.T).max() < 1e-12 * abs(Kp).max()


def test_force_actuator_barycentric_and_patch(cube):
    X, T = cube
    fem = build_fem(X, T, MAT)
    p = np.array([0.0071, 0.0123, 0.0049])
    H = force_actuator(fem, p)
    assert H.shape == (fem.n_dof, 3) and sp.issparse(H)
    lam = np.array([1.0, -2.0, 0.5])
    f = (H @ lam).reshape(-1, 3)
    # total force and first moment are those of the point force (barycentric weights)
    assert np.allclose(f.sum(0), lam, atol=1e-14)
    w = H[0::3, 0].toarray().ravel()
    assert np.isclose(w.sum(), 1) and w.min() >= 0 and np.count_nonzero(w) <= 4
    assert np.allclose(w @ X, p, atol=1e-15)
    # on the surface and just outside (within tolerance): nearest element, weights in [0,1]
    for q in ([0.01, 0.01, 0.02], [0.01, 0.01, 0.0202]):
        w = force_actuator(fem, q)[0::3, 0].toarray().ravel()
        assert np.isclose(w.sum(), 1) and w.min() >= 0
    with pytest.raises(Exception, match="outside the mesh"):
        force_actuator(fem, [0.01, 0.01, 0.03])
    # a patch of surface nodes: surface nodes only, same resultant (9 mm: the side faces, 10 mm
    # away, stay outside the patch, which is the surface within that 3-D distance)
    Hp = force_actuator(fem, [0.01, 0.01, 0.02], radius=0.009)
    wp = Hp[0::3, 0].toarray().ravel()
    assert np.isclose(wp.sum(), 1) and np.count_nonzero(wp) > 4
    assert np.allclose(X[wp > 0, 2], 0.02)


def test_inversion_is_a_typed_error(cube):
    X, T = cube
    fem = build_fem(X, T, MAT)
    x = X.copy()
    x[:, 2] *= -1  # mirror: every element inverted
    with pytest.raises(ElementInversionError, match=f"{len(T)} of {len(T)} elements inverted"):
        internal_force(fem, x)
    x = X.copy()
    x[:, 0] = 0.0  # flattened: det F = 0
    with pytest.raises(ElementInversionError):
        tangent_stiffness(fem, x)


def test_sparse_solvers_agree_and_cholmod_reuses_analysis(cube):
    X, T = cube
    fem = build_fem(X, T, MAT, fixed_nodes=np.flatnonzero(X[:, 2] < 1e-9))
    K = free_tangent(fem, fem.x_rest)
    B = np.random.default_rng(2).standard_normal((fem.n_free, 4))
    ref = SparseSolver("splu").factorize(K).solve(B)
    for method in available_solvers():
        s = SparseSolver(method)
        for scale in (1.0, 2.0):
            Xs = s.factorize(K * scale).solve(B)
            assert np.abs(Xs * scale - ref).max() < 1e-9 * np.abs(ref).max()
        if method == "cholmod":
            assert s.analyses == 1  # same pattern: one symbolic analysis
    with pytest.raises(Exception, match="not positive definite"):
        SparseSolver(available_solvers()[0] if available_solvers()[0] != "splu" else "cholespy").factorize(-K)


def test_indefinite_tangent_takes_ldlt_not_lu(monkeypatch):
    """A symmetric indefinite matrix (what a pressurized cavity's tangent can become) is solved by
    CHOLMOD's LDLᵀ (a Cholesky's fill) and not by SuperLU, whose fill on a 3-D P2 tangent is
    several times larger (docs/performance/design-fem.md: the 4.5 mm urethra solve's memory)."""
    pytest.importorskip("sksparse.cholmod")
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from softphantom.fem.solve import SparseSolver, indefinite_solve
    from softphantom.errors import SolverError

    rng = np.random.default_rng(3)
    n = 200
    A = sp.random(n, n, density=0.03, random_state=rng)
    K = sp.csr_matrix(A + A.T + sp.diags(rng.uniform(-4.0, 4.0, n)))  # symmetric, both signs on the diagonal
    b = rng.normal(size=n)
    with pytest.raises(SolverError):
        SparseSolver("cholmod").factorize(K)
    monkeypatch.setattr(spla, "splu", lambda *a, **k: (_ for _ in ()).throw(AssertionError("SuperLU called")))
    x = indefinite_solve(K, b)
    assert np.allclose(x, np.linalg.solve(K.toarray(), b), rtol=1e-8, atol=1e-10)


def test_pardiso_ldlt_solves_an_indefinite_matrix_and_counts_its_negative_eigenvalues(cube):
    """MKL PARDISO's LDLᵀ (the ``pardiso`` extra) on symmetric matrices with 0, 1 and several
    negative eigenvalues: the dense solve's answer, and the inertia that numpy's eigenvalues give
    (Sylvester); a copy's factor outlives a refactorization of the original, as the other methods'."""
    from softphantom.fem.solve import have_pardiso, indefinite_method

    if not have_pardiso():
        pytest.skip("the pardiso extra (pypardiso, MKL) is not installed")
    import scipy.sparse as sp

    assert indefinite_method() == "pardiso"
    X, T = cube
    fem = build_fem(X, T, MAT, fixed_nodes=np.flatnonzero(X[:, 2] < 1e-9))
    K = free_tangent(fem, fem.x_rest).toarray()
    w, Q = np.linalg.eigh(K)
    b = np.random.default_rng(5).standard_normal((len(K), 3))
    for n_neg in (0, 1, 4):
        shifted = w.copy()
        shifted[:n_neg] = -w[:n_neg] - 0.5 * w[n_neg]  # the softest modes turned negative
        A = sp.csr_matrix((Q * shifted) @ Q.T)
        s = SparseSolver("pardiso").factorize(A)
        assert s.negative_eigenvalues == n_neg == int((np.linalg.eigvalsh(A.toarray()) < 0).sum())
        assert np.abs(s.solve(b) - np.linalg.solve(A.toarray(), b)).max() < 1e-8 * np.abs(np.linalg.solve(A.toarray(), b)).max()
        kept = s.copy()
        s.factorize(sp.csr_matrix(2.0 * A.toarray()))
        assert np.allclose(kept.solve(b[:, 0]), 2.0 * s.solve(b[:, 0]), rtol=1e-8, atol=0)


def test_newton_step_on_an_indefinite_tangent_is_a_shifted_cholesky(monkeypatch):
    """Where the tangent is not positive definite, the Newton direction comes from a shifted
    Cholesky on the same symbolic analysis (a descent direction of the energy), not from the exact
    but simplicial LDLᵀ, which took 33 CPU-s per step on the 9 mm P2 tangent at ν = 0.49
    (docs/model.md); a positive definite matrix afterwards is factored unshifted, same analysis."""
    pytest.importorskip("sksparse.cholmod")
    import scipy.sparse as sp

    import softphantom.fem.solve as fs

    rng = np.random.default_rng(5)
    n = 200
    A = sp.random(n, n, density=0.03, random_state=rng)
    S = A + A.T
    K = sp.csr_matrix(S + sp.diags(rng.uniform(-4.0, 4.0, n)))  # indefinite
    K_pd = sp.csr_matrix(S + sp.diags(np.full(n, 4.0 + abs(S).sum(axis=1).A1.max())))  # diagonally dominant
    assert np.min(np.linalg.eigvalsh(K.toarray())) < 0
    monkeypatch.setattr(fs, "indefinite_solve", lambda *a: (_ for _ in ()).throw(AssertionError("LDLᵀ called")))
    solver = fs.SparseSolver("cholmod")
    b = rng.normal(size=n)  # b = −gradient
    d, tau = fs.descent_step(solver, K, b)
    assert tau in fs.DESCENT_SHIFTS
    assert np.dot(b, d) > 0  # downhill
    dg = np.abs(K.diagonal())
    Ks = K.toarray() + tau * np.diag(np.maximum(dg, dg.mean()))
    assert np.allclose(Ks @ d, b, rtol=1e-8, atol=1e-10)
    d2, tau2 = fs.descent_step(solver, K_pd, b)
    assert tau2 == 0.0 and np.allclose(K_pd @ d2, b, rtol=1e-8, atol=1e-10)
    assert solver.analyses == 1


def _cantilever():
    """A clamped 60 mm beam with 0.1 N down at its tip: (fem, f_ext, its Newton solution)."""
    X, T = box_mesh((0.06, 0.01, 0.01), (12, 2, 2))
    fem = build_fem(X, T, MAT, fixed_nodes=np.flatnonzero(X[:, 0] < 1e-9))
    tip = np.flatnonzero(X[:, 0] > 0.06 - 1e-9)
    f = np.zeros(fem.n_dof)
    f[3 * tip + 2] = -0.1 / tip.size
    return fem, f, solve_static(fem, f, tol=1e-10, solver="cholmod")


def test_a_tangent_that_loses_definiteness_in_a_large_load_step_cuts_the_step(monkeypatch):
    """Newton does not step through an indefinite tangent within a large load increment (the
    step is too large; continuation instead): the increment is halved, and the continued solve
    reaches the same equilibrium as an undisturbed one."""
    pytest.importorskip("sksparse.cholmod")
    import softphantom.fem.solve as fs

    fem, f, ref = _cantilever()
    real = fs.SparseSolver.factorize
    calls = {"n": 0}

    def first_not_pd(self, A):  # the first step's second tangent "is not positive definite"
        calls["n"] += 1
        if calls["n"] == 2:
            raise fs.SolverError("matrix not positive definite (cholmod)")
        return real(self, A)

    seen = []
    newton = fs._newton
    monkeypatch.setattr(fs.SparseSolver, "factorize", first_not_pd)
    monkeypatch.setattr(fs, "_newton", lambda *a, **k: seen.append((a[4], k["on_indefinite"])) or newton(*a, **k))
    sol = fs.solve_static(fem, f, tol=1e-10, solver="cholmod")
    assert sol.converged and sol.load_steps >= 2
    assert seen[0] == (1.0, "cut") and seen[1][0] == 0.5  # the full step gave up, half the load next
    assert np.allclose(sol.x, ref.x, atol=1e-9)


def test_an_increment_that_may_not_be_cut_steps_on_shifted_when_asked(monkeypatch):
    """solve_static's own choice for an increment it may not cut (min_load_step 1) is the exact
    LDLᵀ step; ``on_indefinite="shift"`` (the atlas fallback's first attempt) takes the shifted
    Cholesky instead and reaches the same equilibrium; an unknown policy is a one-line error."""
    pytest.importorskip("sksparse.cholmod")
    import softphantom.fem.solve as fs

    fem, f, ref = _cantilever()
    real, real_ldlt = fs.SparseSolver.factorize, fs.indefinite_solve

    def run(policy):
        calls, ldlt = {"n": 0}, []

        def second_not_pd(self, A):
            calls["n"] += 1
            if calls["n"] == 2:
                raise fs.SolverError("matrix not positive definite (cholmod)")
            return real(self, A)

        monkeypatch.setattr(fs.SparseSolver, "factorize", second_not_pd)
        monkeypatch.setattr(fs, "indefinite_solve", lambda K, b: ldlt.append(1) or real_ldlt(K, b))
        sol = fs.solve_static(fem, f, tol=1e-10, solver="cholmod", min_load_step=1.0, on_indefinite=policy)
        return sol, len(ldlt)

    sol, ldlt = run(None)
    assert sol.converged and ldlt == 1  # the exact step
    sol, ldlt = run("shift")
    assert sol.converged and ldlt == 0 and sol.load_steps == 1
    assert np.allclose(sol.x, ref.x, atol=1e-9)
    with pytest.raises(UserError, match="on_indefinite must be shift, cut or exact"):
        fs.solve_static(fem, f, on_indefinite="ldlt")


def test_splu_orders_symmetric_matrices_symmetrically():
    """SuperLU (the fallback) on a 3-D stiffness-like matrix: minimum degree on A + Aᵀ fills less
    than scipy's default COLAMD (on the 9 mm P2 design tangent 38 M vs 68 M entries)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from softphantom.fem.solve import SparseSolver

    m = 14
    lap1 = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(m, m))
    eye = sp.identity(m)
    K = sp.csc_matrix(sp.kron(sp.kron(lap1, eye), eye) + sp.kron(sp.kron(eye, lap1), eye) + sp.kron(sp.kron(eye, eye), lap1))
    ours = SparseSolver("splu").factorize(K)._factor
    colamd = spla.splu(K)
    assert ours.L.nnz + ours.U.nnz < 0.8 * (colamd.L.nnz + colamd.U.nnz)
    b = np.arange(K.shape[0], dtype=float)
    assert np.allclose(K @ SparseSolver("splu").factorize(K).solve(b), b)
