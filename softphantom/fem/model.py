"""The precomputed FEM model: rest geometry, shape-function gradients at the quadrature points,
the material law of each element, DOF indexing and the sparsity pattern with scatter indices (so
every assembly is one pass of a numba kernel)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from softphantom.errors import MeshError, UserError
from softphantom.fem import elements, kernels
from softphantom.fem.material import DEFAULT_LAW, LAWS, Corotational, Law
from softphantom.records.channels import ChannelLayout


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class FemModel:
    """Everything the assembly needs, computed once by :func:`build_fem`.

    Arrays are read-only. ``n_dof = 3 * n_nodes``; DOF ``3*i + k`` is component ``k`` of node ``i``.
    ``tets`` is the element connectivity: (M,4) linear or (M,10) quadratic tets (corners first,
    then mid-edge nodes in :mod:`softphantom.fem.elements` order); ``order`` is 1 or 2. ``dN``
    (M,Q,n,3) and ``wq`` (M,Q) are the rest shape-function gradients and weights × det J at the
    Q quadrature points (1 for P1, 4 for P2). ``grads``/``volumes`` are those of the straight
    corner tet (point location, scales). ``law_id``/``params`` (M,)/(M,4) select each element's law
    and its parameter row; ``mu``/``lam`` are its small-strain Lamé constants (Pa).
    ``pattern_indptr``/``pattern_indices`` give the CSR pattern of the full stiffness and
    ``scatter`` (M, (3n)²) the position in its data array of each entry of each element block
    (row-major, node-major local DOFs); ``scatter_ff`` the same into the data array of the
    free–free part (CSR ``ff_indptr``/``ff_indices``), −1 where a row or column is fixed, so the
    Newton matrix is assembled in place; ``ff_pos`` maps a position of the full pattern to the
    free–free one (−1: fixed). Index arrays are int32 where they fit (scipy and CHOLMOD take them
    without a copy). ``boundary_faces`` (B,3|6) and the
    ``cavities`` (K,3|6) are triangles of the element's order; ``layout`` (a phantom's
    :class:`~softphantom.records.channels.ChannelLayout`, None for a bare mesh) names those the
    sensors read and the loads inflate, in order.
    """

    nodes: np.ndarray  # (N,3) m, rest positions
    tets: np.ndarray  # (M,4|10) int64, positive orientation
    grads: np.ndarray  # (M,4,3) 1/m, ∇L_a of the straight corner tet
    volumes: np.ndarray  # (M,) m³ of the straight corner tet
    mu: np.ndarray  # (M,) Pa, small-strain shear modulus
    lam: np.ndarray  # (M,) Pa, small-strain first Lamé constant
    density: np.ndarray  # (M,) kg/m³
    fixed_dofs: np.ndarray  # sorted DOF indices held fixed (Dirichlet)
    free_dofs: np.ndarray  # sorted complementary DOF indices
    dof_map: np.ndarray  # (3N,) free index of a DOF, -1 if fixed
    elem_dofs: np.ndarray  # (M,3n) global DOFs of each element
    pattern_indptr: np.ndarray
    pattern_indices: np.ndarray
    pattern_keys: np.ndarray  # sorted row*n_dof+col of the pattern entries
    scatter: np.ndarray  # (M,(3n)²) into the pattern data
    scatter_ff: np.ndarray  # (M,(3n)²) into the free–free data, -1 if fixed
    ff_pos: np.ndarray  # (nnz,) full pattern position -> free–free position, -1 if fixed
    ff_indptr: np.ndarray
    ff_indices: np.ndarray
    boundary_faces: np.ndarray  # (B,3|6) outer + cavity surface triangles, normals out of the solid
    cavities: Mapping[str, np.ndarray] = field(default_factory=dict)  # name -> (K,3|6) triangles
    dN: np.ndarray = None  # (M,Q,n,3) 1/m
    wq: np.ndarray = None  # (M,Q) m³
    law_id: np.ndarray = None  # (M,) int64
    params: np.ndarray = None  # (M,4)
    laws: tuple = ()  # the distinct law objects, for the record
    N_q: np.ndarray = None  # (Q,n) shape functions at the quadrature points
    layout: ChannelLayout | None = None  # which cavities are read and loaded (None: a bare mesh)

    @property
    def order(self) -> int:
        return 1 if self.tets.shape[1] == 4 else 2

    @property
    def corners(self) -> np.ndarray:
        """(M,4) corner nodes of each tet."""
        return self.tets[:, :4]

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

    @property
    def all_corotational(self) -> bool:
        return bool(np.all(self.law_id == Corotational.law_id))

    def lumped_mass(self) -> np.ndarray:
        """(N,) kg, the consistent nodal masses ∫ρ N_a dV (row sums of the consistent mass matrix;
        they give the exact nodal loads of a uniform body force). Linear tets: ρV/4 per node;
        quadratic ones: −ρV/20 at corners and ρV/5 at mid-edges (straight elements)."""
        w = (self.density[:, None, None] * self.wq[:, :, None] * self.N_q[None]).sum(axis=1)
        return np.bincount(self.tets.reshape(-1), weights=w.reshape(-1), minlength=self.n_nodes)

    def residual_floor(self) -> float:
        """N, the round-off floor of a free-DOF force residual: polar decomposition and stress carry
        an absolute strain error ~ machine epsilon, i.e. nodal force errors ~ eps·(2μ+λ)·V·|∇N|.
        Below 16 times that (measured: ~4 eps) a smaller residual is noise."""
        unit = np.bincount(
            self.tets.reshape(-1),
            weights=np.einsum("m,mq,mqa->ma", 2 * self.mu + self.lam, self.wq,
                              np.linalg.norm(self.dN, axis=3)).reshape(-1),
            minlength=self.n_nodes,
        )
        return float(16 * np.finfo(float).eps * np.linalg.norm(np.repeat(unit, 3)[self.free_dofs]))


def _boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tet mesh, normals out of the solid; (B,6) for 10-node tets."""
    corner = tets[:, :4]
    faces = np.concatenate([corner[:, f] for f in elements.TET_FACES])
    key = np.sort(faces, axis=1)
    n = int(tets.max()) + 1
    if n < 2**20:  # one int64 per face: a 1-D unique, much faster than np.unique(axis=0)
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:
        _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    keep = counts[inv.reshape(-1)] == 1
    if tets.shape[1] == 10:
        faces = np.concatenate([tets[:, f] for f in elements.TET10_FACES])
    return faces[keep]


