"""An independent reference for softphantom's FEM: FElupe (quadratic tetrahedra, compressible
neo-Hookean) with the loads of DESIGN.md §5 written here from scratch.

Nothing of ``softphantom.fem`` is used: the solid (element, quadrature, law, assembly) is FElupe's;
the follower pressure and the cavity volumes are integrated here on the 6-node boundary
triangles, the contact patch is a uniform dead traction on the outer surface within a radius, and
the Newton loop is ~20 lines. Only the geometry comes from ``softphantom.design`` (the same gmsh
OpenCASCADE construction, meshed here with ``Mesh.ElementOrder`` 2 so the mid-edge nodes sit on
the curved surfaces).

FElupe's law (its ``NeoHookeCompressible``): ψ = μ/2 (tr C − 3) − μ ln J + λ/2 ln² J.

Used by ``tests/test_fem_reference.py`` (a small case, in CI) and
``benchmarks/bench_reference.py`` (the full-size default design against DESIGN.md's table).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

# CHOLMOD's OpenBLAS: one thread (its pool fights numpy's on two cores: 5.8 s instead of 1.3 s a
# factorization measured here); set before sksparse loads it, a user's own setting wins
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# gmsh's 10-node tet lists the last two mid-edge nodes as (2,3), (1,3); FElupe/VTK as (1,3), (2,3)
GMSH_TO_VTK_TET10 = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])

# Symmetric 7-point rule on the reference triangle, exact to degree 5 (Dunavant / Radon):
# the volume and pressure integrands on a 6-node triangle are of degree 4.
_A1, _B1 = 0.059715871789770, 0.470142064105115
_A2, _B2 = 0.797426985353087, 0.101286507323456
TRI_POINTS = np.array(
    [[1 / 3, 1 / 3], [_B1, _B1], [_A1, _B1], [_B1, _A1], [_B2, _B2], [_A2, _B2], [_B2, _A2]]
)
TRI_WEIGHTS = 0.5 * np.array(
    [0.225, *[0.132394152788506] * 3, *[0.125939180544827] * 3]
)


def tri6_shape(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions (Q,6) and their derivatives (Q,6,2) of the 6-node triangle at ``xi`` (Q,2);
    nodes 0-2 corners, 3 = (0,1), 4 = (1,2), 5 = (2,0) (gmsh and VTK agree here)."""
    r, s = xi[:, 0], xi[:, 1]
    t = 1.0 - r - s
    N = np.stack([t * (2 * t - 1), r * (2 * r - 1), s * (2 * s - 1), 4 * t * r, 4 * r * s, 4 * s * t], 1)
    dr = np.stack([-(4 * t - 1), 4 * r - 1, 0 * r, 4 * (t - r), 4 * s, -4 * s], 1)
    ds = np.stack([-(4 * t - 1), 0 * r, 4 * s - 1, -4 * r, 4 * r, 4 * (t - s)], 1)
    return N, np.stack([dr, ds], 2)


