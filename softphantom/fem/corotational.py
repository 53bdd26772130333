"""Internal force, strain energy and tangent stiffness of any law on linear or quadratic tets.

The public functions (:func:`internal_force`, :func:`strain_energy`, :func:`tangent_stiffness`,
:func:`tangent_data`) run the numba element kernels of :mod:`softphantom.fem.kernels`, which call
each element's law point function at each quadrature point. The rest of this module is the batched
numpy reference of the co-rotational law on linear tets (the paper's model), which the kernels are
tested against and which serves as the fallback without numba for such models:

Per element, F = Ds·Dm⁻¹ = R·S (polar decomposition, batched SVD with a reflection guard), and the
stress is Hooke's law on the corotated strain S − I: σ = 2μ(S − I) + λ tr(S − I) I, first
Piola–Kirchhoff P = R σ, nodal forces f_a = V P ∇N_a. This equals the classic R K0 (Rᵀx − X) force
and is the gradient of the energy V(μ‖S − I‖² + λ/2 tr²(S − I)) ("corotated linear" elasticity),
so its consistent tangent is symmetric. :func:`tangent_stiffness` gives that consistent tangent
(with the rotation-derivative term) by default, or the approximate R K0 Rᵀ with ``consistent=False``.

``USE_NUMBA`` False (no numba, or a test) sends co-rotational P1 models to the numpy path; other
models then run the kernels as plain Python.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from softphantom.errors import SolverError
from softphantom.fem import kernels
from softphantom.fem.model import FemModel

_I3 = np.eye(3)

#: Use the numba kernels (True where numba imports). Tests flip it to run the numpy reference.
USE_NUMBA = kernels.HAVE_NUMBA


class ElementInversionError(SolverError):
    """Some elements have det F <= 0 (inverted or degenerate) in the current configuration
    (counted over quadrature points for quadratic tets)."""

    def __init__(self, count: int, total: int, what: str = "elements") -> None:
        self.count = count
        super().__init__(f"{count} of {total} {what} inverted (det F <= 0)")


def _raise_inverted(fem: FemModel, bad: int) -> None:
    if fem.wq.shape[1] == 1:
        raise ElementInversionError(int(bad), fem.tets.shape[0])
    raise ElementInversionError(int(bad), fem.wq.size, "quadrature points")


def _numpy_path(fem: FemModel) -> bool:
    return not USE_NUMBA and fem.order == 1 and fem.all_corotational


def deformation_gradient(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(M,3,3) F = Σ_a x_a ⊗ ∇N_a for positions ``x`` ((3N,) or (N,3))."""
    xe = np.asarray(x, dtype=np.float64).reshape(-1, 3)[fem.tets]
    return np.einsum("mai,maj->mij", xe, fem.grads)


def _check_finite(x: np.ndarray) -> None:
    if not np.all(np.isfinite(x)):
        raise SolverError("non-finite node positions")


def polar_rotation(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched polar decomposition F = R S (R proper rotation, S symmetric) by SVD.

    Raises :class:`ElementInversionError` if any det F <= 0.

    >>> import numpy as np
    >>> c, s = np.cos(0.3), np.sin(0.3)
    >>> Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    >>> R, S = polar_rotation((Rz @ np.diag([1.1, 0.9, 1.0]))[None])
    >>> bool(np.allclose(R[0], Rz)), bool(np.allclose(S[0], np.diag([1.1, 0.9, 1.0])))
    (True, True)
    """
    det = np.linalg.det(F)
    bad = ~(det > 0)  # also catches NaN
    if np.any(bad):
        raise ElementInversionError(int(bad.sum()), F.shape[0])
    U, s, Vt = np.linalg.svd(F)
    # Reflection guard: det F > 0 makes det(U Vt) > 0 in exact arithmetic; enforce it anyway.
    sign = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    U[:, :, 2] *= sign[:, None]
    s[:, 2] *= sign
    R = U @ Vt
    S = np.einsum("mki,mk,mkj->mij", Vt, s, Vt)
    return R, S


def _stress(fem: FemModel, S: np.ndarray) -> np.ndarray:
    E = S - _I3
    tr = np.trace(E, axis1=1, axis2=2)
    return 2.0 * fem.mu[:, None, None] * E + (fem.lam * tr)[:, None, None] * _I3


def element_forces(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(M,4,3) internal nodal forces of each element."""
    R, S = polar_rotation(deformation_gradient(fem, x))
    P = R @ _stress(fem, S)
    return np.einsum("m,mij,maj->mai", fem.volumes, P, fem.grads)


def _flat(x: np.ndarray) -> np.ndarray:
    """(3N,) C-contiguous float64, read-only view: one array type for the kernels, so numba compiles
    (or loads from its cache) one specialization, never a second one mid-run for a writable x."""
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1).view()
    x.flags.writeable = False
    return x