def _pattern(tets: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """CSR pattern of the (3n,3n) stiffness of ``tets`` and the scatter indices (M,(3k)²), k nodes
    per element.

    Built from the node adjacency (k² node pairs per element instead of 9k² DOF pairs: the pattern is
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
    k = tets.shape[1]
    s = pinv.reshape(m, k, k)
    d_row = deg[tets]  # (M,4), degree of the row node a
    scatter = (
        base[s][:, :, None, :, None]
        + 3 * p3[None, None, :, None, None] * d_row[:, :, None, None, None]
        + p3[None, None, None, None, :]
    )
    return indptr, prow, pcol, scatter.reshape(m, 9 * k * k)


def _per_tet_laws(materials, n_tets: int) -> list:
    if isinstance(materials, Law):
        mats = [materials]
    else:
        mats = list(materials)
        if len(mats) != n_tets:
            raise UserError(f"materials: expected one law or {n_tets} (one per tet), got {len(mats)}")
    for m in mats:
        if not isinstance(m, Law):
            raise UserError(f"materials: expected law objects ({', '.join(LAWS)}), got {type(m).__name__}")
        if type(m).law_id < 0:  # the kernels dispatch on the registry's ids
            raise UserError(f"materials: law {type(m).__name__} is not in softphantom.fem.laws.REGISTRY")
    return mats


def _geometry(nodes: np.ndarray, tets: np.ndarray, quad_degree: int | None):
    """(dN (M,Q,n,3), wq (M,Q), N_q (Q,n)) of the isoparametric map at the quadrature points."""
    order = elements.order_of(tets)
    xi, w = elements.tet_rule(quad_degree or order)
    N, dNr = elements.tet_shape(order, xi)  # (Q,n), (Q,n,3)
    Xe = nodes[tets]  # (M,n,3)
    J = np.einsum("mai,qaj->mqij", Xe, dNr)  # dX/dξ
    det = np.linalg.det(J)
    if np.any(~(det > 0)):
        bad = int(np.sum(np.any(~(det > 0), axis=1)))
        raise MeshError(f"{bad} tets with non-positive orientation (det J <= 0 at a quadrature point)")
    Jinv = np.linalg.inv(J)
    dN = np.einsum("qak,mqkj->mqaj", dNr, Jinv)
    return dN, det * w[None, :], N


def build_fem(
    nodes: np.ndarray,
    tets: np.ndarray,
    materials=DEFAULT_LAW,
    fixed_nodes: np.ndarray | Sequence[int] = (),
    *,
    fixed_dofs: np.ndarray | Sequence[int] = (),
    cavities: Mapping[str, np.ndarray] | None = None,
    quad_degree: int | None = None,
    layout: ChannelLayout | None = None,
) -> FemModel:
    """Precompute a :class:`FemModel` for linear (M,4) or quadratic (M,10) tetrahedra.

    ``materials``: one law object (:mod:`softphantom.fem.laws`: ``Corotational`` a.k.a.
    ``Material``, ``NeoHookean``, ``Yeoh``) or one per tet; default
    :data:`~softphantom.fem.material.DEFAULT_LAW`. ``fixed_nodes`` clamps all three
    components of those nodes; ``fixed_dofs`` clamps single DOFs (``3*node + component``), e.g. for
    symmetry planes. Tets must be positively oriented (det J > 0 at every quadrature point).
    Quadrature: 1 point for linear tets, 4 points (degree 2) for quadratic ones; ``quad_degree``
    overrides it (1 or 2). ``layout``: the channels among ``cavities`` (each must be one).

    >>> import numpy as np
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> fem = build_fem(X, np.array([[0, 1, 2, 3]]), fixed_nodes=[0])
    >>> fem.n_free, round(float(fem.volumes[0]), 6), fem.boundary_faces.shape, fem.order
    (9, 0.166667, (4, 3), 1)
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] not in (4, 10):
        raise MeshError(f"expected nodes (N,3) and tets (M,4) or (M,10), got {nodes.shape} and {tets.shape}")
    n, m = nodes.shape[0], tets.shape[0]
    if m == 0 or tets.min() < 0 or tets.max() >= n:
        raise MeshError("tets must be non-empty and index existing nodes")
    k = tets.shape[1]
    if layout is not None and (missing := [c for c in layout.channels if c not in (cavities or {})]):
        raise MeshError(f"channel {missing[0]!r} has no cavity wall (cavities: {', '.join(cavities or {}) or 'none'})")

    corner = tets[:, :4]
    Dm = np.swapaxes(nodes[corner[:, 1:]] - nodes[corner[:, [0]]], 1, 2)  # columns X_a - X_0
    det = np.linalg.det(Dm)
    if np.any(det <= 0):
        raise MeshError(f"{int(np.sum(det <= 0))} tets with non-positive orientation (det <= 0)")
    g123 = np.linalg.inv(Dm)  # row a-1 of Dm^{-1} is ∇L_a
    grads = np.concatenate([-g123.sum(axis=1, keepdims=True), g123], axis=1)
    if k == 4 and quad_degree in (None, 1):
        dN, wq, Nq = grads[:, None], (det / 6.0)[:, None], np.full((1, 4), 0.25)
    else:
        dN, wq, Nq = _geometry(nodes, tets, quad_degree)

    mats = _per_tet_laws(materials, m)
    distinct = list(dict.fromkeys(mats))
    idx = np.zeros(m, dtype=np.int64) if len(mats) == 1 else np.array([distinct.index(x) for x in mats])
    table = {
        "law": np.array([x.law_id for x in distinct], dtype=np.int64),
        "prm": np.array([x.params() for x in distinct]),
        "mu": np.array([x.mu_Pa for x in distinct]),
        "lam": np.array([x.lambda_Pa for x in distinct]),
        "rho": np.array([x.density_kg_m3 for x in distinct]),
    }

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

    edofs = (3 * tets[:, :, None] + np.arange(3)).reshape(m, 3 * k)
    indptr, prow, pcol, scatter = _pattern(tets, n)
    ukeys = prow * (3 * n) + pcol
    ff = is_free[prow] & is_free[pcol]
    take = np.flatnonzero(ff)
    frow = dof_map[prow[take]]
    ff_indptr = np.concatenate([[0], np.cumsum(np.bincount(frow, minlength=free.size))])
    # int32 indices where they fit: half the memory traffic of the scatter, and scipy keeps them
    # as they are (an int64 CSR index it would scan and copy down at every assembly)
    itype = np.int32 if max(ukeys.size, 3 * n) < 2**31 - 1 else np.int64
    ff_pos = np.full(ukeys.size, -1, dtype=itype)
    ff_pos[take] = np.arange(take.size)

    kernels.warm_up()  # numba: compile or load the kernels now, once per process
    return FemModel(
        nodes=_ro(nodes),
        tets=_ro(tets),
        grads=_ro(grads),
        volumes=_ro(det / 6.0),
        mu=_ro(table["mu"][idx]),
        lam=_ro(table["lam"][idx]),
        density=_ro(table["rho"][idx]),
        fixed_dofs=_ro(fixed),
        free_dofs=_ro(free),
        dof_map=_ro(dof_map),
        elem_dofs=_ro(edofs),
        pattern_indptr=_ro(indptr.astype(itype)),
        pattern_indices=_ro(pcol.astype(itype)),
        pattern_keys=_ro(ukeys),
        scatter=_ro(scatter.astype(itype)),
        scatter_ff=_ro(ff_pos[scatter]),
        ff_pos=_ro(ff_pos),
        ff_indptr=_ro(ff_indptr.astype(itype)),
        ff_indices=_ro(dof_map[pcol[take]].astype(itype)),
        boundary_faces=_ro(_boundary_faces(tets)),
        cavities={c: _ro(np.asarray(v, dtype=np.int64)) for c, v in (cavities or {}).items()},
        dN=_ro(dN),
        wq=_ro(wq),
        law_id=_ro(table["law"][idx]),
        params=_ro(table["prm"][idx]),
        laws=tuple(distinct),
        N_q=_ro(Nq),
        layout=layout,
    )


