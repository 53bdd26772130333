"""The precomputed FEM model: rest geometry, shape-function gradients, Lamé constants, DOF indexing
and the sparsity pattern with scatter indices (so every assembly is one vectorized numpy pass)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from softphantom.errors import MeshError, UserError
from softphantom.fem import kernels
from softphantom.fem.material import ECOFLEX_00_50, Material

# Local DOF order of a tet: node-major (node a, component i) -> 3a + i.
_LOCAL = np.arange(12)


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class FemModel:
    """Everything the co-rotational assembly needs, computed once by :func:`build_fem`.

    Arrays are read-only. ``n_dof = 3 * n_nodes``; DOF ``3*i + k`` is component ``k`` of node ``i``.
    ``pattern_indptr``/``pattern_indices`` give the CSR pattern of the full stiffness and
    ``scatter`` (M, 144) the position in its data array of each entry of each element's 12×12 block
    (row-major, node-major local DOFs). ``free_take`` picks the free–free part of the data array, in
    the CSR order of ``ff_indptr``/``ff_indices``.
    """

    nodes: np.ndarray  # (N,3) m, rest positions
    tets: np.ndarray  # (M,4) int64, positive orientation
    grads: np.ndarray  # (M,4,3) 1/m, ∇N_a in the rest configuration
    volumes: np.ndarray  # (M,) m³
    mu: np.ndarray  # (M,) Pa
    lam: np.ndarray  # (M,) Pa
    density: np.ndarray  # (M,) kg/m³
    fixed_dofs: np.ndarray  # sorted DOF indices held fixed (Dirichlet)
    free_dofs: np.ndarray  # sorted complementary DOF indices
    dof_map: np.ndarray  # (3N,) free index of a DOF, -1 if fixed
    elem_dofs: np.ndarray  # (M,12) global DOFs of each element
    pattern_indptr: np.ndarray
    pattern_indices: np.ndarray
    pattern_keys: np.ndarray  # sorted row*n_dof+col of the pattern entries
    scatter: np.ndarray  # (M,144) into the pattern data
    free_take: np.ndarray  # pattern positions of the free–free entries
    ff_indptr: np.ndarray
    ff_indices: np.ndarray
    boundary_faces: np.ndarray  # (B,3) outer + cavity surface triangles, normals out of the solid
    cavities: Mapping[str, np.ndarray] = field(default_factory=dict)  # name -> (K,3) triangles

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def n_dof(self) -> int:
        return 3 * self.n_nodes

    @property
    def n_free(self) -> int:
        return int(self.free_dofs.size)

    @property
    def x_rest(self) -> np.ndarray:
        """Rest positions flattened to (3N,)."""
        return self.nodes.reshape(-1)

    def lumped_mass(self) -> np.ndarray:
        """(N,) kg: each tet's mass split equally over its 4 nodes."""
        m = np.repeat(self.density * self.volumes / 4.0, 4)
        return np.bincount(self.tets.reshape(-1), weights=m, minlength=self.n_nodes)


def _boundary_faces(tets: np.ndarray) -> np.ndarray:
    # Faces opposite each vertex, ordered so (b-a)x(c-a) points away from the opposite vertex.
    faces = np.concatenate(
        [tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]]
    )
    key = np.sort(faces, axis=1)
    n = int(tets.max()) + 1
    if n < 2**20:  # one int64 per face: a 1-D unique, much faster than np.unique(axis=0)
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:
        _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.reshape(-1)] == 1]


def _pattern(tets: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """CSR pattern of the (3n,3n) stiffness of ``tets`` and the scatter indices (M,144).

    Built from the node adjacency (16 node pairs per tet instead of 144 DOF pairs: the pattern is
    made of full 3×3 blocks), with the same result as ``np.unique`` of all the DOF keys
    (row-major, sorted columns). Returns (indptr, row, col, scatter) with row/col per entry."""
    m = tets.shape[0]
    pair = (tets[:, :, None] * n + tets[:, None, :]).reshape(-1)
    upair, pinv = np.unique(pair, return_inverse=True)
    nrow, ncol = np.divmod(upair, n)
    nptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(nrow, minlength=n), out=nptr[1:])
    deg = np.diff(nptr)
    rank = np.arange(upair.size, dtype=np.int64) - nptr[nrow]
    # entry (node row i, component p; node column j = rank r in the row, component q) lies at
    # 9·nptr[i] + 3p·deg[i] + 3r + q
    base = 9 * nptr[nrow] + 3 * rank  # (P,)
    p3 = np.arange(3)
    pos = base[:, None, None] + 3 * p3[None, :, None] * deg[nrow][:, None, None] + p3[None, None, :]
    nnz = 9 * upair.size
    prow = np.empty(nnz, dtype=np.int64)
    pcol = np.empty(nnz, dtype=np.int64)
    prow[pos] = (3 * nrow[:, None, None] + p3[None, :, None]) + 0 * p3[None, None, :]
    pcol[pos] = (3 * ncol[:, None, None] + p3[None, None, :]) + 0 * p3[None, :, None]
    indptr = (9 * nptr[:-1, None] + 3 * p3[None, :] * deg[:, None]).reshape(-1)
    indptr = np.append(indptr, nnz)
    # element entry (a,i),(b,j) -> 12·(3a+i) + 3b+j
    s = pinv.reshape(m, 4, 4)
    d_row = deg[tets]  # (M,4), degree of the row node a
    scatter = (
        base[s][:, :, None, :, None]
        + 3 * p3[None, None, :, None, None] * d_row[:, :, None, None, None]
        + p3[None, None, None, None, :]
    )
    return indptr, prow, pcol, scatter.reshape(m, 144)


