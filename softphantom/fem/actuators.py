"""Actuators (contact force, cavity pressure) and cavity-volume sensors on closed triangle surfaces
of 3-node (linear) or 6-node (quadratic, :mod:`softphantom.fem.surface`) triangles.

Cavity triangles follow docs/architecture.md: the normal (x2−x1)×(x3−x1) points out of the air
into the silicone, so Φ = Σ x1·(x2×x3)/6 > 0 is the air volume and a positive gauge pressure pushes
the wall into the silicone. For a closed surface the pressure load per unit pressure equals ∂Φ/∂x.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from softphantom.errors import UserError
from softphantom.fem import surface
from softphantom.fem.contact import ContactPatch
from softphantom.fem.model import FemModel


def _tri_xyz(x: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tri = np.asarray(triangles, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] not in (3, 6):
        raise UserError(f"triangles must be (K,3) or (K,6), got {tri.shape}")
    xyz = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    return tri, xyz[tri]


def _tri_dofs(tri: np.ndarray) -> np.ndarray:
    return (3 * tri[:, :, None] + np.arange(3)).reshape(len(tri), -1)


def cavity_volume(x: np.ndarray, triangles: np.ndarray) -> float:
    """Volume (m³) enclosed by a closed, consistently oriented triangle surface (divergence theorem).

    >>> import numpy as np
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> tri = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    >>> round(cavity_volume(X, tri), 12)
    0.166666666667
    """
    tri, p = _tri_xyz(x, triangles)
    if tri.shape[1] == 6:
        return surface.volume6(p)
    return float(np.einsum("ki,ki->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)


def cavity_volume_gradient(x: np.ndarray, triangles: np.ndarray, n_nodes: int) -> np.ndarray:
    """(3N,) exact ∂Φ/∂x: node 1 of a triangle gets (x2×x3)/6, and cyclically."""
    tri, p = _tri_xyz(x, triangles)
    if tri.shape[1] == 6:
        g = surface.volume_gradient6(p)
        return np.bincount(_tri_dofs(tri).reshape(-1), weights=g.reshape(-1), minlength=3 * n_nodes)
    g = np.stack(
        [np.cross(p[:, 1], p[:, 2]), np.cross(p[:, 2], p[:, 0]), np.cross(p[:, 0], p[:, 1])], axis=1
    ) / 6.0
    return np.bincount(_tri_dofs(tri).reshape(-1), weights=g.reshape(-1), minlength=3 * n_nodes)


def pressure_load(x: np.ndarray, triangles: np.ndarray, n_nodes: int) -> np.ndarray:
    """(3N,) nodal forces (N per Pa) of a unit pressure on ``triangles`` at positions ``x``.

    Each node of a triangle gets a third of its area-weighted normal, A·n/3 = (x2−x1)×(x3−x1)/6
    (exact for a uniform pressure on a linear triangle; a follower load: it moves with ``x``).
    Valid on open surfaces too; on a closed one it equals :func:`cavity_volume_gradient`.

    >>> import numpy as np
    >>> X = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0]], float)
    >>> pressure_load(X, np.array([[0, 1, 2]]), 3).reshape(3, 3)[:, 2].tolist()
    [1.0, 1.0, 1.0]
    """
    tri, p = _tri_xyz(x, triangles)
    if tri.shape[1] == 6:  # f_a = ∫ N_a n dA, exact on the quadratic triangle
        vals = surface.pressure_load6(p)
        return np.bincount(_tri_dofs(tri).reshape(-1), weights=vals.reshape(-1), minlength=3 * n_nodes)
    c = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) / 6.0
    vals = np.repeat(c[:, None, :], 3, axis=1)
    return np.bincount(_tri_dofs(tri).reshape(-1), weights=vals.reshape(-1), minlength=3 * n_nodes)


_skew = surface._skew


def pressure_tangent_blocks(x: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rows, cols, values (K·81 each) of d(pressure_load)/dx, triangle by triangle."""
    tri, p = _tri_xyz(x, triangles)
    dofs = _tri_dofs(tri)
    nd = dofs.shape[1]
    if tri.shape[1] == 6:
        blocks = surface.pressure_tangent6(p)  # [k, a, b, i, j]
        vals = np.moveaxis(blocks, 3, 2).reshape(len(tri), -1)  # [k, (a,i), (b,j)]
        rows = np.repeat(dofs, nd, axis=1)
        cols = np.tile(dofs, (1, nd))
        return rows.reshape(-1), cols.reshape(-1), vals.reshape(-1)
    # d[(x2−x1)×(x3−x1)]/dx1 = [x3−x2]×, /dx2 = [x1−x3]×, /dx3 = [x2−x1]×
    d = _skew(np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], axis=1)) / 6.0
    blocks = np.broadcast_to(d[:, None], (tri.shape[0], 3, 3, 3, 3))  # [k, a, b, i, j]
    vals = np.moveaxis(blocks, 3, 2).reshape(-1, 81)  # [k, (a,i), (b,j)]
    dofs = _tri_dofs(tri)
    rows = np.repeat(dofs, 9, axis=1)
    cols = np.tile(dofs, (1, 9))
    return rows.reshape(-1), cols.reshape(-1), vals.reshape(-1)