def fem_from_phantom(model, materials=None, *, order: int | None = None) -> FemModel:
    """Build the :class:`FemModel` of a ``PhantomModel`` (softphantom.design).

    ``materials``: ``None`` (default) takes each region's law from the design file
    (``[materials]`` / ``[region_materials]``, :func:`laws_of_design`); one law object for every
    region; or a dict region name -> law (regions not named keep the design's). ``order``: element
    order, 1 (linear tets) or 2 (10-node, needs a model meshed with ``element_order = 2``); default
    the model's own. Arm ends (``model.fixed_nodes``) are clamped; the cavities are carried over so
    :func:`solve_static` accepts pressures by cavity name, with the model's channel layout.
    """
    by_region = laws_of_design(model.design, model.regions)
    if materials is not None and isinstance(materials, Law):
        by_region = {k: materials for k in by_region}
    elif materials is not None:
        unknown = set(materials) - set(model.regions)
        if unknown:
            raise UserError(f"materials: unknown region(s) {sorted(unknown)}; have {sorted(model.regions)}")
        by_region.update(materials)
    by_id = {rid: by_region[name] for name, rid in model.regions.items()}
    mats = [by_id[int(r)] for r in np.asarray(model.tet_region)]
    nodes, tets, fixed, cav = mesh_arrays(model, order)
    return build_fem(nodes, tets, mats if len(set(mats)) > 1 else mats[0], fixed, cavities=dict(cav),
                     layout=model.layout)


