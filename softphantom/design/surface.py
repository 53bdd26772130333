"""A bulb given as a closed triangle surface (an anatomy import) instead of an ellipsoid, in mm.

The same queries the ellipsoid answers in closed form (design/geometry.py): signed distance
(negative inside), the exit of a line, the outward normal, the volume. Built on trimesh (the
``fab`` extra) and cached per surface, because a design is validated each time it is made.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=8)
def surface_mesh(vertices: tuple, faces: tuple):
    """The trimesh of a (vertices, faces) pair given as nested tuples (cached)."""
    import trimesh

    return trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False)


def signed_distance(mesh, points, k: int = 16) -> np.ndarray:
    """Euclidean signed distance of ``points`` to the surface (negative inside).

    Exact distance to the ``k`` faces with the nearest centroids (a KD-tree; enough for a
    decimated, fairly even surface), sign from the closest face's normal — among faces at the
    same distance (an edge or vertex is closest), the one best aligned with the offset.
    """
    import trimesh

    p = np.atleast_2d(np.asarray(points, float))
    k = min(k, len(mesh.faces))
    tree = _centroid_tree(mesh)
    _, cand = tree.query(p, k=k)
    cand = cand.reshape(len(p), k)
    pp = np.repeat(p, k, axis=0)
    q = trimesh.triangles.closest_point(mesh.triangles[cand.ravel()], pp)
    off = pp - q
    d = np.linalg.norm(off, axis=1).reshape(len(p), k)
    n = mesh.face_normals[cand.ravel()]
    cos = (np.einsum("ij,ij->i", off, n) / np.maximum(np.linalg.norm(off, axis=1), 1e-300)).reshape(len(p), k)
    dmin = d.min(axis=1, keepdims=True)
    tied = d <= dmin + 1e-9 * (1.0 + dmin)
    best = np.argmax(np.where(tied, np.abs(cos), -1.0), axis=1)
    sign = np.sign(cos[np.arange(len(p)), best])
    sign[sign == 0.0] = 1.0
    return sign * dmin[:, 0]


def _centroid_tree(mesh):
    from scipy.spatial import cKDTree

    tree = getattr(mesh, "_softphantom_tree", None)
    if tree is None:
        tree = cKDTree(mesh.triangles_center)
        mesh._softphantom_tree = tree  # the mesh is cached per surface and never modified
    return tree


def ray_exit(mesh, origin, direction) -> float | None:
    """Largest s with origin + s·direction on the surface, or None when the line misses it."""
    o = np.asarray(origin, float)
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    span = float(np.ptp(mesh.vertices, axis=0).max()) * 4.0 + float(np.linalg.norm(o))
    start = o - span * d
    locs, _, _ = mesh.ray.intersects_location([start], [d], multiple_hits=True)
    if len(locs) == 0:
        return None
    return float(((locs - o) @ d).max())


def normal_at(mesh, point) -> np.ndarray:
    """Outward unit normal of the face closest to ``point``."""
    import trimesh

    _, _, tri = trimesh.proximity.closest_point(mesh, np.atleast_2d(np.asarray(point, float)))
    return np.asarray(mesh.face_normals[int(tri[0])], float)


def closest_point(mesh, points) -> np.ndarray:
    """(n, 3) the point of the surface closest to each of ``points``."""
    import trimesh

    q, _, _ = trimesh.proximity.closest_point(mesh, np.atleast_2d(np.asarray(points, float)))
    return np.asarray(q, float)
