"""Closed-form geometry of the BIP primitives (ellipsoid, superellipsoid, capsule, cylinder), in millimetres.

Used to validate a design before meshing (clearances, points on the surface) and to state the
design volumes the mesh is checked against. Pure numpy, no state.
"""

from __future__ import annotations

import math

import numpy as np

FloatArray = np.ndarray


def ellipsoid_volume(semi_axes: tuple[float, float, float]) -> float:
    """Volume of an ellipsoid, 4/3·π·a·b·c.

    >>> round(ellipsoid_volume((1.0, 1.0, 1.0)), 6)
    4.18879
    """
    a, b, c = semi_axes
    return 4.0 / 3.0 * math.pi * a * b * c


def superellipsoid_volume(semi_axes: tuple[float, float, float], exponents: tuple[float, float]) -> float:
    """Volume of Barr's superellipsoid ((|x/a|^(2/e2) + |y/b|^(2/e2))^(e2/e1) + |z/c|^(2/e1) = 1):
    V = 2·a·b·c·e1·e2·B(e1/2 + 1, e1)·B(e2/2, e2/2), B the beta function.

    >>> round(superellipsoid_volume((1.0, 1.0, 1.0), (1.0, 1.0)) / (4 / 3 * math.pi), 12)
    1.0
    >>> round(superellipsoid_volume((1.0, 1.0, 1.0), (1e-9, 1e-9)), 6)  # the box [-1, 1]³
    8.0
    """
    a, b, c = semi_axes
    e1, e2 = exponents
    return 2.0 * a * b * c * e1 * e2 * _beta(0.5 * e1 + 1.0, e1) * _beta(0.5 * e2, 0.5 * e2)


def _beta(x: float, y: float) -> float:
    return math.exp(math.lgamma(x) + math.lgamma(y) - math.lgamma(x + y))


def superellipsoid_level(points, semi_axes, exponents) -> FloatArray:
    """Barr's inside-outside function F: < 1 inside, 1 on the surface, > 1 outside; F(s·p) = s^(2/e1)·F(p),
    so ``p · F(p)^(-e1/2)`` is the surface point on the ray from the centre through p.

    >>> [round(float(f), 12) for f in superellipsoid_level([[2, 0, 0], [0, 0, 0.5]], (2.0, 1.0, 1.0), (0.5, 1.5))]
    [1.0, 0.0625]
    """
    p = np.abs(np.atleast_2d(np.asarray(points, dtype=float))) / np.asarray(semi_axes, dtype=float)
    e1, e2 = exponents
    xy = p[:, 0] ** (2.0 / e2) + p[:, 1] ** (2.0 / e2)
    return xy ** (e2 / e1) + p[:, 2] ** (2.0 / e1)


def capsule_volume(radius: float, cyl_length: float) -> float:
    """Volume of a capsule: cylinder of length ``cyl_length`` plus two hemispherical ends.

    >>> round(capsule_volume(1.0, 0.0), 6) == round(4 / 3 * math.pi, 6)
    True
    """
    return math.pi * radius**2 * cyl_length + 4.0 / 3.0 * math.pi * radius**3


def capsule_cyl_length(radius: float, volume: float) -> float:
    """Cylinder length of the capsule of ``radius`` that holds ``volume`` (negative: too small).

    >>> round(capsule_cyl_length(4.5, 2078.0), 3)
    26.664
    """
    return (volume - 4.0 / 3.0 * math.pi * radius**3) / (math.pi * radius**2)


def unit(v) -> FloatArray:
    """``v`` scaled to unit length (ValueError for a zero vector)."""
    v = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(v))
    if not n > 0.0:
        raise ValueError("zero vector")
    return v / n


def ellipsoid_level(points, semi_axes) -> FloatArray:
    """Σ (x_i/a_i)²: < 1 inside, 1 on the surface, > 1 outside."""
    p = np.atleast_2d(np.asarray(points, dtype=float))
    return np.sum((p / np.asarray(semi_axes, dtype=float)) ** 2, axis=1)


