"""The atlas's Chebyshev maths: Lobatto grids over a load range (optionally stretched about zero
load), tensor interpolation of grid values, and evaluation of the tensor polynomial.

A load ``x`` on its axis [lo, hi] maps to the Chebyshev variable t ∈ [−1, 1] by :func:`axis_t`
(affine, or affine in asinh(x / w) on a stretched axis); :func:`cheb_points` is its inverse at the
Chebyshev–Lobatto points. :func:`to_chebyshev` turns grid values into tensor coefficients,
:func:`tensor_value` / :func:`tensor_jacobian` evaluate them with ``numpy.polynomial.chebyshev``:
they are the references the compiled kernels (:mod:`~softphantom.estimation.atlas.kernels`, the
real-time path) are tested against.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.polynomial import chebyshev as C

from softphantom.estimation.atlas.kernels import axis_t

__all__ = ["axis_t", "axes_t", "cheb_basis", "cheb_points", "lobatto", "tensor_jacobian", "tensor_value",
           "to_chebyshev"]


def lobatto(n: int) -> np.ndarray:
    """``n`` Chebyshev–Lobatto points on [−1, 1], ascending (the middle one exactly 0).

    >>> lobatto(3).tolist()
    [-1.0, 0.0, 1.0]
    """
    t = C.chebpts2(n)
    t[np.abs(t) < 1e-15] = 0.0
    return t


def cheb_points(n: int, lo: float, hi: float, w: float = 0.0) -> np.ndarray:
    """``n`` Chebyshev–Lobatto points on [lo, hi], ascending; with a stretch width ``w`` > 0 the
    points are Chebyshev–Lobatto in asinh(x / w), so they cluster about x = 0 (:func:`axis_t`).

    >>> cheb_points(3, -1.0, 1.0).tolist()
    [-1.0, 0.0, 1.0]
    >>> cheb_points(9, -1.5, 1.5, 0.05).round(3).tolist()  # the default f_x axis (affine: ±0.574 … ±1.386)
    [-1.5, -1.098, -0.451, -0.115, 0.0, 0.115, 0.451, 1.098, 1.5]
    """
    t = lobatto(n)
    if w > 0:
        a0, a1 = math.asinh(lo / w), math.asinh(hi / w)
        x = w * np.sinh(0.5 * (a0 + a1) + 0.5 * (a1 - a0) * t)
        x[0], x[-1] = lo, hi
        x[np.abs(x) < 1e-12 * (hi - lo)] = 0.0
        return x
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * t


def cheb_basis(t: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(T_k(t), T_k'(t)) for k < n.

    >>> b, d = cheb_basis(0.5, 4)
    >>> np.round(b, 12).tolist(), np.round(d, 12).tolist()
    ([1.0, 0.5, -0.5, -1.0], [0.0, 1.0, 2.0, 0.0])
    """
    b = C.chebvander(float(t), n - 1)[0]
    d = np.zeros(n) if n < 2 else C.chebvander(float(t), n - 2)[0] @ C.chebder(np.eye(n))
    return b, d