def internal_force_numpy(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """The numpy reference of :func:`internal_force` (batched SVD, bincount assembly)."""
    x = np.asarray(x, dtype=np.float64)
    _check_finite(x)
    fe = element_forces(fem, x)
    return np.bincount(fem.elem_dofs.reshape(-1), weights=fe.reshape(-1), minlength=fem.n_dof)


def internal_force(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(3N,) co-rotational internal force at positions ``x`` ((3N,) or (N,3)); zero at rest and
    under any rigid motion.

    >>> import numpy as np
    >>> from softphantom.fem.model import build_fem
    >>> from softphantom.fem.material import Material
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> fem = build_fem(X, np.array([[0, 1, 2, 3]]), Material(1e3, 0.3))
    >>> c, s = np.cos(1.0), np.sin(1.0)
    >>> R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    >>> float(np.abs(internal_force(fem, X @ R.T + 5.0)).max()) < 1e-10
    True
    """
    if _numpy_path(fem):
        return internal_force_numpy(fem, x)
    return force_and_energy(fem, x)[0]


_NO_FORCE, _NO_STRESS = np.empty(0), np.empty((0, 3, 3))


def _point_loop(fem: FemModel, x: np.ndarray, mode: int, force=_NO_FORCE, stress=_NO_STRESS) -> float:
    """Run :func:`kernels.point_loop_kernel` (energy; and force or stress by ``mode``) at ``x``;
    returns the energy, raises :class:`ElementInversionError`."""
    bad, energy = kernels.point_loop_kernel(
        x, fem.tets, fem.dN, fem.wq, fem.law_id, fem.params, fem.elem_dofs, mode, force, stress
    )
    if bad:
        _raise_inverted(fem, bad)
    return float(energy)


def force_and_energy(fem: FemModel, x: np.ndarray) -> tuple[np.ndarray, float]:
    """(:func:`internal_force`, :func:`strain_energy`) at ``x`` in one pass over the quadrature
    points (a Newton line search needs both at each trial)."""
    if _numpy_path(fem):
        return internal_force_numpy(fem, x), strain_energy_numpy(fem, x)
    x = _flat(x)
    _check_finite(x)
    out = np.empty(fem.n_dof)
    return out, _point_loop(fem, x, kernels.MODE_FORCE, force=out)


def strain_energy(fem: FemModel, x: np.ndarray) -> float:
    """J, Σ_e Σ_q w_q W(F): the energy whose gradient is :func:`internal_force` (co-rotational:
    W = μ‖S − I‖² + λ/2 tr²(S − I))."""
    if _numpy_path(fem):
        return strain_energy_numpy(fem, x)
    return _point_loop(fem, _flat(x), kernels.MODE_ENERGY)


def strain_energy_numpy(fem: FemModel, x: np.ndarray) -> float:
    """The numpy reference of :func:`strain_energy`."""
    _, S = polar_rotation(deformation_gradient(fem, x))
    E = S - _I3
    tr = np.trace(E, axis1=1, axis2=2)
    w = fem.mu * np.einsum("mij,mij->m", E, E) + 0.5 * fem.lam * tr**2
    return float(np.dot(fem.volumes, w))


def corotated_stress(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(M,3,3) Pa, the corotated Cauchy-like stress R σ Rᵀ per element (small strain, large rotation)."""
    R, S = polar_rotation(deformation_gradient(fem, x))
    return R @ _stress(fem, S) @ np.swapaxes(R, 1, 2)


def cauchy_stress(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(M,3,3) Pa, each element's volume-weighted mean Cauchy stress σ = P Fᵀ / J of its law over its
    quadrature points (any law, any order). For the co-rotational law on linear tets it equals
    :func:`corotated_stress` up to O(strain²)."""
    x = _flat(x)
    _check_finite(x)
    out = np.empty((fem.tets.shape[0], 3, 3))
    _point_loop(fem, x, kernels.MODE_STRESS, stress=out)
    return out


def von_mises(stress: np.ndarray) -> np.ndarray:
    """(M,) von Mises equivalent of (M,3,3) stresses, sqrt(3/2 s:s) with s the deviator."""
    dev = stress - np.trace(stress, axis1=1, axis2=2)[:, None, None] * _I3 / 3.0
    return np.sqrt(1.5 * np.einsum("mij,mij->m", dev, dev))


def _dP_dF(fem: FemModel, R: np.ndarray, S: np.ndarray, consistent: bool) -> np.ndarray:
    """(M,9,9) dP/dF of P = R σ(S), rows and columns row-major over (i,j)."""
    m = R.shape[0]
    # dF = E_kl (unit matrix): M = Rᵀ dF has entries M_ij = R_ki δ_lj, stored [m, kl, i, j]
    M = np.einsum("mki,lj->mklij", R, _I3).reshape(m, 9, 3, 3)
    if consistent:
        A = M - np.swapaxes(M, 2, 3)
        a = np.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], axis=-1)  # axial vector, (m,9,3)
        trS = np.trace(S, axis1=1, axis2=2)
        # W S + S W = [G w]x with G = tr(S) I − S, positive definite while det F > 0
        Ginv = np.linalg.inv(trS[:, None, None] * _I3 - S)
        w = np.einsum("mij,mkj->mki", Ginv, a)
        W = np.zeros((m, 9, 3, 3))
        W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
        W = W - np.swapaxes(W, 2, 3)
        dS = M - W @ S[:, None]
        inner = W @ _stress(fem, S)[:, None]
    else:
        dS = 0.5 * (M + np.swapaxes(M, 2, 3))
        inner = 0.0
    trd = np.trace(dS, axis1=2, axis2=3)
    dsig = 2.0 * fem.mu[:, None, None, None] * dS + (fem.lam[:, None] * trd)[..., None, None] * _I3
    dP = R[:, None] @ (inner + dsig)  # [m, kl, i, j]
    return np.swapaxes(dP.reshape(m, 9, 9), 1, 2)


def _B(fem: FemModel) -> np.ndarray:
    """(M,9,12) d vec(F) / d x_e: ∂F_ij/∂x_(a,l) = δ_il ∇N_a,j."""
    m = fem.tets.shape[0]
    B = np.zeros((m, 3, 3, 4, 3))
    for i in range(3):
        B[:, i, :, :, i] = np.swapaxes(fem.grads, 1, 2)
    return B.reshape(m, 9, 12)


def element_stiffness(fem: FemModel, x: np.ndarray, consistent: bool = True) -> np.ndarray:
    """(M,12,12) element tangents V Bᵀ (dP/dF) B, node-major local DOFs."""
    R, S = polar_rotation(deformation_gradient(fem, x))
    D = _dP_dF(fem, R, S, consistent)
    B = _B(fem)
    return np.swapaxes(B, 1, 2) @ (D @ B) * fem.volumes[:, None, None]


def assemble_pattern(fem: FemModel, Ke: np.ndarray) -> np.ndarray:
    """Data array of the full stiffness in ``fem``'s CSR pattern from (M,12,12) element blocks."""
    return np.bincount(
        fem.scatter.reshape(-1), weights=Ke.reshape(-1), minlength=fem.pattern_keys.size
    )


def tangent_data_numpy(fem: FemModel, x: np.ndarray, consistent: bool = True) -> np.ndarray:
    """The numpy reference of :func:`tangent_data`: (M,12,12) element blocks, then bincount."""
    return assemble_pattern(fem, element_stiffness(fem, x, consistent))


def tangent_data(fem: FemModel, x: np.ndarray, consistent: bool = True, free: bool = False) -> np.ndarray:
    """Data array of the full tangent in ``fem``'s CSR pattern (``pattern_indptr``/``_indices``),
    or (``free``) of its free–free part in the pattern ``ff_indptr``/``ff_indices`` (assembled
    there directly).

    Raises :class:`ElementInversionError` if any det F <= 0 (NaN positions included)."""
    if _numpy_path(fem):
        data = tangent_data_numpy(fem, x, consistent)
        return data[fem.ff_pos >= 0] if free else data
    data = np.empty(fem.ff_indices.size if free else fem.pattern_keys.size)
    bad = kernels.tangent_kernel(
        _flat(x), fem.tets, fem.dN, fem.wq, fem.law_id, fem.params,
        fem.scatter_ff if free else fem.scatter, bool(consistent), data,
    )
    if bad:
        _raise_inverted(fem, bad)
    return data


def tangent_stiffness_numpy(fem: FemModel, x: np.ndarray, consistent: bool = True) -> sp.csr_matrix:
    """The numpy reference of :func:`tangent_stiffness`."""
    x = np.asarray(x, dtype=np.float64)
    _check_finite(x)
    data = tangent_data_numpy(fem, x, consistent)
    return sp.csr_matrix(
        (data, fem.pattern_indices, fem.pattern_indptr), shape=(fem.n_dof, fem.n_dof)
    )


def tangent_stiffness(fem: FemModel, x: np.ndarray, consistent: bool = True) -> sp.csr_matrix:
    """(3N,3N) tangent d f_int / d x at ``x`` as CSR (all DOFs, fixed ones included).

    ``consistent=True`` includes the rotation-derivative (geometric) term: the exact, symmetric
    Hessian of the corotated energy (quadratic Newton convergence). ``consistent=False`` gives the
    classic R K0 Rᵀ (always positive semi-definite; error in d f of the order of the stress/E).

    >>> import numpy as np
    >>> from softphantom.fem.model import build_fem
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> fem = build_fem(X, np.array([[0, 1, 2, 3]]))
    >>> K = tangent_stiffness(fem, X)
    >>> K.shape, float(abs(K @ np.tile([1.0, 0, 0], 4)).max()) < 1e-6
    ((12, 12), True)
    """
    x = np.asarray(x, dtype=np.float64)
    _check_finite(x)
    data = tangent_data(fem, x, consistent)
    return sp.csr_matrix(
        (data, fem.pattern_indices, fem.pattern_indptr), shape=(fem.n_dof, fem.n_dof)
    )


def linear_internal_force(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(3N,) K0 (x − X): small-strain linear elasticity (not rotation invariant), for comparison."""
    K0 = tangent_stiffness(fem, fem.nodes)
    return K0 @ (np.asarray(x, dtype=np.float64).reshape(-1) - fem.x_rest)
