"""benchmarks/bench_atlas_other_axes.py's error measure on polynomials of known degree (no FEM): n
Lagrange points reproduce degree n − 1 and n Hermite points degree 2n − 1, on the axes' ranges in
SI (the pressure's in Pa: the derivative's scaling to the Chebyshev variable matters), and one degree
more is missed."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("bench_atlas_other_axes", BENCH / "bench_atlas_other_axes.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCH))
    return mod


def _poly_scan(bench, coef, lo, hi, w):
    """A scan of two outputs, p(x) and 2 − p(x) with p the polynomial ``coef`` (in the axis's
    variable scaled to [−1, 1]), at a uniform scan plus every scheme's nodes, with exact derivatives."""
    p = np.polynomial.Polynomial(coef, domain=[lo, hi])
    dp = p.deriv()
    xs = {bench.key(x) for x in np.linspace(lo, hi, 17)}
    xs |= {bench.key(x) for _, n in bench.SCHEMES for x in bench.cheb_points(n, lo, hi, w)}
    return {x: (np.array([p(x), 2 - p(x)]), np.array([dp(x), -dp(x)])) for x in xs}


def _max_error(bench, scan, name, n, lo, hi, w):
    xs = np.array(sorted(scan))
    nodes = bench.cheb_points(n, lo, hi, w)
    vals = np.array([scan[bench.key(x)][0] for x in nodes])
    ders = np.array([scan[bench.key(x)][1] for x in nodes])
    pred = bench.interpolate(nodes, vals, ders, lo, hi, w, xs, name == "Hermite")
    return np.abs(pred - np.array([scan[x][0] for x in xs])).max()


@pytest.mark.parametrize("a", [2, 3])
def test_exact_to_the_schemes_degree_and_not_beyond(bench, a):
    lo, hi, w = bench.axis_range(a)
    assert lo < 0 < hi and w == 0.0
    rng = np.random.default_rng(7)
    for name, n in bench.SCHEMES:
        degree = 2 * n - 1 if name == "Hermite" else n - 1
        coef = rng.uniform(0.5, 1.5, degree + 2)
        exact = _poly_scan(bench, coef[:degree + 1], lo, hi, w)
        beyond = _poly_scan(bench, coef, lo, hi, w)
        # the scan's points are its keys, rounded to 1e-9 of the load's unit: a node is off by ≤ 5e-10
        assert _max_error(bench, exact, name, n, lo, hi, w) < 1e-7, (name, n)
        assert _max_error(bench, beyond, name, n, lo, hi, w) > 1e-3, (name, n)


def test_errors_measure_volumes_points_and_pose(bench):
    """``errors``: the largest volume difference, the largest point distance (not a coordinate's),
    and the yaw of the markers' fit: a marker set turned by 0.5° about z reads 0.5° of yaw."""
    rest = np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01], [0.02, 0.01, 0.0]])
    th = np.radians(0.5)
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    ref = np.r_[np.zeros(4), rest.ravel() * 1e3][None]
    pred = np.r_[[0.0, -0.3, 0.1, 0.0], (rest @ R.T).ravel() * 1e3][None]
    dv, dp, yaw, pr = bench.errors(pred, ref, rest[:4])
    assert dv == pytest.approx(0.3)
    assert dp == pytest.approx(np.linalg.norm(rest[4] @ R.T - rest[4]) * 1e3)
    assert abs(yaw) == pytest.approx(0.5, abs=1e-9) and pr == pytest.approx(0.0, abs=1e-9)
