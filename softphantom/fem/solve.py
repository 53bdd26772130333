"""Static equilibrium f_int(x) = f_ext + Σ p_k ∂Φ_k/∂x + f_gravity by Newton with line search and
load stepping, and a sparse direct solver that keeps its symbolic analysis across factorizations."""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from softphantom.errors import SolverError, UserError
from softphantom.fem.actuators import (
    cavity_volume,
    gravity_load,
    pressure_load,
    pressure_tangent_blocks,
)
from softphantom.fem.corotational import (
    ElementInversionError,
    force_and_energy,
    internal_force,
    tangent_data,
)
from softphantom.fem.model import FemModel

SOLVER_METHODS = ("cholmod", "cholespy", "pardiso", "splu")

# CHOLMOD factorizes with the system BLAS, single-threaded: softphantom/__init__.py sets the pools
# (MKL's too, which PARDISO uses).


def _have_cholmod() -> bool:
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


@functools.cache
def have_pardiso() -> bool:
    """Whether MKL PARDISO (pypardiso, the ``pardiso`` extra) is importable and finds MKL."""
    try:
        from pypardiso import PyPardisoSolver

        PyPardisoSolver(mtype=-2)  # loads mkl_rt; ImportError where it is missing
    except (ImportError, OSError):
        return False
    return True


def indefinite_method() -> str:
    """The factorization for symmetric matrices that may be indefinite: MKL PARDISO's LDLᵀ where the
    ``pardiso`` extra is installed (supernodal Bunch-Kaufman; on the default quadratic model's
    tangent with one negative eigenvalue, 83 k DOF, 1.8 CPU-s against SuperLU's 10.7, and 1.3 for
    CHOLMOD's Cholesky of a definite one: benchmarks/bench_factor_indefinite.py), else SuperLU."""
    return "pardiso" if have_pardiso() else "splu"


class _PardisoFactor:
    """One MKL PARDISO LDLᵀ factorization (matrix type −2, real symmetric indefinite) of the upper
    triangle of ``A``. PARDISO keeps the factor in MKL's memory, not Python's: it is released when
    the last reference to this object goes (a :meth:`SparseSolver.copy` shares it).
    ``negative``: the number of negative eigenvalues (the inertia, Sylvester's law on D);
    ``perturbed``: pivots perturbed by PARDISO (1e-8 of the norm), corrected by its iterative
    refinement in each solve."""

    def __init__(self, A: sp.csc_matrix) -> None:
        from pypardiso import PyPardisoSolver
        from pypardiso.pardiso_wrapper import PyPardisoError

        self.U = sp.triu(sp.csr_matrix(A), format="csr")  # A symmetric: either triangle
        self.U.sort_indices()
        s = PyPardisoSolver(mtype=-2)
        s.set_iparm(1, 1)  # the iparm below, not PARDISO's defaults
        s.set_iparm(2, 2)  # nested dissection (METIS)
        s.set_iparm(10, 8)  # pivot perturbation 1e-8
        s.set_iparm(11, 0)  # no scaling and no weighted matching: a near-definite stiffness matrix
        s.set_iparm(13, 0)
        try:
            s.factorize(self.U)
        except PyPardisoError as exc:
            s.free_memory(everything=True)
            raise SolverError(f"PARDISO factorization failed: {exc}") from exc
        self._s = s
        self.negative = int(s.get_iparm(23))
        self.perturbed = int(s.get_iparm(14))

    def solve(self, B: np.ndarray) -> np.ndarray:
        # phase 33 (solve, iterative refinement) on the kept factor; pypardiso's own solve() would
        # hash the whole matrix at each call to recognize it (SHA-1 of ~3 M entries a back-substitution)
        self._s.set_phase(33)
        return self._s._call_pardiso(self.U, np.asfortranarray(B, dtype=np.float64))

    def __del__(self) -> None:
        s = getattr(self, "_s", None)
        if s is not None:
            try:
                s.free_memory(everything=True)  # phase -1: this handle is used once, its analysis too
            except Exception:  # noqa: BLE001 - interpreter shutdown: MKL may be gone already
                pass