def _per_tet_materials(materials, n_tets: int) -> list[Material] | Material:
    if isinstance(materials, Material):
        return materials
    mats = list(materials)
    if len(mats) != n_tets:
        raise UserError(f"materials: expected one Material or {n_tets} (one per tet), got {len(mats)}")
    return mats


def build_fem(
    nodes: np.ndarray,
    tets: np.ndarray,
    materials: Material | Sequence[Material] = ECOFLEX_00_50,
    fixed_nodes: np.ndarray | Sequence[int] = (),
    *,
    fixed_dofs: np.ndarray | Sequence[int] = (),
    cavities: Mapping[str, np.ndarray] | None = None,
) -> FemModel:
    """Precompute a :class:`FemModel` for linear tetrahedra.

    ``fixed_nodes`` clamps all three components of those nodes; ``fixed_dofs`` clamps single DOFs
    (``3*node + component``), e.g. for symmetry planes. Tets must be positively oriented.

    >>> import numpy as np
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> fem = build_fem(X, np.array([[0, 1, 2, 3]]), fixed_nodes=[0])
    >>> fem.n_free, round(float(fem.volumes[0]), 6), fem.boundary_faces.shape
    (9, 0.166667, (4, 3))
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"expected nodes (N,3) and tets (M,4), got {nodes.shape} and {tets.shape}")
    n, m = nodes.shape[0], tets.shape[0]
    if m == 0 or tets.min() < 0 or tets.max() >= n:
        raise MeshError("tets must be non-empty and index existing nodes")

    Dm = np.swapaxes(nodes[tets[:, 1:]] - nodes[tets[:, [0]]], 1, 2)  # columns X_a - X_0
    det = np.linalg.det(Dm)
    if np.any(det <= 0):
        raise MeshError(f"{int(np.sum(det <= 0))} tets with non-positive orientation (det <= 0)")
    Dm_inv = np.linalg.inv(Dm)
    g123 = Dm_inv  # row a-1 of Dm^{-1} is ∇N_a
    grads = np.concatenate([-g123.sum(axis=1, keepdims=True), g123], axis=1)

    mats = _per_tet_materials(materials, m)
    if isinstance(mats, Material):
        mu = np.full(m, mats.mu_Pa)
        lam = np.full(m, mats.lambda_Pa)
        rho = np.full(m, mats.density_kg_m3)
    else:
        mu = np.array([mt.mu_Pa for mt in mats])
        lam = np.array([mt.lambda_Pa for mt in mats])
        rho = np.array([mt.density_kg_m3 for mt in mats])

    fixed = np.concatenate(
        [
            (3 * np.asarray(fixed_nodes, dtype=np.int64)[:, None] + np.arange(3)).reshape(-1),
            np.asarray(fixed_dofs, dtype=np.int64).reshape(-1),
        ]
    )
    fixed = np.unique(fixed)
    if fixed.size and (fixed.min() < 0 or fixed.max() >= 3 * n):
        raise UserError("fixed nodes/DOFs out of range")
    is_free = np.ones(3 * n, dtype=bool)
    is_free[fixed] = False
    free = np.flatnonzero(is_free)
    dof_map = np.full(3 * n, -1, dtype=np.int64)
    dof_map[free] = np.arange(free.size)

    edofs = (3 * tets[:, :, None] + np.arange(3)).reshape(m, 12)
    indptr, prow, pcol, scatter = _pattern(tets, n)
    ukeys = prow * (3 * n) + pcol
    ff = is_free[prow] & is_free[pcol]
    take = np.flatnonzero(ff)
    frow = dof_map[prow[take]]
    ff_indptr = np.concatenate([[0], np.cumsum(np.bincount(frow, minlength=free.size))])

    kernels.warm_up()  # numba: compile or load the kernels now, once per process
    return FemModel(
        nodes=_ro(nodes),
        tets=_ro(tets),
        grads=_ro(grads),
        volumes=_ro(det / 6.0),
        mu=_ro(mu),
        lam=_ro(lam),
        density=_ro(rho),
        fixed_dofs=_ro(fixed),
        free_dofs=_ro(free),
        dof_map=_ro(dof_map),
        elem_dofs=_ro(edofs),
        pattern_indptr=_ro(indptr.astype(np.int64)),
        pattern_indices=_ro(pcol.astype(np.int64)),
        pattern_keys=_ro(ukeys),
        scatter=_ro(scatter),
        free_take=_ro(take),
        ff_indptr=_ro(ff_indptr.astype(np.int64)),
        ff_indices=_ro(dof_map[pcol[take]]),
        boundary_faces=_ro(_boundary_faces(tets)),
        cavities={k: _ro(np.asarray(v, dtype=np.int64)) for k, v in (cavities or {}).items()},
    )


def fem_from_phantom(model, materials: Mapping[str, Material] | Material | None = None) -> FemModel:
    """Build the :class:`FemModel` of a ``PhantomModel`` (softphantom.design).

    ``materials`` is one Material for every region, or a dict region name -> Material; regions
    not named get :data:`ECOFLEX_00_50`. Arm ends (``model.fixed_nodes``) are clamped; the
    cavities are carried over so :func:`solve_static` accepts pressures by cavity name.
    """
    if materials is None or isinstance(materials, Material):
        mats: Material | list[Material] = materials or ECOFLEX_00_50
    else:
        unknown = set(materials) - set(model.regions)
        if unknown:
            raise UserError(f"materials: unknown region(s) {sorted(unknown)}; have {sorted(model.regions)}")
        by_id = {rid: materials.get(name, ECOFLEX_00_50) for name, rid in model.regions.items()}
        mats = [by_id[int(r)] for r in np.asarray(model.tet_region)]
    return build_fem(
        model.nodes, model.tets, mats, model.fixed_nodes, cavities=dict(model.cavities)
    )
