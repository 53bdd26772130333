"""Reference elements: linear (4-node) and quadratic (10-node) tetrahedra, 3- and 6-node
triangles; shape functions, their gradients and the quadrature rules the FEM uses.

Node order (VTK's, also meshio's): tet corners 0–3, then the mid-edge nodes of the edges
(0,1), (1,2), (2,0), (0,3), (1,3), (2,3); triangle corners 0–2, then edges (0,1), (1,2), (2,0).
(gmsh numbers the last two tet edges the other way round, (2,3) before (1,3); :data:`GMSH_TET10`
maps gmsh to this order.) Reference coordinates ξ = (ξ1, ξ2, ξ3) with barycentrics
L0 = 1 − ξ1 − ξ2 − ξ3, L1 = ξ1, L2 = ξ2, L3 = ξ3; corner shape functions L_i (2 L_i − 1), edge
ones 4 L_i L_j.

Quadrature (exactness stated and tested in tests/test_fem_p2.py):

- tet, 1 point (centroid): exact for degree 1 — the linear tet's stiffness (constant gradients).
- tet, 4 points (Keast; barycentrics (a, b, b, b) and permutations, a = (5 + 3√5)/20,
  b = (5 − √5)/20, weights 1/24): exact for degree 2 — the quadratic tet's linear-elastic stiffness
  (∇N of degree 1) and its consistent nodal loads ∫ρ g N_a on straight elements.
- triangle, 6 points (Strang–Fix/Dunavant degree 4): exact for degree 4, for cavity volumes and
  pressure loads on 6-node triangles (x·(∂x/∂s × ∂x/∂t) is of degree 2+1+1 = 4 on a quadratic
  surface, so the enclosed volume of a curved P2 surface is exact).
"""

from __future__ import annotations

import numpy as np

#: local corner pairs of the 6 mid-edge nodes 4..9 of a 10-node tet
TET10_EDGES = np.array([[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]])
#: gmsh's 10-node tet order -> ours: ``ours = gmsh_conn[:, GMSH_TET10]``
GMSH_TET10 = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])
#: faces of a tet opposite each vertex, corner order with the normal pointing away from it
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _edge_node(i: int, j: int) -> int:
    for k, (a, b) in enumerate(TET10_EDGES):
        if {a, b} == {i, j}:
            return 4 + k
    raise ValueError((i, j))


#: the 6-node faces of a 10-node tet: corners (a, b, c), then edges (a,b), (b,c), (c,a)
TET10_FACES = np.array(
    [[a, b, c, _edge_node(a, b), _edge_node(b, c), _edge_node(c, a)] for a, b, c in TET_FACES]
)

_A = (5.0 + 3.0 * np.sqrt(5.0)) / 20.0
_B = (5.0 - np.sqrt(5.0)) / 20.0


def tet_rule(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """(Q,3) points ξ and (Q,) weights on the reference tet (volume 1/6) exact for ``degree``
    (1: centroid, 2: 4-point Keast)."""
    if degree <= 1:
        return np.array([[0.25, 0.25, 0.25]]), np.array([1.0 / 6.0])
    if degree == 2:
        bary = np.full((4, 4), _B) + np.eye(4) * (_A - _B)
        return bary[:, 1:].copy(), np.full(4, 1.0 / 24.0)
    raise ValueError(f"no tet rule of degree {degree}")


def tri_rule() -> tuple[np.ndarray, np.ndarray]:
    """(6,2) points and (6,) weights on the reference triangle (area 1/2), exact for degree 4."""
    a1, a2 = 0.445948490915965, 0.091576213509771
    w1, w2 = 0.223381589678011, 0.109951743655322
    pts = np.array([[a1, a1], [1 - 2 * a1, a1], [a1, 1 - 2 * a1], [a2, a2], [1 - 2 * a2, a2], [a2, 1 - 2 * a2]])
    return pts, 0.5 * np.array([w1, w1, w1, w2, w2, w2])


def tet_shape(order: int, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions (Q,n) and reference gradients (Q,n,3) at points ``xi`` (Q,3).

    >>> N, dN = tet_shape(2, np.array([[0.2, 0.3, 0.1]]))
    >>> round(float(N.sum()), 12), float(abs(dN.sum(axis=1)).max()) < 1e-12
    (1.0, True)
    """
    xi = np.atleast_2d(np.asarray(xi, dtype=np.float64))
    L = np.column_stack([1.0 - xi.sum(axis=1), xi])  # (Q,4)
    dL = np.vstack([-np.ones(3), np.eye(3)])  # (4,3): dL_i/dξ
    if order == 1:
        return L, np.broadcast_to(dL, (len(xi), 4, 3)).copy()
    N = np.empty((len(xi), 10))
    dN = np.empty((len(xi), 10, 3))
    N[:, :4] = L * (2 * L - 1)
    dN[:, :4] = (4 * L - 1)[:, :, None] * dL[None]
    for k, (i, j) in enumerate(TET10_EDGES):
        N[:, 4 + k] = 4 * L[:, i] * L[:, j]
        dN[:, 4 + k] = 4 * (L[:, i, None] * dL[j] + L[:, j, None] * dL[i])
    return N, dN


def tri_shape(order: int, st: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle shape functions (Q,n) and reference gradients (Q,n,2) at points ``st`` (Q,2)."""
    st = np.atleast_2d(np.asarray(st, dtype=np.float64))
    L = np.column_stack([1.0 - st.sum(axis=1), st])
    dL = np.vstack([-np.ones(2), np.eye(2)])
    if order == 1:
        return L, np.broadcast_to(dL, (len(st), 3, 2)).copy()
    N = np.empty((len(st), 6))
    dN = np.empty((len(st), 6, 2))
    N[:, :3] = L * (2 * L - 1)
    dN[:, :3] = (4 * L - 1)[:, :, None] * dL[None]
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        N[:, 3 + k] = 4 * L[:, i] * L[:, j]
        dN[:, 3 + k] = 4 * (L[:, i, None] * dL[j] + L[:, j, None] * dL[i])
    return N, dN


def order_of(conn: np.ndarray) -> int:
    """Element order from the number of nodes per tet (4 or 10) or triangle (3 or 6)."""
    n = np.asarray(conn).shape[1]
    return {4: 1, 10: 2, 3: 1, 6: 2}[n]