def available_solvers() -> tuple[str, ...]:
    """The sparse direct solvers importable here, in order of preference."""
    out = []
    if _have_cholmod():
        out.append("cholmod")
    try:
        import cholespy  # noqa: F401

        out.append("cholespy")
    except ImportError:
        pass
    out.append("splu")
    return tuple(out)


class SparseSolver:
    """Sparse direct solver for symmetric matrices, one factorization, many right-hand sides.

    ``method``: ``"cholmod"`` (scikit-sparse; the symbolic analysis is kept and reused while the
    sparsity pattern stays the same), ``"cholespy"`` (self-contained wheel; re-analyses each time),
    ``"pardiso"`` (MKL PARDISO's LDLᵀ, the ``pardiso`` extra; takes indefinite matrices at the
    cost of a Cholesky and counts their negative eigenvalues, :attr:`negative_eigenvalues`),
    ``"splu"`` (scipy SuperLU; also takes indefinite matrices), or ``"auto"`` (the first available
    of cholmod, cholespy, splu: the Cholesky methods raise :class:`SolverError` on a matrix that
    is not positive definite, the test a Newton step needs; see :func:`indefinite_method`).

    >>> import numpy as np, scipy.sparse as sp
    >>> s = SparseSolver("splu").factorize(sp.csr_matrix(np.diag([2.0, 4.0])))
    >>> s.solve(np.ones((2, 4)))[:, 0].tolist()
    [0.5, 0.25]
    """

    def __init__(self, method: str = "auto") -> None:
        if method == "auto":
            method = available_solvers()[0]
        if method == "pardiso" and not have_pardiso():
            raise UserError("solver 'pardiso' needs the pardiso extra: pip install 'softphantom[pardiso]' (MKL)")
        if method not in SOLVER_METHODS:
            raise UserError(f"solver must be one of {SOLVER_METHODS + ('auto',)}, got {method!r}")
        if method == "cholmod" and not _have_cholmod():
            raise UserError("solver 'cholmod' needs scikit-sparse (and Debian's libsuitesparse-dev)")
        self.method = method
        self._pattern: tuple[np.ndarray, np.ndarray] | None = None
        self._factor = None
        self.n = 0
        self.analyses = 0  # how many symbolic analyses were done (for tests and benchmarks)
        self._numeric = False  # a usable numeric factor is there

    def factorize(self, A: sp.spmatrix) -> SparseSolver:
        """Factorize symmetric ``A``; returns ``self`` for chaining."""
        if A.shape[0] != A.shape[1]:
            raise UserError(f"matrix must be square, got {A.shape}")
        if self.method != "splu" and sp.isspmatrix_csr(A):
            # symmetric: the CSR arrays are those of the CSC of Aᵀ = A (no conversion, no copy;
            # the Cholesky methods read one triangle)
            A = sp.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)
        else:
            A = sp.csc_matrix(A)
        A.sort_indices()
        if not np.all(np.isfinite(A.data)):
            raise SolverError("matrix has non-finite entries")
        self.n = A.shape[0]
        key = self._same_pattern(A)
        try:
            if self.method == "cholmod":
                from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

                if self._factor is None or key is not self._pattern:
                    self._factor = analyze(A, mode="supernodal")
                    self.analyses += 1
                try:
                    self._factor.cholesky_inplace(A)
                except CholmodNotPositiveDefiniteError as exc:
                    # the symbolic analysis stays valid for the next matrix of this pattern
                    # (a shifted retry, the next Newton step): only the numeric factor is lost
                    self._numeric = False
                    raise SolverError("matrix not positive definite (cholmod)") from exc
            elif self.method == "cholespy":
                from cholespy import CholeskySolverD, MatrixType

                try:
                    self._factor = CholeskySolverD(
                        self.n, A.indptr.astype(np.int32), A.indices.astype(np.int32),
                        np.ascontiguousarray(A.data), MatrixType.CSC,
                    )
                except ValueError as exc:
                    self._factor = None
                    self._numeric = False
                    raise SolverError(f"matrix not positive definite (cholespy): {exc}") from exc
                self.analyses += 1
            elif self.method == "pardiso":
                self._factor = None  # the old factor's MKL memory goes first; a failure leaves none
                self._factor = _PardisoFactor(A)
                self.analyses += 1
            else:
                try:
                    # the matrices here are symmetric: a symmetric fill-reducing ordering (minimum
                    # degree on A + Aᵀ) and diagonal pivots first; COLAMD, scipy's default, holds
                    # 1.8x the factor on the 9 mm P2 tangent (68 M vs 38 M entries, 49 k DOF)
                    self._factor = spla.splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
                except RuntimeError as exc:
                    self._numeric = False
                    raise SolverError(f"singular matrix (splu): {exc}") from exc
                self.analyses += 1
        finally:
            self._pattern = key if self._factor is not None else None
        self._numeric = True
        return self

    def copy(self) -> SparseSolver:
        """An independent solver holding the same factorization (and symbolic analysis): a later
        :meth:`factorize` of either leaves the other's factor as it was. CHOLMOD refactors in
        place, so its factor is copied; the other methods make a new factor object each time.

        >>> import numpy as np, scipy.sparse as sp
        >>> a = SparseSolver("splu").factorize(sp.csr_matrix(np.diag([2.0, 4.0])))
        >>> b = a.copy()
        >>> _ = a.factorize(sp.csr_matrix(np.diag([1.0, 1.0])))
        >>> b.solve(np.ones(2)).tolist(), a.solve(np.ones(2)).tolist()
        ([0.5, 0.25], [1.0, 1.0])
        """
        out = SparseSolver(self.method)
        out._pattern, out.n, out.analyses, out._numeric = self._pattern, self.n, self.analyses, self._numeric
        out._factor = self._factor.copy() if self.method == "cholmod" and self._factor is not None else self._factor
        return out

    @property
    def negative_eigenvalues(self) -> int | None:
        """The factored matrix's number of negative eigenvalues where the method gives it
        (``pardiso``; a Cholesky's is 0), else None."""
        if not self.factored:
            return None
        if self.method == "pardiso":
            return self._factor.negative
        return 0 if self.method in ("cholmod", "cholespy") else None

    @property
    def factored(self) -> bool:
        """A usable numeric factor is there (the last :meth:`factorize` succeeded)."""
        return self._factor is not None and self._numeric

    def _same_pattern(self, A: sp.csc_matrix) -> tuple[np.ndarray, np.ndarray]:
        """The kept pattern if ``A`` has it (compared in place, no byte copies), else a copy of
        A's (indptr, indices)."""
        if self._pattern is not None:
            p, i = self._pattern
            if np.array_equal(A.indptr, p) and np.array_equal(A.indices, i):
                return self._pattern
        return (A.indptr.copy(), A.indices.copy())

    def solve(self, B: np.ndarray) -> np.ndarray:
        """Solve A X = B for (n,) or (n,k) ``B``."""
        if not self.factored:
            raise SolverError("solve() before a successful factorize()")
        B = np.asarray(B, dtype=np.float64)
        if B.shape[0] != self.n:
            raise UserError(f"right-hand side has {B.shape[0]} rows, matrix {self.n}")
        if self.method == "cholmod":
            X = self._factor(B)
        elif self.method == "cholespy":
            Bc = np.ascontiguousarray(B)
            X = np.zeros_like(Bc)
            self._factor.solve(Bc, X)
        else:
            X = self._factor.solve(B)
        if not np.all(np.isfinite(X)):
            raise SolverError("linear solve produced non-finite values")
        return X