def pressure_load_tangent(x: np.ndarray, triangles: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """(3N,3N) d(pressure_load)/dx per unit pressure (sparse). On a closed surface it is the
    Hessian of Φ, hence symmetric: the pressure load is conservative."""
    r, c, v = pressure_tangent_blocks(x, triangles)
    n = 3 * n_nodes
    return sp.csr_matrix((v, (r, c)), shape=(n, n))


def _locate(fem: FemModel, xyz: np.ndarray, point: np.ndarray) -> tuple[int, np.ndarray]:
    # Barycentric coordinates of ``point`` in every tet: ξ = Dm⁻¹ (p − x0), with Dm⁻¹ = ∇N_1..3.
    xe = xyz[fem.corners]
    if np.allclose(xyz, fem.nodes):
        G = fem.grads
    else:
        Dm = np.swapaxes(xe[:, 1:] - xe[:, [0]], 1, 2)
        g = np.linalg.inv(Dm)
        G = np.concatenate([-g.sum(axis=1, keepdims=True), g], axis=1)
    bary = np.einsum("maj,mj->ma", G, point - xe[:, 0]) 
    bary[:, 0] += 1.0  # N_0 = 1 − ξ1 − ξ2 − ξ3
    e = int(np.argmax(bary.min(axis=1)))
    return e, bary[e]


def point_weights(fem: FemModel, point, x: np.ndarray | None = None, tol_m: float = 1e-3):
    """(nodes, weights) of the shape functions of the element containing ``point`` (m) at
    positions ``x`` (default rest): barycentric on linear tets; on quadratic ones the isoparametric
    coordinates (Newton on x(ξ) = point from the corner-tet guess) and the 10 shape functions, so a
    quadratic field is interpolated exactly. A point on the surface, or outside by at most
    ``tol_m``, goes to the nearest element (coordinates clipped into it)."""
    p = np.asarray(point, dtype=np.float64).reshape(3)
    xyz = (fem.nodes if x is None else np.asarray(x, dtype=np.float64)).reshape(-1, 3)
    e, bary = _locate(fem, xyz, p)
    if bary.min() < -1e-9:
        b = np.clip(bary, 0.0, None)
        b /= b.sum()
        dist = float(np.linalg.norm(b @ xyz[fem.corners[e]] - p))
        if dist > tol_m:
            raise UserError(
                f"point {np.round(p * 1e3, 3).tolist()} mm is {dist * 1e3:.3g} mm outside "
                f"the mesh (tolerance {tol_m * 1e3:.3g} mm)"
            )
        bary = b
    if fem.order == 1:
        return fem.tets[e], bary
    from softphantom.fem.elements import tet_shape

    xe = xyz[fem.tets[e]]
    xi = bary[1:].copy()
    inside = bary.min() >= -1e-9
    for _ in range(20):
        N, dN = tet_shape(2, xi[None])
        r = N[0] @ xe - p
        J = xe.T @ dN[0]  # dx/dξ
        step = np.linalg.solve(J, r)
        xi -= step
        if not inside:  # surface points: stay in the element
            xi = np.clip(xi, 0.0, None)
            if xi.sum() > 1.0:
                xi /= xi.sum()
        if np.abs(step).max() < 1e-14:
            break
    N, _ = tet_shape(2, xi[None])
    return fem.tets[e], N[0]


def force_actuator(
    fem: FemModel,
    point,
    radius: float = 0.0,
    *,
    x: np.ndarray | None = None,
    tol_m: float = 1e-3,
) -> sp.csr_matrix:
    """(3N,3) sparse H: ``H @ λ`` spreads a force λ (N, world axes) applied at ``point`` (m).

    ``radius > 0``: the one contact model, :class:`~softphantom.fem.contact.ContactPatch`
    (a uniform traction on the outer surface within ``radius`` of ``point``, consistent nodal
    loads; a point force is singular in 3-D, so local displacements only converge for a patch).
    ``radius == 0``: a point load on the nodes of the element that contains ``point`` with its
    shape-function weights (:func:`point_weights`; barycentric on linear tets). ``x`` (default
    rest) is the configuration in which the point is located. Column j applies 1 N along axis j.

    >>> import numpy as np
    >>> from softphantom.fem.model import build_fem
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> H = force_actuator(build_fem(X, np.array([[0, 1, 2, 3]])), [0.25, 0.25, 0.25])
    >>> H.shape, H.toarray()[0::3, 0].tolist()
    ((12, 3), [0.25, 0.25, 0.25, 0.25])
    """
    if radius > 0:
        return ContactPatch(tuple(np.asarray(point, dtype=np.float64).reshape(3)), float(radius)).load_matrix(fem, x)
    nodes, w = point_weights(fem, point, x, tol_m)
    rows = (3 * nodes[:, None] + np.arange(3)).reshape(-1)
    cols = np.tile(np.arange(3), nodes.size)
    return sp.csr_matrix((np.repeat(w, 3), (rows, cols)), shape=(fem.n_dof, 3))


def gravity_load(fem: FemModel, g=(0.0, 0.0, -9.81)) -> np.ndarray:
    """(3N,) N, the consistent nodal weights ∫ρ N_a dV g (linear tets: ρ V g / 4 per node;
    default g along −z, z up on the bench)."""
    return (fem.lumped_mass()[:, None] * np.asarray(g, dtype=np.float64)).reshape(-1)
