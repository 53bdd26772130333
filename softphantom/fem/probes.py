"""Read-outs of a solution: points carried by the mesh (markers, targets), deformed volumes."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from softphantom.fem.actuators import point_weights
from softphantom.fem.model import FemModel


def probe_matrix(fem: FemModel, points, tol_m: float = 1e-3) -> sp.csr_matrix:
    """(k, N) sparse P such that ``P @ x.reshape(N, 3)`` are the current positions of ``points``
    (m, given at rest): shape-function interpolation in the element that contains each point
    (barycentric for linear tets, the 10 quadratic shape functions for quadratic ones; nearest
    element for points on the surface or within ``tol_m`` outside).

    >>> import numpy as np
    >>> from softphantom.fem.model import build_fem
    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> P = probe_matrix(build_fem(X, np.array([[0, 1, 2, 3]])), [[0.2, 0.3, 0.1]])
    >>> (P @ (2 * X)).round(12).tolist()
    [[0.4, 0.6, 0.2]]
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return sp.csr_matrix((0, fem.n_nodes))
    rows, cols, vals = [], [], []
    for i, p in enumerate(pts):
        nodes, w = point_weights(fem, p, tol_m=tol_m)
        rows.append(np.full(nodes.size, i))
        cols.append(nodes)
        vals.append(w)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(len(pts), fem.n_nodes))


def tet_volumes(fem: FemModel, x: np.ndarray) -> np.ndarray:
    """(M,) m³, signed volumes of the (straight corner) tets at positions ``x``."""
    xe = np.asarray(x, dtype=np.float64).reshape(-1, 3)[fem.corners]
    return np.linalg.det(np.swapaxes(xe[:, 1:] - xe[:, [0]], 1, 2)) / 6.0