@dataclass(frozen=True, eq=False)
class StaticSolution:
    """Result of :func:`solve_static`. ``x``, ``u``: (N,3) m. ``residual_norm``: final
    ‖r_free‖ / max(‖f_applied‖, ‖f_int‖) (relative). ``load_fraction`` < 1 if the load stepping
    stopped early (then ``converged`` is False and ``x`` is the last equilibrium reached)."""

    x: np.ndarray
    u: np.ndarray
    iterations: int
    residual_norm: float
    converged: bool
    status: str
    load_steps: int = 1
    load_fraction: float = 1.0


def _pressure_list(fem: FemModel, pressures) -> list[tuple[np.ndarray, float]]:
    if pressures is None:
        return []
    if isinstance(pressures, Mapping):
        out = []
        for name, p in pressures.items():
            if name not in fem.cavities:
                raise UserError(f"unknown cavity {name!r}; have {sorted(fem.cavities)}")
            out.append((np.asarray(fem.cavities[name]), float(p)))
        return out
    return [(np.asarray(t, dtype=np.int64), float(p)) for t, p in pressures]


def indefinite_solve(K: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """Solve symmetric, possibly indefinite ``K`` x = ``b``: MKL PARDISO's LDLᵀ where installed, else
    CHOLMOD's simplicial LDLᵀ (no pivoting, the fill of a Cholesky factor) when scikit-sparse is
    there and its residual is ≤ 1e-8 of ‖b‖, else SuperLU. LU on a 3-D P2 tangent holds several times the Cholesky factor (9 mm design, 49 k
    DOF: 38-68 M entries against 16 M), which a 4.5 mm urethra solve (219 k DOF) cannot afford.

    >>> import numpy as np, scipy.sparse as sp
    >>> K = sp.csr_matrix(np.array([[2.0, 1.0, 0.0], [1.0, -3.0, 1.0], [0.0, 1.0, 1.0]]))  # indefinite
    >>> np.allclose(K @ indefinite_solve(K, np.ones(3)), 1.0)
    True
    """
    b = np.asarray(b, dtype=np.float64)
    if have_pardiso():
        return SparseSolver("pardiso").factorize(K).solve(b)
    if _have_cholmod():
        from sksparse.cholmod import CholmodError, analyze

        A = sp.csc_matrix(K)
        A.sort_indices()
        try:
            f = analyze(A, mode="simplicial")
            f.cholesky_inplace(A)  # simplicial: LDLᵀ, which takes indefinite matrices
            x = f(b)
            if np.all(np.isfinite(x)) and np.linalg.norm(A @ x - b) <= 1e-8 * max(np.linalg.norm(b), 1e-300):
                return x
        except CholmodError:
            pass
    return SparseSolver("splu").factorize(K).solve(b)


SHIFT_MAX_LOAD_STEP = 1.0 / 16
"""Largest load increment (fraction of the load) whose Newton may step on through a tangent that
is not positive definite (:func:`descent_step`); larger increments are halved instead."""

DESCENT_SHIFTS = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)
"""Relative diagonal shifts τ tried, in order, when a Newton tangent is not positive definite."""


