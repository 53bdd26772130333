"""The numba kernels (softphantom.fem.kernels) against the numpy reference of the co-rotational FEM:
same forces, energy and tangents to round-off on a random deformed, largely rotated state; the same
typed errors; and the numpy fallback used when numba is off."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softphantom.errors import SolverError
from softphantom.fem import (
    ElementInversionError,
    Material,
    build_fem,
    free_tangent,
    internal_force,
    polar_rotation,
    strain_energy,
    tangent_stiffness,
)
from softphantom.fem import corotational as C
from softphantom.fem import kernels
from softphantom.fem.meshes import box_mesh

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")


def rot(axis, deg):
    """The rotation by ``deg`` about ``axis`` (scipy's, independent of the FEM)."""
    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


@pytest.fixture(scope="module")
def deformed():
    X, T = box_mesh((0.02, 0.03, 0.015), (3, 4, 2))
    rng = np.random.default_rng(7)
    # two materials, per tet (different Lamé constants per element)
    mats = [Material(1.0e5, 0.45), Material(3.0e4, 0.3)]
    fem = build_fem(X, T, [mats[i % 2] for i in range(len(T))], fixed_nodes=[0, 1, 2])
    h = 0.005
    # ~10 % random strain, a stretch along x, a 130° rotation and a translation
    x = (X * [1.15, 0.95, 1.0] + 0.1 * h * rng.standard_normal(X.shape)) @ rot([1, -2, 0.5], 130).T
    x = x + [0.01, -0.02, 0.003]
    return fem, x.reshape(-1)


def _rel(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_numba_matches_numpy_reference(deformed):
    fem, x = deformed
    assert C.USE_NUMBA
    f = internal_force(fem, x)
    f_ref = C.internal_force_numpy(fem, x)
    assert np.abs(f_ref).max() > 1.0  # a genuinely loaded state
    assert _rel(f, f_ref) < 1e-12
    e, e_ref = strain_energy(fem, x), C.strain_energy_numpy(fem, x)
    assert abs(e - e_ref) < 1e-12 * e_ref
    for consistent in (True, False):
        K = tangent_stiffness(fem, x, consistent)
        K_ref = C.tangent_stiffness_numpy(fem, x, consistent)
        assert K.shape == K_ref.shape
        assert np.array_equal(K.indptr, K_ref.indptr) and np.array_equal(K.indices, K_ref.indices)
        assert _rel(K.data, K_ref.data) < 1e-12
    # free_tangent goes through the kernel too
    Kff = free_tangent(fem, x)
    Kff_ref = C.tangent_stiffness_numpy(fem, x)[fem.free_dofs][:, fem.free_dofs]
    assert _rel(Kff.toarray(), Kff_ref.toarray()) < 1e-12


def test_polar_kernel_matches_svd_reference():
    rng = np.random.default_rng(3)
    Fs = []
    for _ in range(200):
        A = np.eye(3) + rng.uniform(0, 0.6) * rng.standard_normal((3, 3))
        if np.linalg.det(A) <= 0:
            continue
        Fs.append(rot(rng.standard_normal(3), rng.uniform(0, 180)) @ A)
    Fs.append(rot([0, 0, 1], 179.9) @ np.diag([3.0, 0.2, 1.0]))  # strong anisotropy
    Fs.append(np.diag([1.0, 1.0, 1.0 + 1e-9]))  # near rest
    Fs = np.array(Fs)
    R_ref, S_ref = polar_rotation(Fs)
    R, S, X, Y = (np.empty((3, 3)) for _ in range(4))
    for F, Rr, Sr in zip(Fs, R_ref, S_ref):
        kernels._polar(np.ascontiguousarray(F), R, S, X, Y)
        assert np.abs(R - Rr).max() < 1e-13
        assert np.abs(S - Sr).max() < 1e-13 * np.abs(Sr).max()
        assert np.linalg.det(R) > 0 and np.array_equal(S, S.T)


def test_rigid_motion_zero_force_and_typed_errors(deformed):
    fem, _ = deformed
    X = fem.nodes
    x = (X @ rot([2, 1, -1], 75).T + 0.1).reshape(-1)
    assert np.abs(internal_force(fem, x)).max() < 1e-9
    assert abs(strain_energy(fem, x)) < 1e-15
    xm = X.copy()
    xm[:, 2] *= -1  # mirror: every element inverted
    n = len(fem.tets)
    for fn in (internal_force, strain_energy, tangent_stiffness, free_tangent):
        with pytest.raises(ElementInversionError, match=f"{n} of {n} elements inverted"):
            fn(fem, xm)
    xn = X.reshape(-1).copy()
    xn[5] = np.nan
    with pytest.raises(SolverError, match="non-finite"):
        internal_force(fem, xn)
    with pytest.raises(SolverError, match="non-finite"):
        tangent_stiffness(fem, xn)
    with pytest.raises(ElementInversionError):  # free_tangent/energy: NaN counts as inverted
        free_tangent(fem, xn)


def test_numpy_fallback_when_numba_is_off(deformed, monkeypatch):
    fem, x = deformed
    f, K, e = internal_force(fem, x), tangent_stiffness(fem, x).data, strain_energy(fem, x)
    monkeypatch.setattr(C, "USE_NUMBA", False)
    assert np.array_equal(internal_force(fem, x), C.internal_force_numpy(fem, x))
    assert _rel(internal_force(fem, x), f) < 1e-12
    assert _rel(tangent_stiffness(fem, x).data, K) < 1e-12
    assert abs(strain_energy(fem, x) - e) < 1e-12 * e


def test_pattern_and_scatter_equal_the_unique_of_all_dof_pairs():
    X, T = box_mesh((1.0, 2.0, 1.0), (2, 3, 2))
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(X) + 1)  # shuffled numbering, one unused node
    Xp = np.zeros((len(X) + 1, 3))
    Xp[perm[: len(X)]] = X
    Xp[perm[-1]] = [5.0, 5.0, 5.0]
    Tp = perm[T]
    fem = build_fem(Xp, Tp, fixed_nodes=[perm[0]], fixed_dofs=[3 * perm[3] + 1])
    n, m = 3 * len(Xp), len(Tp)
    ed = (3 * Tp[:, :, None] + np.arange(3)).reshape(m, 12)
    keys = (np.repeat(ed, 12, axis=1) * n + np.tile(ed, (1, 12))).reshape(-1)
    ukeys, inv = np.unique(keys, return_inverse=True)
    prow, pcol = np.divmod(ukeys, n)
    assert np.array_equal(fem.pattern_keys, ukeys)
    assert np.array_equal(fem.scatter, inv.reshape(m, 144))
    assert np.array_equal(fem.pattern_indices, pcol)
    assert np.array_equal(fem.pattern_indptr, np.concatenate([[0], np.cumsum(np.bincount(prow, minlength=n))]))
    K = tangent_stiffness(fem, Xp)
    assert np.abs(K - K.T).max() < 1e-9 * np.abs(K).max()


def test_force_and_energy_in_one_pass_equal_the_separate_calls(deformed):
    fem, x = deformed
    f, e = C.force_and_energy(fem, x)
    assert np.array_equal(f, internal_force(fem, x)) and e == strain_energy(fem, x)
    assert e > 0 and np.abs(f).max() > 1.0
