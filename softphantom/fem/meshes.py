"""Small structured tetrahedral meshes for verification (boxes/beams), built with numpy."""

from __future__ import annotations

import numpy as np

from softphantom.errors import UserError

# Kuhn subdivision of the unit cube into 6 tets along the main diagonal 0-7 (conforming across
# neighbouring cubes because every cube is split the same way). Corner c = i + 2j + 4k.
_KUHN = np.array(
    [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]
)


def box_mesh(size, divisions, origin=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N,3) and positively oriented tets (M,4) filling a box of ``size`` (m) split into
    ``divisions`` = (nx, ny, nz) cubes-by-6-tets.

    >>> X, T = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    >>> X.shape, T.shape
    ((8, 3), (6, 4))
    """
    nx, ny, nz = (int(d) for d in divisions)
    if min(nx, ny, nz) < 1:
        raise UserError(f"divisions must be >= 1, got {divisions}")
    ax = [np.linspace(0.0, float(s), n + 1) + float(o) for s, n, o in zip(size, (nx, ny, nz), origin)]
    X = np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1).reshape(-1, 3)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    base = (i * (ny + 1) + j) * (nz + 1) + k
    di, dj, dk = (ny + 1) * (nz + 1), nz + 1, 1
    corner = np.array([(c & 1) * di + ((c >> 1) & 1) * dj + ((c >> 2) & 1) * dk for c in range(8)])
    T = (base.reshape(-1, 1, 1) + corner[_KUHN][None]).reshape(-1, 4)
    d = np.linalg.det(np.swapaxes(X[T[:, 1:]] - X[T[:, [0]]], 1, 2))
    T[d < 0] = T[d < 0][:, [0, 2, 1, 3]]
    return X, T.astype(np.int64)


def quadratic_mesh(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Straight-sided 10-node tets from 4-node ones: a node at the midpoint of every edge (shared
    between neighbours), numbered after the corners; connectivity in
    :mod:`softphantom.fem.elements` order.

    >>> X, T = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    >>> X2, T2 = quadratic_mesh(X, T)
    >>> X2.shape, T2.shape  # 8 corners + 19 edges
    ((27, 3), (6, 10))
    """
    from softphantom.fem.elements import TET10_EDGES

    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    pairs = np.sort(tets[:, TET10_EDGES], axis=2).reshape(-1, 2)  # (6M,2)
    n = len(nodes)
    uniq, inv = np.unique(pairs[:, 0] * n + pairs[:, 1], return_inverse=True)
    a, b = np.divmod(uniq, n)
    mid = 0.5 * (nodes[a] + nodes[b])
    T10 = np.concatenate([tets, n + inv.reshape(-1, 6)], axis=1)
    return np.vstack([nodes, mid]), T10
