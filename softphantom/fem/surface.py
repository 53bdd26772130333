"""Surface quantities on 3- and 6-node triangles: enclosed volume, its exact gradient, the follower
pressure load and its tangent (quadrature exact for the quadratic surface), and consistent nodal
loads of a traction spread on a circular contact patch.

A 6-node triangle is the quadratic surface x(s, t) = Σ N_a(s, t) x_a (corners, then mid-edge nodes
of (0,1), (1,2), (2,0)). With n = x_s × x_t (not normalized; |n| ds dt = dA):

- volume Φ = (1/3) ∫ x·n ds dt over a closed surface (divergence theorem); the integrand is of
  degree 4 on a quadratic triangle, so the 6-point degree-4 rule is exact;
- ∂Φ/∂x_a = (1/3) ∫ [N_a n + N_a,s (x_t × x) + N_a,t (x × x_s)] ds dt;
- unit-pressure load f_a = ∫ N_a n ds dt (a follower load), equal to ∂Φ/∂x_a on a closed surface
  (both exact, so equal to round-off: the pressure work is p dΦ); its tangent
  ∂f_a/∂x_b = ∫ N_a (N_b,t [x_s]× − N_b,s [x_t]×) ds dt.
"""

from __future__ import annotations

import numpy as np

from softphantom.fem.elements import tri_rule, tri_shape

_PTS, _W = tri_rule()
_N2, _dN2 = tri_shape(2, _PTS)  # (6,6), (6,6,2)


def _skew(v: np.ndarray) -> np.ndarray:
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def _quad_geometry(p: np.ndarray):
    """At the 6 quadrature points of each 6-node triangle (p: (K,6,3)): x, x_s, x_t (K,6,3)."""
    x = np.einsum("qa,kai->kqi", _N2, p)
    xs = np.einsum("qa,kai->kqi", _dN2[:, :, 0], p)
    xt = np.einsum("qa,kai->kqi", _dN2[:, :, 1], p)
    return x, xs, xt


def volume6(p: np.ndarray) -> float:
    """Φ of 6-node triangles p (K,6,3) (m³)."""
    x, xs, xt = _quad_geometry(p)
    return float(np.einsum("q,kqi,kqi->", _W, x, np.cross(xs, xt)) / 3.0)


def volume_gradient6(p: np.ndarray) -> np.ndarray:
    """(K,6,3) ∂Φ/∂x_a per triangle node."""
    x, xs, xt = _quad_geometry(p)
    n = np.cross(xs, xt)
    g = (np.einsum("q,qa,kqi->kai", _W, _N2, n)
         + np.einsum("q,qa,kqi->kai", _W, _dN2[:, :, 0], np.cross(xt, x))
         + np.einsum("q,qa,kqi->kai", _W, _dN2[:, :, 1], np.cross(x, xs)))
    return g / 3.0


def pressure_load6(p: np.ndarray) -> np.ndarray:
    """(K,6,3) N per Pa: f_a = ∫ N_a n ds dt."""
    _, xs, xt = _quad_geometry(p)
    return np.einsum("q,qa,kqi->kai", _W, _N2, np.cross(xs, xt))


def pressure_tangent6(p: np.ndarray) -> np.ndarray:
    """(K,6,6,3,3) ∂f_a/∂x_b [k, a, b, i, j]."""
    _, xs, xt = _quad_geometry(p)
    Ss, St = _skew(xs), _skew(xt)  # (K,Q,3,3)
    return (np.einsum("q,qa,qb,kqij->kabij", _W, _N2, _dN2[:, :, 1], Ss)
            - np.einsum("q,qa,qb,kqij->kabij", _W, _N2, _dN2[:, :, 0], St))