def mesh_arrays(model, order: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(nodes (N,3) m, elements, fixed nodes, {cavity: wall faces}) of a ``PhantomModel`` for the
    element ``order`` (default the model's own): the stored arrays the FEM is built from, as stored
    (views, no arithmetic), so they are the same bits on every machine."""
    model_order = int(getattr(model, "element_order", 1))
    order = model_order if order is None else int(order)
    if order not in (1, 2):
        raise UserError(f"order must be 1 or 2, got {order}")
    if order == 2 and model_order != 2:
        raise UserError("order 2 needs a model meshed with [mesh] element_order = 2")
    if order == 2:
        return model.nodes, model.tets10, model.fixed_nodes, dict(model.cavities6)
    nc = int(getattr(model, "n_corner_nodes", len(model.nodes)))
    return model.nodes[:nc], model.tets, model.fixed_nodes[model.fixed_nodes < nc], dict(model.cavities)


def material_specs(design, regions: Mapping[str, int]) -> dict[str, tuple[str, tuple[tuple[str, float], ...]]]:
    """Region name -> (law name, its parameters by name as the design file gives them): the inputs
    :func:`laws_of_design` makes the law objects from (a region without a material: the default
    preset's)."""
    from softphantom.design.params import DEFAULT_MATERIAL, MATERIAL_PRESETS

    specs = {m.name: m for m in getattr(design, "materials", ())}
    assign = design.material_of_regions(regions) if hasattr(design, "material_of_regions") else {}
    out = {}
    for region in regions:
        mname = assign.get(region)
        spec = specs[mname] if mname is not None else MATERIAL_PRESETS[DEFAULT_MATERIAL]
        out[region] = (spec.law, tuple(sorted((str(k), float(v)) for k, v in dict(spec.values).items())))
    return out


def laws_of_design(design, regions: Mapping[str, int]) -> dict:
    """Region name -> law object from a design's ``materials`` and ``region_materials`` (validated
    here: an unknown law, a missing or non-physical parameter raise a one-line DesignError naming
    the material, the region and the field)."""
    from softphantom.fem.material import law_from_spec

    specs = {m.name: m for m in getattr(design, "materials", ())}
    assign = design.material_of_regions(regions) if hasattr(design, "material_of_regions") else {}
    out = {}
    cache: dict[str, object] = {}
    for region in regions:
        mname = assign.get(region)
        if mname is None:
            out[region] = DEFAULT_LAW
            continue
        if mname not in cache:
            spec = specs[mname]
            cache[mname] = law_from_spec(spec.law, dict(spec.values), f"materials.{mname} (region {region})")
        out[region] = cache[mname]
    return out