def descent_step(solver: SparseSolver, K: sp.csr_matrix, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Newton step K⁻¹``b`` and the shift used (0), or, where the symmetric tangent ``K`` is not
    positive definite — a large load step on a nearly incompressible law, strong compression, an
    inflated cavity — the step of K + τ·max(|diag K|, mean |diag K|) for the first τ of :data:`DESCENT_SHIFTS` whose
    Cholesky holds: a descent direction of the total energy (what the line search needs), on the
    same pattern, symbolic analysis and supernodal fill. The equilibria sought are minima, so the
    tangent is positive definite again near them and plain Newton (quadratic) resumes. Only if every
    shift fails, or for a solver that factors indefinite matrices itself, the unshifted step:
    ``splu``, or :func:`indefinite_solve` (the exact LDLᵀ step, simplicial: on the 9 mm P2 tangent
    with 1.5 mm arms at ν = 0.49, 33 CPU-s against 3.7 s for the supernodal Cholesky).

    >>> import numpy as np, scipy.sparse as sp
    >>> K = sp.csr_matrix(np.array([[2.0, 0.0], [0.0, -1.0]]))  # a saddle
    >>> d, tau = descent_step(SparseSolver("auto"), K, np.array([-1.0, -1.0]))
    >>> tau > 0 or SparseSolver("auto").method == "splu", bool(np.dot(d, [1.0, 1.0]) < 0)
    (True, True)
    """
    try:
        return solver.factorize(K).solve(b), 0.0
    except SolverError:
        if solver.method == "splu":
            raise
    diag = K.diagonal()
    scale = np.maximum(np.abs(diag), max(float(np.mean(np.abs(diag))), 1e-300))  # small pivots get the mean
    Ks = K.copy()  # one copy: each shift overwrites its diagonal
    for tau in DESCENT_SHIFTS:
        Ks.setdiag(diag + tau * scale)
        try:
            return solver.factorize(Ks).solve(b), tau
        except SolverError:
            continue
    return indefinite_solve(K, b), 0.0


def free_tangent(
    fem: FemModel,
    x: np.ndarray,
    pressures: Mapping[str, float] | Sequence[tuple[np.ndarray, float]] | None = None,
    consistent: bool = True,
) -> sp.csr_matrix:
    """(n_free, n_free) Jacobian of the free-DOF residual f_int − Σ p ∂Φ/∂x at ``x``: the Newton
    matrix. Pressure terms are scattered into the mesh's own pattern, so the pattern (and a
    :class:`SparseSolver`'s symbolic analysis) stays the same from call to call."""
    n = fem.n_dof
    plist = [(tri, p) for tri, p in _pressure_list(fem, pressures) if p != 0.0]
    # faces of the mesh go into its own pattern; other triangles need the full matrix
    blocks = [(p, *pressure_tangent_blocks(x, tri)) for tri, p in plist]
    keyed = [(p, r, c, v, np.searchsorted(fem.pattern_keys, r * n + c)) for p, r, c, v in blocks]
    in_pattern = all(
        np.all(fem.pattern_keys[np.minimum(pos, fem.pattern_keys.size - 1)] == r * n + c)
        for _, r, c, _, pos in keyed
    )
    if not in_pattern:
        K = sp.csr_matrix((tangent_data(fem, x, consistent), fem.pattern_indices, fem.pattern_indptr), shape=(n, n))
        K = K - sum((sp.csr_matrix((p * v, (r, c)), shape=(n, n)) for p, r, c, v in blocks), sp.csr_matrix((n, n)))
        return sp.csr_matrix(K[fem.free_dofs][:, fem.free_dofs])
    data = tangent_data(fem, x, consistent, free=True)  # assembled straight into K_ff
    for p, _, _, v, pos in keyed:
        ff = fem.ff_pos[pos]
        keep = ff >= 0
        data -= p * np.bincount(ff[keep], weights=v[keep], minlength=data.size)
    return sp.csr_matrix((data, fem.ff_indices, fem.ff_indptr), shape=(fem.n_free, fem.n_free))


def _applied(fem, x, f_fixed, plist, t):
    f = t * f_fixed
    for tri, p in plist:
        f = f + (t * p) * pressure_load(x, tri, fem.n_nodes)
    return f


def _newton(fem, x, f_fixed, plist, t, tol, max_iter, solver, consistent, on_indefinite="shift"):
    """Newton at load fraction t from x. Returns (ok, x, iterations, rel_residual, reason). On a
    tangent that is not positive definite, ``on_indefinite``: ``"shift"`` steps on with
    :func:`descent_step`; ``"exact"`` takes the exact step (:func:`indefinite_solve`: it can reach an
    equilibrium whose tangent is indefinite, e.g. an inflated cavity past its pressure maximum);
    ``"cut"`` ends the attempt (so the caller cuts the load step)."""
    free = fem.free_dofs
    x_rest = fem.x_rest

    def residual_and_potential(xx):
        fi, energy = force_and_energy(fem, xx)
        fa = _applied(fem, xx, f_fixed, plist, t)
        ref = max(np.linalg.norm(fa), np.linalg.norm(fi), 1e-300)
        # total potential energy: the forces are conservative (pressure load = p ∂Φ/∂x)
        pi = energy - t * np.dot(f_fixed, xx - x_rest)
        for tri, p in plist:
            pi -= t * p * cavity_volume(xx, tri)
        return (fi - fa)[free], ref, pi

    floor = fem.residual_floor()  # below it a smaller residual is round-off noise

    r, ref, pi0 = residual_and_potential(x)
    rn = np.linalg.norm(r)
    scaled = [(tri, t * p) for tri, p in plist]
    for it in range(max_iter + 1):
        if rn <= max(tol * ref, floor):
            return True, x, it, rn / ref, "converged"
        if it == max_iter:
            break
        K = free_tangent(fem, x, scaled, consistent)
        if on_indefinite == "shift":
            d, _ = descent_step(solver, K, -r)
        else:
            try:
                d = solver.factorize(K).solve(-r)
            except SolverError:
                if solver.method == "splu":
                    raise
                if on_indefinite == "cut":
                    return False, x, it + 1, rn / ref, "tangent not positive definite"
                d = indefinite_solve(K, -r)
        slope = float(np.dot(r, d))  # dΠ/dα at α = 0
        alpha, accepted, inverted = 1.0, False, 0
        for _ in range(12):
            xt = x.copy()
            xt[free] += alpha * d
            try:
                rt, reft, pit = residual_and_potential(xt)
            except ElementInversionError as exc:
                inverted = exc.count
                alpha *= 0.5
                continue
            rtn = np.linalg.norm(rt)
            # Armijo on the energy; or a plain decrease of the residual (the energy difference is
            # lost in round-off near convergence, and d may not descend if K is indefinite).
            if (slope < 0 and pit <= pi0 + 1e-4 * alpha * slope) or rtn < rn or rtn <= floor:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            why = f"line search failed ({inverted} elements inverted along the step)" if inverted else "line search failed"
            return False, x, it + 1, rn / ref, why
        x, r, rn, ref, pi0 = xt, rt, rtn, reft, pit
    return False, x, max_iter, rn / ref, f"no convergence in {max_iter} iterations"


def solve_static(
    fem: FemModel,
    f_ext: np.ndarray | None = None,
    pressures: Mapping[str, float] | Sequence[tuple[np.ndarray, float]] | None = None,
    gravity: bool = False,
    x0: np.ndarray | None = None,
    tol: float = 1e-8,
    max_iter: int = 25,
    solver: str | SparseSolver = "auto",
    *,
    consistent: bool = True,
    min_load_step: float = 1.0 / 1024,
    on_indefinite: str | None = None,
) -> StaticSolution:
    """Quasi-static equilibrium of the co-rotational model under nodal forces ``f_ext`` ((3N,) N,
    e.g. ``force_actuator(fem, p) @ λ``), cavity ``pressures`` (Pa; a dict cavity name → p for a
    model with cavities, or a sequence of (triangles, p) pairs), and optionally gravity (−z).

    Newton on the free DOFs (consistent tangent) with a backtracking line search (Armijo on the
    total potential energy, or a decrease of the residual norm); converged when
    ‖r_free‖ ≤ ``tol`` · max(‖f_applied‖, ‖f_int‖), or below the round-off floor of the internal
    force (16·eps·(2μ+λ)·V·|∇N| per node, reached only at strains below ~1e-7). If a load step
    fails (no convergence, line search failure, inversion, a tangent that is not positive definite
    while the increment is above :data:`SHIFT_MAX_LOAD_STEP`) the load increment is halved
    (adaptive load stepping); small increments step on with a shifted tangent. Fixed DOFs
    stay where ``x0`` puts them (rest by default), which also prescribes displacements.
    ``on_indefinite`` ("shift", "cut", "exact") overrides that choice for every increment (a caller
    that tries one full-load increment and has its own fallback: "shift", not the slow exact step).

    >>> import numpy as np
    >>> from softphantom.fem.model import build_fem
    >>> from softphantom.fem.material import Material
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> fem = build_fem(X, np.array([[0, 1, 2, 3]]), Material(1e3, 0.3), fixed_nodes=[0, 1, 2])
    >>> f = np.zeros(12); f[11] = 1.0  # 1 N along z on node 3
    >>> sol = solve_static(fem, f, solver="splu")
    >>> sol.converged, sol.u[3, 2] > 0
    (True, np.True_)
    """
    n = fem.n_dof
    x = fem.x_rest.copy() if x0 is None else np.array(x0, dtype=np.float64).reshape(-1)
    if x.size != n:
        raise UserError(f"x0 has {x.size} values, expected {n}")
    f_fixed = np.zeros(n) if f_ext is None else np.asarray(f_ext, dtype=np.float64).reshape(-1)
    if f_fixed.size != n:
        raise UserError(f"f_ext has {f_fixed.size} values, expected {n}")
    if gravity:
        f_fixed = f_fixed + gravity_load(fem)
    if not (np.all(np.isfinite(f_fixed)) and np.all(np.isfinite(x))):
        raise UserError("non-finite loads or initial positions")
    if on_indefinite not in (None, "shift", "cut", "exact"):
        raise UserError(f"on_indefinite must be shift, cut or exact, got {on_indefinite!r}")
    plist = _pressure_list(fem, pressures)
    lin = solver if isinstance(solver, SparseSolver) else SparseSolver(solver)
    internal_force(fem, x)  # raises ElementInversionError on an inverted start

    t, dt, total_it, steps = 0.0, 1.0, 0, 0
    rel, status = 0.0, "converged"
    while t < 1.0:
        t_try = min(1.0, t + dt)
        # a tangent that loses definiteness within a large load step means the step is too large
        # (the conventional remedy: continuation); only small steps may step on, shifted (a
        # genuinely indefinite path, e.g. an inflating cavity). Where paths can part: at nu = 0.49
        # the 9 mm P2 mesh has two converged states 0.2 % apart (docs/model.md). An increment that
        # cannot be cut (a caller's own continuation: min_load_step 1) takes the exact step (it
        # can reach an equilibrium past a cavity's pressure maximum) unless the caller says "shift"
        policy = on_indefinite or (
            "exact" if dt * 0.5 < min_load_step else "shift" if dt <= SHIFT_MAX_LOAD_STEP else "cut")
        ok, x_new, its, rel_try, reason = _newton(
            fem, x, f_fixed, plist, t_try, tol, max_iter, lin, consistent, on_indefinite=policy
        )
        total_it += its
        if ok:
            x, t, rel = x_new, t_try, rel_try
            steps += 1
            if its <= 4:
                dt *= 2.0
        else:
            dt *= 0.5
            if dt < min_load_step:
                status = f"{reason} at load fraction {t_try:.4g} (reached {t:.4g})"
                rel = rel_try
                break
    X = x.reshape(-1, 3)
    return StaticSolution(
        x=X,
        u=X - fem.nodes,
        iterations=total_it,
        residual_norm=float(rel),
        converged=t >= 1.0,
        status="converged" if t >= 1.0 else status,
        load_steps=steps,
        load_fraction=float(t),
    )