def to_chebyshev(values: np.ndarray, shape: tuple[int, ...], t0: np.ndarray | None = None,
                 hermite: tuple[int, np.ndarray] | None = None) -> np.ndarray:
    """Tensor Chebyshev coefficients (shape + (m,)) of grid values (shape + (m,)) at
    Chebyshev–Lobatto points: one small Vandermonde solve per axis. ``t0`` (shape): the first
    axis's Chebyshev variable at each point, where the points of a line along it are not the
    Lobatto points (a displacement axis, ``atlas.build.NODE_TOL``): each such line is interpolated
    through its own points first, then the other axes as usual — the polynomial is still exact at
    every point.

    ``hermite`` (axis a, derivatives): the values' derivatives with respect to axis a's Chebyshev
    variable t at the same points (shape + (m,)); along a the n values and n derivatives of a line
    determine its polynomial of degree 2n − 1 (a confluent Vandermonde solve), so the coefficients
    are 2n long along a. Only a's derivatives are needed: the fit is Hermite along a times Lagrange
    along the others, which is exact for any polynomial of degree < 2n in t_a and < n_b in the
    others. With ``t0``: on the first axis each line through its own points; along another axis
    (a force first axis) ``t0`` must not vary along a.

    >>> to_chebyshev(np.array([[1.0], [0.0], [1.0]]), (3,))[:, 0].round(12).tolist()  # t² = (T_0 + T_2) / 2
    [0.5, 0.0, 0.5]
    >>> t = lobatto(2)  # t³ from its values and slopes at ±1 alone: (3 T_1 + T_3) / 4
    >>> (to_chebyshev((t ** 3)[:, None], (2,), hermite=(0, (3 * t ** 2)[:, None]))[:, 0].round(12) + 0.0).tolist()
    [0.0, 0.75, 0.0, 0.25]
    """
    n = shape[0]
    if t0 is None:
        t0 = np.broadcast_to(lobatto(n).reshape((n,) + (1,) * (len(shape) - 1)), shape)
    T = np.moveaxis(np.asarray(t0, float), 0, -1).reshape(-1, n)  # (lines, n)

    def lines(v):  # (lines, n, m): each line along the first axis
        return np.moveaxis(np.asarray(v, float), 0, len(shape) - 1).reshape(len(T), n, -1)

    def back(c, n_terms):
        return np.moveaxis(c.reshape(*shape[1:], n_terms, -1), len(shape) - 1, 0)

    a, d = hermite if hermite is not None else (None, None)
    if a == 0:  # each line's values and slopes at its own points: a confluent Vandermonde per line
        M = np.concatenate([C.chebvander(T, 2 * n - 1), C.chebvander(T, 2 * n - 2) @ C.chebder(np.eye(2 * n))], axis=1)
        c = back(np.linalg.solve(M, np.concatenate([lines(values), lines(d)], axis=1)), 2 * n)
        c = c.reshape((2 * n, *np.shape(values)[1:]))
    else:
        V0 = C.chebvander(T, n - 1)
        c = back(np.linalg.solve(V0, lines(values)), n).reshape(np.shape(values))
        if a is not None:  # the derivatives along another axis, fitted along this one alike
            d = back(np.linalg.solve(V0, lines(d)), n).reshape(np.shape(values))
            m = shape[a]
            M = np.vstack([C.chebvander(lobatto(m), 2 * m - 1),
                           C.chebvander(lobatto(m), 2 * m - 2) @ C.chebder(np.eye(2 * m))])
            c = np.moveaxis(np.tensordot(np.linalg.inv(M), np.concatenate([c, d], axis=a), axes=([1], [a])), 0, a)
    others = [b for b in range(1, len(shape)) if b != a]
    for ax in others:
        n = shape[ax]
        V = C.chebvander(lobatto(n), n - 1)  # V[j, k] = T_k(t_j)
        c = np.moveaxis(np.tensordot(np.linalg.inv(V), c, axes=([1], [ax])), 0, ax)
    return c


def axes_t(lam, lo, hi, w) -> tuple[np.ndarray, np.ndarray]:
    """(t, dt/dλ) per axis: the Chebyshev variable of each load (:func:`axis_t`)."""
    return np.array([axis_t(float(x), a, b, c) for x, a, b, c in zip(np.asarray(lam, float), lo, hi, w)]).T


def tensor_value(c: np.ndarray, t) -> np.ndarray:
    """The tensor polynomial with coefficients ``c`` (n1, …, n_d, *outputs) at the Chebyshev
    variables ``t`` (d,).

    >>> c = np.zeros((2, 3)); c[1, 2] = 1.0  # T_1(t_0) · T_2(t_1)
    >>> float(tensor_value(c, [0.5, 0.5]))
    -0.25
    """
    r = c
    for ti in t:
        r = C.chebval(float(ti), r)
    return r


def tensor_jacobian(c: np.ndarray, t, dt) -> np.ndarray:
    """(*outputs, d) the derivatives of :func:`tensor_value` per unit load, ``dt`` (d,) the axes'
    dt/dλ.

    >>> c = np.zeros((2, 3)); c[1, 2] = 1.0  # T_1(t_0) · T_2(t_1) = t_0 (2 t_1² − 1)
    >>> tensor_jacobian(c, [0.5, 0.5], [1.0, 2.0]).tolist()  # (2 t_1² − 1, 4 t_0 t_1 · 2)
    [-0.5, 2.0]
    """
    return np.stack([tensor_value(C.chebder(c, scl=g, axis=a), t) for a, g in enumerate(dt)], axis=-1)
