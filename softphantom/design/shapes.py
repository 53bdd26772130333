"""Parametric bodies as closed triangle surfaces, in mm: Barr's superellipsoid, optionally bent
into a bean (a kidney).

The superellipsoid with semi-axes (a, b, c) and exponents (e1, e2) is
``((|x/a|^(2/e2) + |y/b|^(2/e2))^(e2/e1) + |z/c|^(2/e1) = 1``: e1 shapes it north–south (along
z), e2 east–west (its cross-sections in x–y); (1, 1) is the ellipsoid, below 1 it tends to a box,
2 makes edges. It is the set of points (a·ρ·X, b·ρ·Y, c·ζ) with (ρ, ζ) on the unit
superellipse of exponent e1 (the meridian) and (X, Y) on that of e2 (the cross-section).

**Bend** (:func:`bend_points`): the body's longest axis L (the largest semi-axis, the first of
equal ones) is bent towards the next longest W by the shear ``w' = w + bend·(l / s_L)²``: the
centre line becomes a parabolic arc whose ends (l = ±s_L) lie ``bend`` from its middle, so the
body is concave on the +W side for bend > 0 (a kidney's hilum there). A shear has Jacobian 1:
the volume is the superellipsoid's, exactly.

:func:`body_surface` triangulates it: rings of constant latitude from pole to pole, each ring's
points spread along the cross-section by equal steps of a density that keeps the chord within
``tol_mm`` of the curve (the square root of the curvature) and the edges under ``max_edge_mm``;
rings shrink towards the poles with fewer points, neighbouring rings are zipped by their
parameter, and the poles close with fans. Closed, watertight, normals outward. The design keeps
only the parameters; the triangles are derived again when it is loaded.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from softphantom.design.geometry import superellipsoid_level

EXPONENT_RANGE = (0.3, 1.5)
"""Castable and meshable exponents: below 0.3 the edges round with radii under a millimetre on a
gland-sized body (needle-thin triangles, a mold that traps air); above 1.5 it grows ridges (2: edges)
that the smooth CAD body the mesher uses rounds off by a millimetre or more."""
TOL_MM = 0.02  # chord tolerance of the rings: a triangle's inside then lies within 0.05 mm of the shape
MAX_EDGE_MM = 4.0  # longest ring step on flat parts (the default mesh's surface size)
_DENSE = 4001  # samples of each quadrant curve for its density


def bend_axes(semi_axes) -> tuple[int, int]:
    """(L, W): the axis bent (the largest semi-axis, the first of equal ones) and the one it bends
    towards (the largest of the other two).

    >>> bend_axes((20.0, 55.0, 15.0))
    (1, 0)
    >>> bend_axes((30.0, 30.0, 30.0))
    (0, 1)
    """
    order = sorted(range(3), key=lambda i: (-semi_axes[i], i))
    return order[0], order[1]


def bend_points(points, semi_axes, bend_mm: float) -> np.ndarray:
    """The bean's shear ``w += bend·(l / s_L)²`` (:func:`bend_axes`); ``-bend_mm`` undoes it.

    >>> bend_points([[0.0, 55.0, 0.0], [0.0, 0.0, 0.0]], (20.0, 55.0, 15.0), 10.0).tolist()
    [[10.0, 55.0, 0.0], [0.0, 0.0, 0.0]]
    """
    p = np.array(np.atleast_2d(points), dtype=float)
    lo, w = bend_axes(semi_axes)
    p[:, w] += bend_mm * (p[:, lo] / semi_axes[lo]) ** 2
    return p


def unit_superellipse(t, e: float) -> np.ndarray:
    """Points (X, Y) of |X|^(2/e) + |Y|^(2/e) = 1 at polar angles ``t`` (the first quadrant)."""
    t = np.asarray(t, float)
    c, s = np.abs(np.cos(t)), np.abs(np.sin(t))
    r = (c ** (2.0 / e) + s ** (2.0 / e)) ** (-0.5 * e)
    return np.column_stack([r * np.cos(t), r * np.sin(t)])


def _density(curves: list[np.ndarray], tol_mm: float, max_edge_mm: float) -> np.ndarray:
    """Cumulative sampling measure along dense first-quadrant curves (same parameter): per segment
    the larger of length/max_edge and √(κ/(8·tol))·length (a chord of length h over curvature κ
    strays κh²/8), the largest over the curves."""
    g = np.zeros(len(curves[0]) - 1)
    for p in curves:
        seg = np.diff(p, axis=0)
        ds = np.linalg.norm(seg, axis=1)
        ang = np.arctan2(seg[:, 1], seg[:, 0])
        turn = np.abs(np.angle(np.exp(1j * np.diff(ang))))  # at the inner samples
        kappa = turn / (0.5 * (ds[1:] + ds[:-1]))
        k_seg = np.concatenate([[kappa[0]], 0.5 * (kappa[1:] + kappa[:-1]), [kappa[-1]]])
        g = np.maximum(g, np.maximum(ds / max_edge_mm, ds * np.sqrt(k_seg / (8.0 * tol_mm))))
    return np.concatenate([[0.0], np.cumsum(g)])


def _levels(t_dense: np.ndarray, cum: np.ndarray, n: int) -> np.ndarray:
    """``n + 1`` parameters from t_dense[0] to t_dense[-1] at equal steps of ``cum``."""
    t = np.interp(np.linspace(0.0, cum[-1], n + 1), cum, t_dense)
    t[0], t[-1] = t_dense[0], t_dense[-1]
    return t


def _ring(xy_quadrant: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed ring (counter-clockwise from +X) from the first quadrant's m + 1 points, by
    symmetry, and its parameters in [0, 1): quadrant q holds [q/4, (q+1)/4)."""
    m = len(xy_quadrant) - 1
    q = xy_quadrant
    s = np.arange(m) / m
    back = q[::-1][:-1]  # from (0, 1) back to (1, 0)
    pts = np.vstack([q[:-1], back * [-1.0, 1.0], q[:-1] * [-1.0, -1.0], back * [1.0, -1.0]])
    return pts, np.concatenate([s, 1.0 + s, 2.0 + s, 3.0 + s]) / 4.0