def ellipsoid_signed_distance(points, semi_axes) -> FloatArray:
    """Euclidean signed distance to the ellipsoid surface (negative inside).

    The closest point is x_i = a_i² p_i / (t + a_i²) with t the largest root of
    G(t) = Σ (a_i p_i / (t + a_i²))² − 1 (Eberly). G is convex and decreasing right of its pole
    −min a_i², so Newton's method started left of the root, where one term alone is 1, climbs to it
    without overshooting; in s = t + min a_i² (no cancellation near the pole). A coordinate on the
    smallest axis is nudged off zero so the root always exists (medial-axis points).

    >>> d = ellipsoid_signed_distance([[0, 0, 0], [0, 0, 5.0], [12.0, 0, 0]], (10.0, 8.0, 4.0))
    >>> [round(float(x), 4) for x in d]
    [-4.0, 1.0, 2.0]
    """
    p = np.atleast_2d(np.asarray(points, dtype=float))
    x = ellipsoid_closest_point(p, semi_axes)
    d = np.linalg.norm(p - x, axis=1)
    return np.where(ellipsoid_level(p, semi_axes) < 1.0, -d, d)


def ellipsoid_closest_point(points, semi_axes) -> FloatArray:
    """(n, 3) the point of the ellipsoid surface closest to each of ``points`` (Eberly, as in
    :func:`ellipsoid_signed_distance`).

    >>> ellipsoid_closest_point([[0, 0, 5.0], [-12.0, 0, 0]], (10.0, 8.0, 4.0)).round(6).tolist()
    [[0.0, 0.0, 4.0], [-10.0, 0.0, 0.0]]
    """
    e = np.asarray(semi_axes, dtype=float)
    q = np.atleast_2d(np.asarray(points, dtype=float))
    sign = np.where(q < 0.0, -1.0, 1.0)
    p = np.abs(q)
    p = np.where(p < 1e-9, 1e-9, p)
    e2 = e**2
    shift = e2 - e2.min()
    ep2 = (e * p) ** 2
    s = np.max(e * p - shift, axis=1)  # G >= 0 there: the term of that axis is 1
    for _ in range(100):  # about 6 steps, rarely more than 15
        den = s[:, None] + shift
        r = ep2 / (den * den)
        step = np.maximum((r.sum(axis=1) - 1.0) / (2.0 * (r / den).sum(axis=1)), 0.0)
        s = s + step
        if not (step > 1e-15 * s).any():
            break
    x = e2 * p / (s[:, None] + shift)
    x = np.where((np.abs(q) < 1e-9) & (x < 1e-6), 0.0, x)  # a zero coordinate stays zero (not the nudge)
    return sign * x


def ray_exit(origin, direction, semi_axes) -> float | None:
    """Largest s with origin + s·direction on the ellipsoid, or None when the line misses it.

    >>> ray_exit((0, 0, 0), (0, -1, 0), (32.0, 25.0, 30.0))
    25.0
    """
    o = np.asarray(origin, dtype=float) / np.asarray(semi_axes, dtype=float)
    d = np.asarray(direction, dtype=float) / np.asarray(semi_axes, dtype=float)
    qa, qb, qc = d @ d, 2.0 * o @ d, o @ o - 1.0
    disc = qb * qb - 4.0 * qa * qc
    if disc <= 0.0:
        return None
    return float((-qb + math.sqrt(disc)) / (2.0 * qa))


def project_to_ellipsoid(point, semi_axes) -> FloatArray:
    """Radial projection (from the centre) of ``point`` onto the ellipsoid surface."""
    p = np.asarray(point, dtype=float)
    return p / math.sqrt(float(ellipsoid_level(p, semi_axes)[0]))