def tri3_shape(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear triangle: shape functions (Q,3) and derivatives (Q,3,2) at ``xi`` (Q,2)."""
    r, s = xi[:, 0], xi[:, 1]
    N = np.stack([1.0 - r - s, r, s], 1)
    d = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    return N, np.broadcast_to(d, (len(xi), 3, 2)).copy()


def tri_shape(nper: int, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions of the 3- or 6-node triangle."""
    return tri3_shape(xi) if nper == 3 else tri6_shape(xi)


def tet10_shape(bary: np.ndarray) -> np.ndarray:
    """(Q,10) quadratic tet shape functions at barycentric coordinates (Q,4), VTK node order."""
    t1, t2, t3, t4 = bary.T
    return np.stack(
        [t1 * (2 * t1 - 1), t2 * (2 * t2 - 1), t3 * (2 * t3 - 1), t4 * (2 * t4 - 1),
         4 * t1 * t2, 4 * t2 * t3, 4 * t3 * t1, 4 * t1 * t4, 4 * t2 * t4, 4 * t3 * t4], 1)


def _skew(v: np.ndarray) -> np.ndarray:
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def surface_terms(x: np.ndarray, tris: np.ndarray, n_nodes: int, tangent: bool = True):
    """Volume enclosed by the 3- or 6-node triangles ``tris`` at positions ``x`` (N,3) (normals out of
    the air: Φ = ⅓∮ x·n dA > 0), its gradient (= the follower load per unit pressure, ∫ N_a n dA)
    (3N,), and that gradient's derivative (3N,3N) sparse (the pressure stiffness per unit
    pressure), all by the degree-5 rule (exact for these degree-4 integrands)."""
    k = tris.shape[1]
    N6, DN6 = tri_shape(k, TRI_POINTS)
    xe = x[tris]  # (K,k,3)
    xr = np.einsum("qa,kai->kqi", DN6[:, :, 0], xe)
    xs = np.einsum("qa,kai->kqi", DN6[:, :, 1], xe)
    xq = np.einsum("qa,kai->kqi", N6, xe)
    nA = np.cross(xr, xs)  # (K,Q,3) area-weighted normal per unit reference area
    vol = float(np.einsum("q,kqi,kqi->", TRI_WEIGHTS, xq, nA) / 3.0)
    fa = np.einsum("q,qa,kqi->kai", TRI_WEIGHTS, N6, nA)  # ∫ N_a n dA
    dofs = (3 * tris[:, :, None] + np.arange(3)).reshape(len(tris), 3 * k)
    g = np.bincount(dofs.reshape(-1), weights=fa.reshape(-1), minlength=3 * n_nodes)
    if not tangent:
        return vol, g, None
    # d(x_r × x_s) = [x_r]× dx_s − [x_s]× dx_r, dx_r = Σ_b N_b,r dx_b
    Kq = (np.einsum("qb,kqij->kqbij", DN6[:, :, 1], _skew(xr))
          - np.einsum("qb,kqij->kqbij", DN6[:, :, 0], _skew(xs)))
    Ke = np.einsum("q,qa,kqbij->kaibj", TRI_WEIGHTS, N6, Kq).reshape(len(tris), 3 * k, 3 * k)
    rows = np.repeat(dofs, 3 * k, axis=1).reshape(-1)
    cols = np.tile(dofs, (1, 3 * k)).reshape(-1)
    K = sp.csr_matrix((Ke.reshape(-1), (rows, cols)), shape=(3 * n_nodes, 3 * n_nodes))
    return vol, g, K


def patch_load(x: np.ndarray, tris: np.ndarray, n_nodes: int, point, force, radius: float,
               subdivisions: int = 4) -> np.ndarray:
    """(3N,) nodal forces of ``force`` (N) spread as a uniform dead traction over the part of the
    surface ``tris`` (6-node) within ``radius`` (m) of ``point``: ∫ N_a t dA with t = F / A_patch,
    integrated on ``subdivisions``² sub-triangles per triangle (the patch's rim cuts triangles)."""
    n = subdivisions
    sub = []
    for i in range(n):
        for j in range(n - i):
            sub.append([[i, j], [i + 1, j], [i, j + 1]])
            if i + j < n - 1:
                sub.append([[i + 1, j], [i + 1, j + 1], [i, j + 1]])
    sub = np.asarray(sub, float) / n  # (S,3,2) corners in the parent's (r,s)
    pts = (sub[:, 0, None] + TRI_POINTS[None, :, 0, None] * (sub[:, 1, None] - sub[:, 0, None])
           + TRI_POINTS[None, :, 1, None] * (sub[:, 2, None] - sub[:, 0, None])).reshape(-1, 2)
    w = np.tile(TRI_WEIGHTS, len(sub)) / n**2
    N, dN = tri_shape(tris.shape[1], pts)
    xe = x[tris]
    xq = np.einsum("qa,kai->kqi", N, xe)
    dA = np.linalg.norm(np.cross(np.einsum("qa,kai->kqi", dN[:, :, 0], xe),
                                 np.einsum("qa,kai->kqi", dN[:, :, 1], xe)), axis=2) * w
    inside = np.linalg.norm(xq - np.asarray(point, float), axis=2) <= radius
    wa = dA * inside
    area = wa.sum()
    if area <= 0:
        raise ValueError(f"no surface within {radius} m of {point}")
    share = np.einsum("kq,qa->ka", wa, N) / area  # (K,6), sums to 1
    out = np.zeros((n_nodes, 3))
    np.add.at(out, tris.reshape(-1), share.reshape(-1, 1) * np.asarray(force, float))
    return out.reshape(-1)


@dataclass(frozen=True, eq=False)
class Tet10Mesh:
    """A quadratic tet mesh (SI): ``nodes`` (N,3), ``tets`` (M,10) VTK order, positive; named
    closed ``cavities`` of 6-node triangles (normals out of the air), ``outer`` surface triangles,
    ``fixed_nodes``, named ``points`` (markers, targets, p_ext) at rest."""

    nodes: np.ndarray
    tets: np.ndarray
    cavities: dict[str, np.ndarray]
    outer: np.ndarray
    fixed_nodes: np.ndarray
    points: dict[str, np.ndarray] = field(default_factory=dict)


def orient_tets(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap corners 1, 2 (and their mid-edge nodes) of negatively oriented 4- or 10-node tets."""
    c = nodes[tets[:, :4]]
    det = np.einsum("ki,ki->k", c[:, 1] - c[:, 0], np.cross(c[:, 2] - c[:, 0], c[:, 3] - c[:, 0]))
    out = tets.copy()
    neg = det < 0
    out[neg] = tets[neg][:, [0, 2, 1, 3, 6, 5, 4, 7, 9, 8][: tets.shape[1]]]
    return out


def orient_faces(nodes: np.ndarray, tets: np.ndarray, tris: np.ndarray, into_solid: bool) -> np.ndarray:
    """Orient 3- or 6-node triangles so the corner normal points into the tet that owns them
    (``into_solid``) or out of it."""
    opp = {}
    for t in tets[:, :4]:
        for k in range(4):
            f = tuple(sorted(np.delete(t, k)))
            opp[f] = t[k]
    o = np.array([opp[tuple(sorted(f))] for f in tris[:, :3]])
    x = nodes[tris[:, :3]]
    towards = np.einsum("ki,ki->k", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), nodes[o] - x[:, 0]) > 0
    flip = towards != into_solid
    out = tris.copy()
    out[flip] = tris[flip][:, [0, 2, 1, 5, 4, 3][: tris.shape[1]]]
    return out


def locate(mesh: Tet10Mesh, point) -> tuple[int, np.ndarray]:
    """Element whose straight-sided corner tet contains ``point`` (or is nearest), and the clipped
    barycentric coordinates there."""
    p = np.asarray(point, float)
    c = mesh.nodes[mesh.tets[:, :4]]
    D = np.swapaxes(c[:, 1:] - c[:, [0]], 1, 2)
    lam = np.linalg.solve(D, (p - c[:, 0])[..., None])[..., 0]
    bary = np.concatenate([1 - lam.sum(1, keepdims=True), lam], 1)
    e = int(np.argmax(bary.min(1)))
    b = np.clip(bary[e], 0, None)
    return e, b / b.sum()


def probe(mesh: Tet10Mesh, points) -> sp.csr_matrix:
    """(k,N) interpolation of nodal fields at ``points`` with the quadratic shape functions."""
    rows, cols, vals = [], [], []
    for i, p in enumerate(np.atleast_2d(points)):
        e, b = locate(mesh, p)
        k = mesh.tets.shape[1]
        rows += [i] * k
        cols += list(mesh.tets[e])
        vals += list(tet10_shape(b[None])[0] if k == 10 else b)
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(np.atleast_2d(points)), len(mesh.nodes)))


@dataclass(frozen=True, eq=False)
class RefSolution:
    """``x`` (N,3) m, Newton ``iterations`` in all, final relative residual ``residual``."""

    x: np.ndarray
    iterations: int
    residual: float


class _Cholesky:
    """Sparse Cholesky of the symmetric part, the symbolic analysis kept across Newton steps
    (CHOLMOD; SuperLU of the full matrix where it is missing or the matrix is indefinite)."""

    def __init__(self) -> None:
        self.factor = None
        self.key = None

    def solve(self, K: sp.spmatrix, r: np.ndarray) -> np.ndarray:
        A = sp.csc_matrix(0.5 * (K + K.T))
        A.sort_indices()
        try:
            from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

            try:
                key = (A.indptr.tobytes(), A.indices.tobytes())
                if self.factor is None or key != self.key:
                    self.factor, self.key = analyze(A, mode="supernodal"), key
                self.factor.cholesky_inplace(A)
                return self.factor(r)
            except CholmodNotPositiveDefiniteError:
                pass
        except ImportError:
            pass
        return spla.splu(sp.csc_matrix(K)).solve(r)


def solve_felupe(mesh: Tet10Mesh, mu: float, lam: float, *, force=None, at=None,
                 patch_radius: float = 4e-3, load: np.ndarray | None = None,
                 pressures: dict[str, float] | None = None,
                 steps: int = 3, tol: float = 1e-10, max_iter: int = 30) -> RefSolution:
    """Equilibrium of FElupe's compressible neo-Hookean P2 solid under a patch ``force`` (N) at
    ``at`` (m), nodal dead loads ``load`` ((3N,) N) and follower cavity ``pressures`` (Pa), ``fixed_nodes`` clamped; ``steps`` equal
    load increments, full Newton to ‖r‖ ≤ ``tol``·‖f_ext‖ each (with backtracking on the residual
    norm; the quadratic convergence of the exact tangent makes 1e-10 cheap)."""
    import felupe

    if mesh.tets.shape[1] == 10:
        region = felupe.RegionQuadraticTetra(felupe.Mesh(mesh.nodes, mesh.tets, "tetra10"))
    else:
        region = felupe.RegionTetra(felupe.Mesh(mesh.nodes, mesh.tets, "tetra"))
    fld = felupe.FieldContainer([felupe.Field(region, dim=3)])
    solid = felupe.SolidBody(felupe.NeoHookeCompressible(mu=mu, lmbda=lam), fld)
    n = len(mesh.nodes)
    fixed = np.zeros(3 * n, bool)
    fixed[(3 * mesh.fixed_nodes[:, None] + np.arange(3)).reshape(-1)] = True
    free = ~fixed
    f_patch = np.zeros(3 * n)
    if force is not None and np.any(force):
        f_patch = patch_load(mesh.nodes, mesh.outer, n, at, force, patch_radius)
    if load is not None:
        f_patch = f_patch + np.asarray(load, float).reshape(-1)
    pressures = pressures or {}
    u = np.zeros(3 * n)
    its, rel = 0, 0.0
    chol = _Cholesky()

    def residual(u, t):
        fld[0].values[:] = u.reshape(-1, 3)
        r = np.asarray(solid.assemble.vector(fld).todense()).reshape(-1) - t * f_patch
        x = mesh.nodes + u.reshape(-1, 3)
        ref = np.linalg.norm(f_patch) * t
        Kp = []
        for name, p in pressures.items():
            _, g, K = surface_terms(x, mesh.cavities[name], n)
            r -= t * p * g
            ref = max(ref, np.linalg.norm(t * p * g))
            Kp.append(t * p * K)
        return r, max(ref, 1e-300), Kp

    for k in range(1, steps + 1):
        t = k / steps
        r, ref, Kp = residual(u, t)
        for it in range(max_iter + 1):
            rn = np.linalg.norm(r[free])
            if rn <= tol * ref:
                break
            if it == max_iter:
                raise RuntimeError(f"reference Newton: no convergence at load {t:.3g} (|r|/ref {rn / ref:.2e})")
            K = solid.assemble.matrix(fld).tocsr()
            for Kpi in Kp:
                K = K - Kpi
            Kff = K[free][:, free]
            d = np.zeros(3 * n)
            d[free] = chol.solve(Kff, -r[free])
            alpha = 1.0
            while True:
                try:
                    rt, reft, Kpt = residual(u + alpha * d, t)
                    ok = np.all(np.isfinite(rt)) and np.linalg.norm(rt[free]) < rn
                except Exception:
                    ok = False
                if ok or alpha < 1e-3:
                    break
                alpha *= 0.5
            u = u + alpha * d
            r, ref, Kp = rt, reft, Kpt
            its += 1
        rel = float(np.linalg.norm(r[free]) / ref)
    return RefSolution(mesh.nodes + u.reshape(-1, 3), its, rel)


def corner_mesh(mesh: Tet10Mesh) -> Tet10Mesh:
    """The linear (4-node) mesh of the corners of a quadratic one: same elements, straight."""
    used = np.unique(mesh.tets[:, :4])
    remap = np.full(len(mesh.nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    fixed = remap[mesh.fixed_nodes]
    return Tet10Mesh(mesh.nodes[used], remap[mesh.tets[:, :4]],
                     {k: remap[v[:, :3]] for k, v in mesh.cavities.items()}, remap[mesh.outer[:, :3]],
                     fixed[fixed >= 0], dict(mesh.points))


def cavity_volumes(mesh: Tet10Mesh, x: np.ndarray) -> dict[str, float]:
    """m³, volume of each cavity at positions ``x`` (N,3)."""
    return {k: surface_terms(x, t, len(x), tangent=False)[0] for k, t in mesh.cavities.items()}


@contextmanager
def _gmsh_model(name: str):
    """A fresh gmsh model (initializing gmsh if needed, quiet); removed (and gmsh finalized if
    initialized here) on exit."""
    import gmsh

    init_here = not gmsh.isInitialized()
    if init_here:
        gmsh.initialize(argv=["softphantom-ref"], readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(name)
        yield
    finally:
        try:
            gmsh.model.remove()
        except Exception:
            pass
        if init_here:
            gmsh.finalize()


def _gmsh_nodes() -> tuple[np.ndarray, np.ndarray]:
    """All nodes of the current gmsh model (m, from mm) and the tag -> row lookup."""
    import gmsh

    tags, coords, _ = gmsh.model.mesh.getNodes()
    pos = np.full(int(tags.max()) + 1, -1, np.int64)
    pos[tags.astype(np.int64)] = np.arange(len(tags))
    return np.asarray(coords).reshape(-1, 3) * 1e-3, pos


def _gmsh_elements(pos: np.ndarray, dim: int, entities, etype: int, nper: int) -> np.ndarray:
    """Elements of gmsh type ``etype`` (``nper`` nodes) on ``entities``, as node rows."""
    import gmsh

    out = [np.zeros((0, nper), np.int64)]
    for e in entities:
        types, _, nt = gmsh.model.mesh.getElements(dim, e)
        out += [np.asarray(v, np.int64).reshape(-1, nper) for t, v in zip(types, nt) if t == etype]
    return pos[np.vstack(out)]


# --- the default BIP design, meshed with quadratic tets ---------------------------------------

def bip_tet10(design, size_mm: float | None = None, optimize: bool = True, order: int = 2) -> Tet10Mesh:
    """The design's geometry meshed by gmsh exactly as ``softphantom.design`` does (same
    OpenCASCADE construction, sizes and physical groups), then (``order`` 2) elevated to order 2
    on the CAD (curved mid-edge nodes; ``optimize`` untangles any element the curving inverted).
    ``order`` 1 gives the linear mesh itself (the corners of the order-2 one)."""
    import dataclasses

    import gmsh

    from softphantom.design import mesh as dmesh

    if size_mm is not None:
        design = dataclasses.replace(design, mesh=design.mesh.scaled_to(size_mm))
    with dmesh._GMSH_LOCK, _gmsh_model("reference"):
        dmesh._build(design, design.mesh)
        if order == 2:
            gmsh.model.mesh.setOrder(2)
            if optimize:
                gmsh.model.mesh.optimize("HighOrder")
        tt, nt, tri, ntri = (11, 10, 9, 6) if order == 2 else (4, 4, 2, 3)
        X, pos = _gmsh_nodes()

        def group(dim, gid, etype, nper):
            return _gmsh_elements(pos, dim, gmsh.model.getEntitiesForPhysicalGroup(dim, gid), etype, nper)

        tets = np.vstack([group(3, rid, tt, nt) for rid in dmesh.REGION_IDS.values()])
        tets = tets[:, GMSH_TO_VTK_TET10] if order == 2 else tets
        cav = {k: group(2, gid, tri, ntri) for k, gid in dmesh.CAVITY_GROUP_IDS.items()}
        fixed = group(2, dmesh.FIXED_GROUP_ID, tri, ntri)
        outer = group(2, dmesh.OUTER_GROUP_ID, tri, ntri)
    points = {k: np.asarray(v) * 1e-3 for k, v in {**design.marker_dict, **design.target_dict,
                                                   **design.p_ext_mm()}.items()}
    return _compact(X, tets, cav, outer, fixed, points)


def _compact(X, tets, cavities, outer, fixed, points=None) -> Tet10Mesh:
    """Keep the nodes the tets use, renumbered; orient tets and faces (cavity normals out of the
    air, outer ones out of the solid)."""
    used = np.unique(tets)
    remap = np.full(len(X), -1, np.int64)
    remap[used] = np.arange(len(used))
    nodes = X[used]
    tets = orient_tets(nodes, remap[tets])
    cav = {k: orient_faces(nodes, tets, remap[v], into_solid=True) for k, v in cavities.items()}
    outer = orient_faces(nodes, tets, remap[outer], into_solid=False)
    return Tet10Mesh(nodes, tets, cav, outer, np.unique(remap[fixed]), points or {})


# --- a small BIP-like case for CI: a block clamped at one end, a cavity, a loaded end face --------

def block_with_cavity(size=(0.04, 0.02, 0.02), cavity_radius=0.005, h=0.005) -> tuple[Tet10Mesh, np.ndarray]:
    """A box ``size`` (m) with a spherical cavity at its centre, quadratic tets of size ``h``:
    clamped on x = 0; returns the mesh (cavity ``"cavity"``) and the 6-node triangles of the far
    face x = size[0] (normals out of the solid), for an end load. gmsh OpenCASCADE, one thread."""
    import gmsh

    with _gmsh_model("block"):
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        L, W, H = (s * 1e3 for s in size)
        occ = gmsh.model.occ
        box = occ.addBox(0, 0, 0, L, W, H)
        ball = occ.addSphere(L / 2, W / 2, H / 2, cavity_radius * 1e3)
        out, _ = occ.cut([(3, box)], [(3, ball)])
        occ.synchronize()
        vol = out[0][1]
        clamp, end, cav = [], [], []
        for _, s in gmsh.model.getBoundary([(3, vol)], oriented=False):
            c = occ.getCenterOfMass(2, abs(s))
            if abs(c[0]) < 1e-6:
                clamp.append(abs(s))
            elif abs(c[0] - L) < 1e-6:
                end.append(abs(s))
            elif gmsh.model.getType(2, abs(s)) == "Sphere":
                cav.append(abs(s))
        gmsh.option.setNumber("Mesh.MeshSizeMax", h * 1e3)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * h * 1e3)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        gmsh.model.mesh.optimize("HighOrder")
        X, pos = _gmsh_nodes()

        def elems(dim, ents, etype, nper):
            return _gmsh_elements(pos, dim, ents, etype, nper)

        tets = elems(3, [vol], 11, 10)[:, GMSH_TO_VTK_TET10]
        tri_clamp, tri_end, tri_cav = elems(2, clamp, 9, 6), elems(2, end, 9, 6), elems(2, cav, 9, 6)
    mesh = _compact(X, tets, {"cavity": tri_cav}, tri_end, tri_clamp)
    return mesh, mesh.outer