def _zip(a: np.ndarray, sa: np.ndarray, b: np.ndarray, sb: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles between ring ``a`` (below) and ring ``b`` (above), vertex indices, both
    counter-clockwise from parameter 0, outward; a ring of one vertex (a pole) gives a fan."""
    na, nb = len(a), len(b)
    ta, tb = np.append(sa, 1.0), np.append(sb, 1.0)
    out, i, j = [], 0, 0
    while i < na or j < nb:
        if j == nb or (i < na and ta[i + 1] <= tb[j + 1]):
            if na > 1:
                out.append((a[i], a[(i + 1) % na], b[j % nb]))
            i += 1
        else:
            if nb > 1:
                out.append((a[i % na], b[(j + 1) % nb], b[j]))
            j += 1
    return out


def _rings(semi_axes, exponents, tol_mm: float, max_edge_mm: float, full: bool = True):
    """The latitudes (ρ, ζ) from the equator to the north pole (ζ = 1) and the polar angles of the
    cross-section's first quadrant at the equator, each spaced by :func:`_density`."""
    a, b, c = (float(x) for x in semi_axes)
    e1, e2 = (float(x) for x in exponents)
    t = np.linspace(0.0, 0.5 * math.pi, _DENSE)
    mer, sec = unit_superellipse(t, e1), unit_superellipse(t, e2)
    cum_m = _density([mer * [a, c], mer * [b, c]], tol_mm, max_edge_mm)
    cum_s = _density([sec * [a, b]], tol_mm, max_edge_mm)
    lat = unit_superellipse(_levels(t, cum_m, max(2, math.ceil(cum_m[-1]))), e1)
    lat[-1] = (0.0, 1.0)
    return lat, t, cum_s


def _quadrant(t: np.ndarray, cum_s: np.ndarray, m: int, e2: float) -> np.ndarray:
    """m + 1 points of the unit cross-section's first quadrant, from (1, 0) to (0, 1)."""
    q = unit_superellipse(np.interp(np.linspace(0.0, 1.0, m + 1), cum_s / cum_s[-1], t), e2)
    q[0], q[-1] = (1.0, 0.0), (0.0, 1.0)
    return q


def superellipsoid_surface(semi_axes, exponents, tol_mm: float = TOL_MM,
                           max_edge_mm: float = MAX_EDGE_MM) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) mm, faces (M, 3)) of the superellipsoid, closed, normals outward.

    >>> v, f = superellipsoid_surface((30.0, 25.0, 20.0), (1.0, 1.0))
    >>> bool(abs(superellipsoid_level(v, (30.0, 25.0, 20.0), (1.0, 1.0)) - 1).max() < 1e-12)
    True
    """
    a, b, c = (float(x) for x in semi_axes)
    lat, t, cum_s = _rings(semi_axes, exponents, tol_mm, max_edge_mm)
    m_eq = max(2, math.ceil(cum_s[-1]))
    verts: list[np.ndarray] = []
    rings: list[tuple[np.ndarray, np.ndarray]] = []

    def add(points: np.ndarray, s: np.ndarray) -> None:
        start = sum(len(v) for v in verts)
        verts.append(points)
        rings.append((np.arange(start, start + len(points)), s))

    n_lat = len(lat) - 1
    add(np.array([[0.0, 0.0, -c]]), np.zeros(1))  # the south pole
    for k in range(-(n_lat - 1), n_lat):
        rho, zeta = lat[abs(k)]
        xy, s = _ring(_quadrant(t, cum_s, max(2, math.ceil(m_eq * math.sqrt(rho))), float(exponents[1])))
        add(np.column_stack([a * rho * xy[:, 0], b * rho * xy[:, 1], np.full(len(xy), math.copysign(c * zeta, k))]), s)
    add(np.array([[0.0, 0.0, c]]), np.zeros(1))  # the north pole
    faces = [f for (ia, sa), (ib, sb) in zip(rings[:-1], rings[1:]) for f in _zip(ia, sa, ib, sb)]
    return np.vstack(verts), np.asarray(faces, dtype=np.int64)


LOFT_TOL_MM = 0.1  # chord tolerance of the loft's sections: its splines then stray far less
LOFT_MAX_EDGE_MM = 6.0
CAP_MM = 2.0


def occ_body(occ, semi_axes, exponents, bend_mm: float = 0.0) -> int:
    """The (bent) superellipsoid as a smooth OpenCASCADE solid (gmsh ``occ`` API); returns its
    volume tag. A loft (``addThruSections``) through closed interpolating splines on rings of
    constant latitude, every ring through the same cross-section parameters, from the last ring
    before the south pole to the last before the north; each pole closed by a surface filling the
    end ring through the pole. Smooth, so gmsh meshes it at any size and puts quadratic nodes
    on it."""
    a, b, c = (float(x) for x in semi_axes)
    lat, t, cum_s = _rings(semi_axes, exponents, LOFT_TOL_MM, LOFT_MAX_EDGE_MM)
    xy, _ = _ring(_quadrant(t, cum_s, max(2, math.ceil(cum_s[-1])), float(exponents[1])))
    # a last ring CAP_MM across before each pole: the filling there strays a few µm, over a
    # wider ring (a flat pole) up to a millimetre
    rho_cap = CAP_MM / (2.0 * max(a, b))
    e1 = float(exponents[0])
    if lat[-2, 0] > 1.5 * rho_cap:
        zeta_cap = (1.0 - rho_cap ** (2.0 / e1)) ** (0.5 * e1)
        lat = np.vstack([lat[:-1], [(rho_cap, zeta_cap)], lat[-1:]])
    n_lat = len(lat) - 1
    wires = []
    for k in range(-(n_lat - 1), n_lat):
        rho, zeta = lat[abs(k)]
        ring = np.column_stack([a * rho * xy[:, 0], b * rho * xy[:, 1], np.full(len(xy), math.copysign(c * zeta, k))])
        if bend_mm:
            ring = bend_points(ring, semi_axes, bend_mm)
        tags = [occ.addPoint(*p) for p in ring]
        wires.append(occ.addWire([occ.addSpline([*tags, tags[0]])]))
    loft = occ.addThruSections(wires, makeSolid=False)
    occ.synchronize()
    import gmsh

    ends = [abs(e) for _, e in gmsh.model.getBoundary(loft, combined=True, oriented=False)]
    poles = bend_points([[0.0, 0.0, -c], [0.0, 0.0, c]], semi_axes, bend_mm)
    if len(ends) != 2:
        raise ValueError(f"the loft has {len(ends)} end curves, expected 2")
    caps = []
    for e in ends:
        pole = poles[int(np.argmin(np.linalg.norm(poles - np.array(occ.getCenterOfMass(1, e)), axis=1)))]
        caps.append(occ.addSurfaceFilling(occ.addWire([e]), pointTags=[occ.addPoint(*pole)]))
    return occ.addVolume([occ.addSurfaceLoop([t for _, t in loft] + caps, sewing=True)])


@lru_cache(maxsize=16)
def body_surface(semi_axes: tuple, exponents: tuple, bend_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The (bent) superellipsoid's triangles (:func:`superellipsoid_surface` then :func:`bend_points`),
    cached per parameters (read-only arrays)."""
    tol = TOL_MM
    if bend_mm:
        lo, _ = bend_axes(semi_axes)
        # the shear curves a chord along L by 2·bend/s_L² more: finer rings keep the tolerance
        tol = TOL_MM / (1.0 + 2.0 * abs(bend_mm) / semi_axes[lo] ** 2 * max(semi_axes))
    v, f = superellipsoid_surface(semi_axes, exponents, tol_mm=tol)
    if bend_mm:
        v = bend_points(v, semi_axes, bend_mm)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f