def orthonormal_frame(axis) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(u, v, w) right-handed with w = unit(axis); deterministic choice of u."""
    w = unit(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = unit(np.cross(helper, w))
    v = np.cross(w, u)
    return u, v, w


def segment_distance(points, a, b) -> FloatArray:
    """Distance of each point to the segment [a, b]."""
    p = np.atleast_2d(np.asarray(points, dtype=float))
    a = np.asarray(a, dtype=float)
    ab = np.asarray(b, dtype=float) - a
    L2 = float(ab @ ab)
    s = np.zeros(len(p)) if L2 == 0.0 else np.clip((p - a) @ ab / L2, 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * ab), axis=1)


def segment_segment_distance(a0, a1, b0, b1, samples: int = 401) -> float:
    """Distance between two segments (dense sampling of the first; exact enough for clearances)."""
    s = np.linspace(0.0, 1.0, samples)[:, None]
    pts = np.asarray(a0, float) + s * (np.asarray(a1, float) - np.asarray(a0, float))
    return float(segment_distance(pts, b0, b1).min())


def capsule_surface_points(a, b, radius: float, spacing: float = 0.4) -> FloatArray:
    """Points on the surface of the capsule with axis [a, b] and ``radius`` (about ``spacing`` apart)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    u, v, w = orthonormal_frame(b - a if np.linalg.norm(b - a) > 0 else (0, 0, 1))
    L = float(np.linalg.norm(b - a))
    n_ang = max(16, int(math.ceil(2 * math.pi * radius / spacing)))
    ang = np.linspace(0.0, 2 * math.pi, n_ang, endpoint=False)
    ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v
    n_len = max(2, int(math.ceil(L / spacing)) + 1)
    s = np.linspace(0.0, L, n_len)
    cyl = (a + s[:, None, None] * w + radius * ring[None, :, :]).reshape(-1, 3)
    n_pol = max(4, int(math.ceil(0.5 * math.pi * radius / spacing)))
    pol = np.linspace(0.0, 0.5 * math.pi, n_pol + 1)[1:]
    caps = []
    for centre, sign in ((b, 1.0), (a, -1.0)):
        for th in pol:
            caps.append(centre + radius * (math.cos(th) * ring + sign * math.sin(th) * w))
    return np.vstack([cyl, *caps])


def ellipsoid_surface_points(centre, semi_axes, n: int = 1200) -> FloatArray:
    """``n`` points on an axis-aligned ellipsoid's surface (a Fibonacci sphere, scaled)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    unit_pts = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return np.asarray(centre, float) + unit_pts * np.asarray(semi_axes, float)


def disk_rim_points(centre, axis, radius: float, n: int = 64) -> FloatArray:
    """Points on the rim circle of a disk."""
    u, v, _ = orthonormal_frame(axis)
    ang = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    return np.asarray(centre, float) + radius * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v)


def min_dihedral_angles_deg(nodes, tets) -> FloatArray:
    """Smallest of the six dihedral angles of each tetrahedron, in degrees."""
    x = np.asarray(nodes, dtype=float)[np.asarray(tets)]
    normals = []
    for i in range(4):
        j, k, m = (q for q in range(4) if q != i)
        n = np.cross(x[:, k] - x[:, j], x[:, m] - x[:, j])
        # outward: away from the opposite vertex i
        flip = np.einsum("ij,ij->i", n, x[:, i] - x[:, j]) > 0.0
        n = np.where(flip[:, None], -n, n)
        normals.append(n / np.linalg.norm(n, axis=1)[:, None])
    out = np.full(len(x), 180.0)
    for i in range(4):
        for j in range(i + 1, 4):
            c = np.clip(-np.sum(normals[i] * normals[j], axis=1), -1.0, 1.0)
            out = np.minimum(out, np.degrees(np.arccos(c)))
    return out


def tet_signed_volumes(nodes, tets) -> FloatArray:
    """Signed volume of each tetrahedron (positive for the positive orientation)."""
    x = np.asarray(nodes, dtype=float)[np.asarray(tets)]
    return np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6.0


def surface_enclosed_volume(nodes, tris) -> float:
    """Φ = Σ x1·(x2×x3)/6 over the triangles (divergence theorem; > 0 for outward normals)."""
    x = np.asarray(nodes, dtype=float)[np.asarray(tris)]
    return float(np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0)
