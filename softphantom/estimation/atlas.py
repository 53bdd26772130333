"""An atlas of converged equilibria over the load envelope, and the estimator that inverts it.

Offline (:func:`build_atlas`, in parallel through :mod:`softphantom.parallel`): converged forward
solves (:class:`~softphantom.estimation.forward.ForwardModel`) on a tensor grid of Chebyshev–Lobatto
points over the envelope box ``f_i ∈ [f_min,i, f_max,i]`` (N), ``p_u ∈ [p_min, p_max]`` (Pa). Each output —
the 4 arm-cavity volume changes, the tracked points (markers, targets) and the coefficients of the
displacement field in its POD basis — becomes a tensor Chebyshev polynomial in the 4 loads, exact
at the grid points and spectrally accurate between them for this smooth map. Where a corner of the
box is unreachable for the model (a solve that does not converge), the build records it, does not
try the points beyond it, fills them by extrapolation from converged neighbours and marks the
cells around them as outside the envelope (:func:`build_atlas`). The first axis may instead be the
contact patch's work-conjugate x-displacement, mapped onto the f_x range (``AtlasConfig.x_control
= "displacement"``): where the arm pair steps, f_x barely moves while the state moves across, and
the map is smooth in the displacement where it is nearly a jump in f_x; f_x is then one more
output (:meth:`Atlas.forces`).

Online (:class:`AtlasEstimator`): per sample, a Gauss–Newton iteration in the 3 force components
(the urethra pressure is measured) on the polynomial volumes, each step the bounded QP of
:func:`~softphantom.estimation.qp.solve_volume_qp` with the polynomial's Jacobian; the points and
the full field come from the same polynomials at the solution. No refresh and no thread: the step
is compiled (:mod:`~softphantom.estimation.atlas_kernels`), tens of microseconds a sample. Outside the envelope the loads are clamped to it and the
estimate carries ``in_envelope=False`` (the CSV's ``in_envelope`` column); so does an estimate in a
cell the build could not solve.

Cache: :func:`load_or_build` keeps the atlas next to the model under the SHA-256 of everything it
depends on (mesh, law and its parameters, element, contact patch, envelope, grid, format version).
A file whose content hash does not match, of another format or built for another model is refused
with one line and never overwritten unless asked (``softphantom atlas build --rebuild``);
:mod:`~softphantom.estimation.atlas_store` verifies, describes and installs atlas files.
"""

from __future__ import annotations

import bisect
import hashlib
import io
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.estimation import atlas_kernels as ak
from softphantom.estimation.atlas_kernels import axis_t
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.estimator import (
    EstimatorState, check_sample, pose_and_shifts, repeat_last, rest_estimate, sensitivity_cond,
)
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.linearization import PatchControl
from softphantom.estimation.qp import solve_volume_qp
from softphantom.estimation.types import Estimate
from softphantom.pose import DegenerateMarkersError, Pose6, rigid_fit

FORMAT = 4  # bump when the file layout or the build changes its meaning (3: stretched axes; 4: x_control, cFx)
GN_MAX_ITER = 12
GN_TOL_N = 1e-7
FACE_TOL_N = 1e-9  # a Gauss–Newton that ends this close to a piece's shared f_y face goes on in the neighbour
FALLBACK_MIN_LOAD_STEP = 1.0 / 32
VIA_TOL = 1e-3  # relative residual of the continuation steps between grid points (they only start the next)
FIELD_MAX_MODES = 64
STRETCH_FX_N = 0.02  # the default f_x stretch width: the arm pair's step core at 3.5–5 N (docs/estimation.md)
STRETCH_MIN_POINTS = 9  # f_x points from which the default stretches f_x
STRETCH_Q = 0.3  # the default stretch of a displacement axis (N-equivalent; docs/estimation.md)
X_CONTROLS = ("displacement", "force")
OFFLINE = ("full", "rom")  # how the grid is solved: full solves, or a reduced model checked by full solves
# a displacement-controlled point is kept where it lands within this fraction of the distance to the
# next node along q (the fit takes each line's own nodes, _to_chebyshev): a new solve costs more
# than the slightly moved node
NODE_TOL = 0.1
UX_MAX_ITER = 30
BORDERED_HALVINGS = 2  # a mixed-control step that fails is split in two, and each half again
BORDERED_TOL = 1e-3  # a mixed-control solve hits the patch displacement this close (of NODE_TOL's): on the node
FIELD_RTOL = 1e-5  # POD truncation: dropped displacement energy below this fraction (≈ 3e-3 relative RMS)


@dataclass(frozen=True)
class AtlasConfig:
    """The envelope and the grid of the atlas.

    ``force_min_N`` / ``force_max_N`` (3,) the envelope box of the force components (the default
    covers the phantom's use with a margin: pushes mostly along +y, the needle axis, up to 5.2 N,
    ±2 N sideways — the paper's pushes and a lateral (1.5, 0.5, −1.0) N push, whose estimate runs
    ≈ 20 % above it on a stiffer model; a 6 N push with 1.4 N sideways does not converge on the
    default mesh, and corners the model cannot reach are flagged, :func:`build_atlas`);
    ``p_min_kPa`` / ``p_max_kPa`` the urethra pressure range; ``n_force`` (3,) / ``n_pressure``
    Chebyshev–Lobatto points per axis (their product is the number of forward solves);
    ``linear_pressure`` (only with ``n_pressure=2``): the two pressure planes from one plane of
    solves at the range's middle and the exact pressure derivative there (the tangent line: half the
    solves, and exact at the middle, where a push scenario's pressure stays; its error at the
    range's ends, the curvature term, is as large as the two-plane secant's at the middle);
    ``force_cluster_N`` (3,) per force axis the width (N) of a stretch that clusters the points
    about zero force (Chebyshev–Lobatto in asinh(f / w), :func:`cheb_points`; 0: none). The default
    (None) stretches f_x by :data:`STRETCH_FX_N` when it has at least :data:`STRETCH_MIN_POINTS`
    points and the envelope spans 0: above ≈ 3.5 N along f_y the default design's arms 2 and 3
    trade ≈ 20 mm³ of volume within ±0.1 N of f_x = 0 (one of the pair buckles, the sign of f_x
    picks which), a step no polynomial in f_x itself follows with a few points
    (docs/estimation.md). With fewer points the stretch costs more than it gains: the smooth part
    of the map is then a steep function of the stretched variable (3 points over ±1.5 N: a linear
    map is missed by 0.55 N at f_x = 0.18 N), so such grids stay affine.

    ``x_control``: what the first axis holds. ``"force"`` (the default): f_x itself.
    ``"displacement"``: the work-conjugate x-displacement of the contact patch, ū_x = H_xᵀu, mapped per
    (f_y, f_z, p_u) point affinely onto [f_x,min, f_x,max] so that its ends are the envelope's f_x
    faces; the axis variable ``q`` (N-equivalent) is f_x at the faces and f_x itself becomes an
    output (:meth:`Atlas.forces`). A stable equilibrium has ∂ū_x/∂f_x = H_xᵀK⁻¹H_x > 0, so ū_x is
    monotone in f_x, and where the arm pair steps (f_x moves a few hundredths of a newton while the
    state moves across) the displacement moves with the state: the outputs are smooth in q where
    they are steep in f_x (docs/estimation.md). The build solves the two faces first, then walks
    each line along q from face to face, each node's point one mixed-control solve (f_x an unknown
    fixed by ū_x: :class:`~softphantom.estimation.linearization.PatchControl`), force-controlled
    trials where that fails (:func:`_lines`, :func:`_solve_ux`, :data:`NODE_TOL`).
    The step is still the steepest part of the map in q, but far wider than in f_x: the default
    stretch of such an axis is :data:`STRETCH_Q` (N-equivalent); ``linear_pressure`` needs
    ``"force"`` (its tangent line is at fixed f_x).

    The default is resolved in :attr:`cluster_N`, not stored, so ``dataclasses.replace`` with
    another first axis or grid takes that one's default:

    >>> AtlasConfig().cluster_N, AtlasConfig(x_control="displacement").cluster_N
    ((0.02, 0.0, 0.0), (0.3, 0.0, 0.0))
    >>> from dataclasses import replace
    >>> replace(AtlasConfig(), n_force=(4, 5, 4)).cluster_N
    (0.0, 0.0, 0.0)
    >>> AtlasConfig(n_pressure=2, linear_pressure=True, x_control="displacement")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: atlas linear_pressure needs x_control 'force' (the tangent line is at fixed f_x), got 'displacement'
    >>> AtlasConfig(n_force=(5, 2, 5))
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: atlas n_force: each must be an integer in 3..15, got (5, 2, 5)
    """

    force_min_N: tuple[float, float, float] = (-2.0, -1.0, -2.0)
    force_max_N: tuple[float, float, float] = (2.0, 5.2, 2.0)
    p_min_kPa: float = -2.0
    p_max_kPa: float = 40.0
    n_force: tuple[int, int, int] = (11, 9, 4)
    n_pressure: int = 3
    linear_pressure: bool = False
    force_cluster_N: tuple[float, float, float] | None = None
    x_control: str = "force"
    f_y_splits_N: tuple[float, ...] = ()
    offline: str = "full"

    def __post_init__(self) -> None:
        if self.offline not in OFFLINE:
            raise UserError(f"atlas offline: one of {', '.join(OFFLINE)}, got {self.offline!r}")
        lo = tuple(float(v) for v in self.force_min_N)
        hi = tuple(float(v) for v in self.force_max_N)
        if len(lo) != 3 or len(hi) != 3 or not all(math.isfinite(a) and math.isfinite(b) and a < b
                                                   for a, b in zip(lo, hi)):
            raise UserError(f"atlas force envelope {lo}..{hi} N: need 3 finite ranges with min < max")
        object.__setattr__(self, "force_min_N", lo)
        object.__setattr__(self, "force_max_N", hi)
        # floats, so -2 and -2.0 give one cache key (atlas_key hashes the fields' JSON)
        object.__setattr__(self, "p_min_kPa", float(self.p_min_kPa))
        object.__setattr__(self, "p_max_kPa", float(self.p_max_kPa))
        if not (math.isfinite(self.p_min_kPa) and math.isfinite(self.p_max_kPa) and self.p_min_kPa < self.p_max_kPa):
            raise UserError(f"atlas pressure range [{self.p_min_kPa}, {self.p_max_kPa}] kPa is empty")
        n = tuple(self.n_force) if np.ndim(self.n_force) else (self.n_force,) * 3
        if len(n) != 3 or any(int(v) != v or not 3 <= v <= 15 for v in n):
            raise UserError(f"atlas n_force: each must be an integer in 3..15, got {self.n_force}")
        object.__setattr__(self, "n_force", tuple(int(v) for v in n))
        if int(self.n_pressure) != self.n_pressure or not 2 <= self.n_pressure <= 15:
            raise UserError(f"atlas n_pressure must be an integer in 2..15, got {self.n_pressure}")
        if self.linear_pressure and self.n_pressure != 2:
            raise UserError(f"atlas linear_pressure needs n_pressure 2, got {self.n_pressure}")
        if self.x_control not in X_CONTROLS:
            raise UserError(f"atlas x_control: one of {', '.join(X_CONTROLS)}, got {self.x_control!r}")
        if self.linear_pressure and self.offline != "full":
            raise UserError("atlas linear_pressure needs offline 'full' (its tangent line comes from the full solves)")
        if self.linear_pressure and self.x_control != "force":
            raise UserError("atlas linear_pressure needs x_control 'force' (the tangent line is at fixed f_x), "
                            f"got {self.x_control!r}")
        w = self.force_cluster_N
        if w is not None:
            w = tuple(float(v) for v in (w if np.ndim(w) else (w,) * 3))
            if len(w) != 3 or not all(math.isfinite(v) and v >= 0 for v in w):
                raise UserError(f"atlas force_cluster_N: 3 widths ≥ 0 N (0: no stretch), got {self.force_cluster_N}")
            object.__setattr__(self, "force_cluster_N", w)
        splits = tuple(float(v) for v in (self.f_y_splits_N if np.ndim(self.f_y_splits_N) else (self.f_y_splits_N,)))
        edges = (lo[1], *splits, hi[1])
        if not all(math.isfinite(v) for v in splits) or any(b <= a for a, b in zip(edges, edges[1:])):
            raise UserError(f"atlas f_y_splits_N: increasing values strictly inside the f_y range {lo[1]}..{hi[1]} N, "
                            f"got {self.f_y_splits_N}")
        object.__setattr__(self, "f_y_splits_N", splits)

    @property
    def cluster_N(self) -> tuple[float, float, float]:
        """The stretch widths per force axis: ``force_cluster_N``, or the default for this grid and
        first axis where it is None (the first axis stretched where there are enough points, above)."""
        if self.force_cluster_N is not None:
            return self.force_cluster_N
        stretch = self.n_force[0] >= STRETCH_MIN_POINTS and self.force_min_N[0] < 0 < self.force_max_N[0]
        return ((STRETCH_FX_N if self.x_control == "force" else STRETCH_Q) if stretch else 0.0, 0.0, 0.0)

    def as_dict(self) -> dict:
        """The fields with the stretch resolved: what the cache key hashes and an atlas file keeps,
        so a file's polynomial never meets another default's stretch."""
        d = asdict(self)
        d["force_cluster_N"] = self.cluster_N
        if not self.f_y_splits_N:
            del d["f_y_splits_N"]  # an atlas of one piece keeps the key it had before the field
        if self.offline == "full":
            del d["offline"]  # likewise an atlas of full solves
        return d

    def patches(self) -> tuple["AtlasConfig", ...]:
        """The configurations of the pieces along f_y (``f_y_splits_N``): each an ordinary atlas
        over its f_y range with this grid; ``(self,)`` without splits.

        >>> [c.force_max_N[1] for c in AtlasConfig(f_y_splits_N=(3.3,)).patches()]
        [3.3, 5.2]
        >>> AtlasConfig(f_y_splits_N=(6.0,))
        Traceback (most recent call last):
        ...
        softphantom.errors.UserError: atlas f_y_splits_N: increasing values strictly inside the f_y range -1.0..5.2 N, got (6.0,)
        """
        if not self.f_y_splits_N:
            return (self,)
        edges = (self.force_min_N[1], *self.f_y_splits_N, self.force_max_N[1])
        lo, hi = self.force_min_N, self.force_max_N
        return tuple(replace(self, force_min_N=(lo[0], a, lo[2]), force_max_N=(hi[0], b, hi[2]), f_y_splits_N=())
                     for a, b in zip(edges, edges[1:]))

    @property
    def lower(self) -> np.ndarray:
        return np.array([*self.force_min_N, self.p_min_kPa * 1e3])

    @property
    def upper(self) -> np.ndarray:
        return np.array([*self.force_max_N, self.p_max_kPa * 1e3])

    @property
    def stretch(self) -> np.ndarray:
        """(4,) the axes' stretch widths (N, N, N; the pressure axis 0: affine), :func:`axis_t`."""
        return np.array([*self.cluster_N, 0.0])

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return (*self.n_force, int(self.n_pressure))

    @property
    def n_solves(self) -> int:
        """Forward solves of the build (one pressure plane with ``linear_pressure``)."""
        return math.prod(self.n_force) * (1 if self.linear_pressure else int(self.n_pressure)) * (len(self.f_y_splits_N) + 1)

    def axes(self) -> list[np.ndarray]:
        """The grid's load values per axis (N, N, N, Pa), from the lower bound up."""
        return [cheb_points(n, lo, hi, w) for n, lo, hi, w in zip(self.shape, self.lower, self.upper, self.stretch)]


# The quadratic (10-node) BIP model's atlas: its back arm pair snaps through above f_y ≈ 4.3 N (a fold
# in f_x, followed by the displacement axis) and one f_y polynomial over -1..5.2 N rings below it;
# pieces split at these forces keep each f_y polynomial smooth (measured: docs/estimation.md).
P2_F_Y_SPLITS_N = (3.3,)
P2_N_FORCE = (11, 6, 4)


def default_atlas_config(order: int = 1) -> AtlasConfig:
    """The atlas a model of element ``order`` gets when none is asked for: the linear model's
    :class:`AtlasConfig` defaults; for the quadratic model the displacement axis, in pieces along
    f_y (:data:`P2_F_Y_SPLITS_N`), each :data:`P2_N_FORCE` × 3 points.

    >>> default_atlas_config(1) == AtlasConfig()
    True
    >>> c = default_atlas_config(2)
    >>> c.x_control, c.f_y_splits_N, c.shape
    ('displacement', (3.3,), (11, 6, 4, 3))
    """
    if int(order) == 2:
        return AtlasConfig(n_force=P2_N_FORCE, x_control="displacement", f_y_splits_N=P2_F_Y_SPLITS_N)
    return AtlasConfig()


def cheb_points(n: int, lo: float, hi: float, w: float = 0.0) -> np.ndarray:
    """``n`` Chebyshev–Lobatto points on [lo, hi], ascending; with a stretch width ``w`` > 0 the
    points are Chebyshev–Lobatto in asinh(x / w), so they cluster about x = 0 (:func:`axis_t`).

    >>> cheb_points(3, -1.0, 1.0).tolist()
    [-1.0, 0.0, 1.0]
    >>> cheb_points(9, -1.5, 1.5, 0.05).round(3).tolist()  # the default f_x axis (affine: ±0.574 … ±1.386)
    [-1.5, -1.098, -0.451, -0.115, 0.0, 0.115, 0.451, 1.098, 1.5]
    """
    t = -np.cos(np.pi * np.arange(n) / (n - 1))
    t[np.abs(t) < 1e-15] = 0.0
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
    b = np.empty(n)
    d = np.empty(n)
    b[0], d[0] = 1.0, 0.0
    if n > 1:
        b[1], d[1] = t, 1.0
    for k in range(2, n):
        b[k] = 2 * t * b[k - 1] - b[k - 2]
        d[k] = 2 * b[k - 1] + 2 * t * d[k - 1] - d[k - 2]
    return b, d


def _to_chebyshev(values: np.ndarray, shape: tuple[int, ...], t0: np.ndarray | None = None) -> np.ndarray:
    """Tensor Chebyshev coefficients (shape + (m,)) of grid values (shape + (m,)) at
    Chebyshev–Lobatto points: one small Vandermonde solve per axis. ``t0`` (shape): the first
    axis's Chebyshev variable at each point, where the points of a line along it are not the
    Lobatto points (a displacement axis, :data:`NODE_TOL`): each such line is interpolated through
    its own points first, then the other axes as usual — the polynomial is still exact at every
    point."""
    c = values
    n = shape[0]
    if t0 is None:
        t0 = np.broadcast_to(-np.cos(np.pi * np.arange(n) / (n - 1)).reshape((n,) + (1,) * (len(shape) - 1)), shape)
    T = np.moveaxis(np.asarray(t0, float), 0, -1).reshape(-1, n)  # (lines, n)
    Vs = np.stack([np.stack([cheb_basis(float(x), n)[0] for x in line]) for line in T])  # (lines, n, n)
    rhs = np.moveaxis(c, 0, len(shape) - 1).reshape(len(T), n, -1)  # (lines, n, m)
    c = np.moveaxis(np.linalg.solve(Vs, rhs).reshape(*shape[1:], n, -1), len(shape) - 1, 0)
    c = c.reshape(values.shape)
    for ax, n in enumerate(shape[1:], start=1):
        t = -np.cos(np.pi * np.arange(n) / (n - 1))
        V = np.stack([cheb_basis(x, n)[0] for x in t])  # V[j, k] = T_k(t_j)
        c = np.moveaxis(np.tensordot(np.linalg.inv(V), c, axes=([1], [ax])), 0, ax)
    return c


# -- the cache key ---------------------------------------------------------------------------------
def atlas_key(fwd: ForwardModel, acfg: AtlasConfig) -> str:
    """SHA-256 (hex) of everything the atlas depends on: mesh and fixed DOFs, law and parameters,
    element, cavities, contact patch (its actuator), tracked points (the probe), envelope, grid,
    solver tolerance, format."""
    h = hashlib.sha256()
    fem = fwd.fem

    def add(a) -> None:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())

    add(fem.x_rest)
    add(fem.tets)
    add(fem.free_dofs)
    # the law per element (its id and parameters) and the element (the connectivity's width):
    # whatever the FemModel carries, so a new law or element order changes the key
    for name in ("mu", "lam", "law_id", "params"):
        v = getattr(fem, name, None)
        if v is not None:
            add(np.asarray(v))
    for name in sorted(fem.cavities):
        h.update(name.encode())
        add(np.asarray(fem.cavities[name]))
    for M in (fwd.H_f.tocsr(), fwd.probe.tocsr()):
        M.sort_indices()
        add(M.indptr)
        add(M.indices)
        add(M.data)
    atlas = acfg.as_dict()
    if not acfg.linear_pressure:  # the keys of atlases built before the option stay valid
        del atlas["linear_pressure"]
    meta = {"format": FORMAT, "atlas": atlas, "tol": fwd.config.tol,
            "markers": fwd.marker_names, "targets": fwd.target_names}
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


# -- the build -------------------------------------------------------------------------------------
def _inner(p: tuple[int, int], centre: tuple[int, int]) -> list[tuple[int, int]]:
    """The neighbours of grid point ``p`` one step nearer ``centre`` along each axis."""
    j, k = p
    j0, k0 = centre
    out = []
    if j != j0:
        out.append((j - (1 if j > j0 else -1), k))
    if k != k0:
        out.append((j, k - (1 if k > k0 else -1)))
    return out


def _children(p: tuple[int, int], centre: tuple[int, int], ny: int, nz: int) -> list[tuple[int, int]]:
    """The points solved from ``p`` in a plane's walk: a spine along f_z through the centre, a
    branch along f_y from each spine point (a sideways step is the hard one for the solver: the
    fewest of them). A spine point's branches come before the next spine point, so every point's
    inner neighbours (:func:`_inner`) are solved before it."""
    j, k = p
    j0, k0 = centre
    if j != j0:
        out = [(j + (1 if j > j0 else -1), k)]
    else:
        out = [(j0 + 1, k), (j0 - 1, k)]
        out += [(j0, k0 + 1), (j0, k0 - 1)] if k == k0 else [(j0, k + (1 if k > k0 else -1))]
    return [(a, b) for a, b in out if 0 <= a < ny and 0 <= b < nz]


def _plane_walk(ny: int, nz: int, j0: int, k0: int) -> list[tuple[tuple[int, int], tuple[int, int] | None, int]]:
    """The (f_y, f_z) grid points of a plane from the one nearest zero load outwards, depth first
    along :func:`_children`: (point, the point it is solved from (None: from rest), number of points
    solved from it). Depth first, a point's start is the point solved just before it except after a
    branch's end, so the walk keeps the factors of only a few points (:func:`_sweep`).

    >>> [p for p, _, _ in _plane_walk(3, 3, 1, 1)]
    [(1, 1), (2, 1), (0, 1), (1, 2), (2, 2), (0, 2), (1, 0), (2, 0), (0, 0)]
    """
    centre = (j0, k0)
    out = []
    stack: list[tuple[tuple[int, int], tuple[int, int] | None]] = [(centre, None)]
    while stack:
        p, parent = stack.pop()
        kids = _children(p, centre, ny, nz)
        out.append((p, parent, len(kids)))
        stack.extend((c, p) for c in reversed(kids))
    return out


def x_patch(fwd: ForwardModel) -> np.ndarray:
    """(3N,) the contact patch's x load vector H_x (per N of f_x): ū_x = H_xᵀ(x − x_rest) is the
    displacement work-conjugate to f_x, the first axis of a displacement-controlled atlas."""
    return np.asarray(fwd.H_f[:, 0].todense()).ravel()


def _solve_ux(fwd: ForwardModel, h: np.ndarray, lam: np.ndarray, target: float, start, bracket,
              tol_m: float, bordered: bool = True, prev=None, fx_range=None) -> tuple:
    """The equilibrium at (f_y, f_z, p_u) = ``lam[1:]`` whose patch displacement ū_x = hᵀ(x − x_rest)
    is ``target`` (m) within ``tol_m``, and the number of solves it took: f_x by Newton on
    ū_x(f_x), the slope the secant of the last two trials (the first: the solve's own ∂ū_x/∂f_x,
    from a factor that may be stale where the state steps), kept inside ``bracket`` (f_x, N, at
    whose ends ū_x lies below and above the target: a stable path's ū_x increases with f_x) and
    bisecting it where Newton leaves it; ``lam[0]`` the first guess. Each trial is a converged
    force-controlled solve (:meth:`ForwardModel.solve`) from the previous one.

    First, though, one mixed-control solve (:class:`PatchControl`: f_x an unknown of bordered chord
    iterations, to ``BORDERED_TOL`` of ``tol_m``) from ``start`` (with ``prev``, the point before it
    on the line: a secant predictor), its f_x anywhere in ``fx_range`` (default ``bracket``): where
    the state snaps through in f_x (the quadratic model's arm pair above ≈ 4.3 N of f_y) the path at
    fixed ū_x goes through a fold, f_x falling on its unstable branch, which no force-controlled
    solve reaches. The trials above only where it fails, or without ``bordered`` (the
    force-controlled-only build, the benchmarks' peer)."""
    lo, hi = (float(b) for b in bracket)
    x_rest = fwd.fem.x_rest
    if bordered:
        rng = tuple(float(b) for b in (bracket if fx_range is None else fx_range))
        lin = _bordered(fwd, h, lam, float(target), start, prev, rng, BORDERED_TOL * tol_m, BORDERED_HALVINGS)
        if lin is not None:
            return lin, 1
    f = float(lam[0])
    lin = start
    trial = np.array(lam, float)
    prev = None
    for n in range(1, UX_MAX_ITER + 1):
        if not lo < f < hi:
            f = 0.5 * (lo + hi)
        trial[0] = f
        lin = fwd.solve(trial, lin, via_tol=VIA_TOL)
        g = float(h @ (lin.x - x_rest)) - target
        if abs(g) <= tol_m:
            return lin, n
        if g < 0:
            lo = f
        else:
            hi = f
        d = (g - prev[1]) / (f - prev[0]) if prev is not None and f != prev[0] else float(h @ lin.U[:, 0])
        prev = (f, g)
        f = f - g / d if d > 0 else math.nan
    raise SolverError(f"atlas: no f_x in [{lo:+.4f}, {hi:+.4f}] N gives the patch displacement "
                      f"{target * 1e3:+.4f} mm at f_y {lam[1]:+.2f} N, f_z {lam[2]:+.2f} N")


def _bordered(fwd: ForwardModel, h: np.ndarray, lam: np.ndarray, target: float, start, prev, bracket, tol_m: float,
              halvings: int):
    """The mixed-control equilibrium at patch displacement ``target`` (m) from ``start`` (``prev``
    the point before it on the line, or None), f_x kept inside ``bracket``; where it does not
    converge, the step in displacement is halved (up to ``halvings`` times, each half from the
    last converged state). None where that fails too."""
    ctl = PatchControl(h, fwd.fem.x_rest, target, tol_m, prev, tuple(bracket))
    try:
        return fwd.eq.solve(start, lam, control=ctl)
    except SolverError:
        if halvings <= 0:
            return None
    mid = 0.5 * (target + float(h @ (start.x - fwd.fem.x_rest)))
    half = _bordered(fwd, h, lam, mid, start, prev, bracket, tol_m, halvings - 1)
    if half is None:
        return None
    return _bordered(fwd, h, lam, target, half, start, bracket, tol_m, halvings - 1)


def _sweep(model, config: EstimatorConfig, acfg: AtlasConfig, i: int, l: int):
    """One task: the (f_y, f_z) plane at grid f_x index ``i`` and pressure index ``l`` (with
    ``acfg.linear_pressure``: at the pressure range's middle, ``l`` ignored). The point
    nearest zero load is reached from rest by continuation, every other one from a converged inner
    neighbour (one grid step nearer zero load): a predictor on the neighbour's sensitivities,
    chord iterations with the neighbour's last factor (kept until the points solved from it are
    done, :func:`_plane_walk`), a refactorization where they stall, Newton where they fail
    (:meth:`~softphantom.estimation.linearization.EquilibriumSolver.solve`). A point whose
    inner neighbour did not converge is
    not tried: reachability is taken to be monotone in the load, so a failure does not cost the
    (slow) failing solves of everything beyond it. Expected solver failures are recorded, not
    raised (a displacement axis's planes at its f_x faces are solved here; the points between by
    :func:`_lines`). Returns (i, l,
    V (ny,nz,4), P (ny,nz,k,3), X (ny,nz,3N) displacements, solved (ny,nz), first failure message
    or '', CPU seconds of this process, pressure derivatives (dV, dP, dX) of the same shapes per Pa
    or None, FX (ny,nz) the points' f_x N, Q (ny,nz) their first coordinate (the node), the number
    of converged forward solves); unsolved entries are NaN."""
    t0 = time.process_time()
    # only the equilibria are kept: the sensitivities come from the kept factor (no GMRES), which
    # is the tangent at the start point's equilibrium; failures are expected at the envelope's
    # corners: the Newton fallback gives up at 1/32 of the load (not 1/1024: a failing solve cost
    # ~10 converging ones)
    fwd = ForwardModel(model, config, exact_sensitivities=False, fallback_min_load_step=FALLBACK_MIN_LOAD_STEP)
    ax = acfg.axes()
    ny, nz = len(ax[1]), len(ax[2])
    linear = acfg.linear_pressure
    p_u = 0.5 * (ax[3][0] + ax[3][-1]) if linear else ax[3][l]
    V = np.full((ny, nz, 4), np.nan)
    P = np.full((ny, nz, fwd.probe.shape[0], 3), np.nan)
    X = np.full((ny, nz, fwd.fem.n_dof), np.nan)
    dV, dP, dX = (np.full_like(a, np.nan) for a in (V, P, X)) if linear else (None, None, None)
    solved = np.zeros((ny, nz), bool)
    FX = np.full((ny, nz), np.nan)
    n_solves = 0
    Q = np.full((ny, nz), ax[0][i])
    centre = (int(np.argmin(np.abs(ax[1]))), int(np.argmin(np.abs(ax[2]))))
    lins: dict[tuple[int, int], object] = {}
    kept: dict[tuple[int, int], object] = {}  # factors of solved points with points still to solve from them
    left: dict[tuple[int, int], int] = {}
    last = None  # the point whose factor the solver holds
    first_error = ""
    for p, parent, n_kids in _plane_walk(ny, nz, *centre):
        if parent in left:
            left[parent] -= 1
        reachable = all(q in lins for q in _inner(p, centre))
        if reachable and parent is not None and last != parent:
            fwd.eq.restore(kept[parent])
        if parent in left and left[parent] == 0:
            kept.pop(parent, None)  # its last child: the copy (28 MB at 6 mm) is not needed any more
        if not reachable:
            continue  # beyond a failure: unreachable (see the docstring)
        j, k = p
        lam = np.array([ax[0][i], ax[1][j], ax[2][k], p_u])
        last = None
        try:
            # a linear pressure axis needs the exact pressure derivative: the tangent at the solution
            # (elsewhere a new factor there costs more than the chord iterations it saves)
            lin = fwd.solve(lam, lins.get(parent), factor_at_solution=linear, via_tol=VIA_TOL)
        except SolverError as exc:
            first_error = first_error or str(exc).splitlines()[0]
            continue
        last = p
        n_solves += 1
        if n_kids > 1:
            kept[p] = fwd.eq.keep()
        left[p] = n_kids
        lins[p] = lin
        solved[j, k] = True
        FX[j, k] = lin.lam[0]
        V[j, k] = lin.V
        P[j, k] = lin.sub_x
        X[j, k] = lin.x - fwd.fem.x_rest
        if linear:
            dV[j, k] = lin.W[:, 3]
            dP[j, k] = lin.sub_U[:, :, 3]
            dX[j, k] = lin.U[:, 3]
    return (i, l, V, P, X, solved, first_error, time.process_time() - t0, (dV, dP, dX) if linear else None, FX, Q,
            n_solves)


def _lines(model, config: EstimatorConfig, acfg: AtlasConfig, k: int, l: int, ends):
    """One task of a displacement axis's inner points: the lines along q at f_z index ``k`` and
    pressure index ``l``, each walked from its lower f_x face to the upper one. ``ends`` (ny,) × 2:
    the faces' patch displacements (m; NaN: unsolved) at (·, k, l). A line starts at its lower face
    point (solved again here, force-controlled, from the previous line's: the f_y rows walked from
    the one nearest zero outwards); each next point is solved at the displacement of its q from
    the point before it (:func:`_solve_ux`: one mixed-control solve, its predictor the secant of
    the last two along the line) — one small step of the state each, where a plane at fixed q
    (:func:`_sweep`) crosses the arm pair's step in f_x from a neighbour in f_y. Returns (k, l, V (n1−2, ny, 4), P (n1−2, ny, k, 3), X
    (n1−2, ny, 3N), solved (n1−2, ny), first failure or '', CPU seconds, FX (n1−2, ny), Q (n1−2, ny),
    converged forward solves)."""
    t0 = time.process_time()
    fwd = ForwardModel(model, config, exact_sensitivities=False, fallback_min_load_step=FALLBACK_MIN_LOAD_STEP)
    ax = acfg.axes()
    n1, ny = len(ax[0]), len(ax[1])
    h = x_patch(fwd)
    lo, hi = ax[0][0], ax[0][-1]
    span = hi - lo
    fz, p_u = ax[2][k], ax[3][l]
    m = n1 - 2
    V = np.full((m, ny, 4), np.nan)
    P = np.full((m, ny, fwd.probe.shape[0], 3), np.nan)
    X = np.full((m, ny, fwd.fem.n_dof), np.nan)
    FX = np.full((m, ny), np.nan)
    Q = np.broadcast_to(ax[0][1:-1, None], (m, ny)).copy()
    solved = np.zeros((m, ny), bool)
    first_error, n_solves = "", 0
    j0 = int(np.argmin(np.abs(ax[1])))
    faces: dict[int, tuple] = {}  # j → (the lower face's Linearization, its kept factor)
    for j in [*range(j0, ny), *range(j0 - 1, -1, -1)]:
        parent = j - 1 if j > j0 else (j + 1 if j < j0 else None)
        u0, u1 = float(ends[0][j]), float(ends[1][j])
        if not (np.isfinite(u0) and np.isfinite(u1)) or (parent is not None and parent not in faces):
            continue  # a face unsolved, or the row before it: beyond the reachable region
        try:
            if parent is not None:
                fwd.eq.restore(faces[parent][1])
            lin = fwd.solve(np.array([lo, ax[1][j], fz, p_u]), faces[parent][0] if parent is not None else None,
                            via_tol=VIA_TOL)
            n_solves += 1
            faces[j] = (lin, fwd.eq.keep())
            before = None  # the point before the last on the line
            for i in range(1, n1 - 1):
                target = u0 + (ax[0][i] - lo) / span * (u1 - u0)
                gap = min(ax[0][i] - ax[0][i - 1], ax[0][i + 1] - ax[0][i])
                u = float(h @ (lin.x - fwd.fem.x_rest))
                u_b = float(h @ (before.x - fwd.fem.x_rest)) if before is not None else u
                if u != u_b and lin.lam[0] != before.lam[0]:  # the secant along the line
                    d = (u - u_b) / (lin.lam[0] - before.lam[0])
                else:
                    d = float(h @ lin.U[:, 0])
                guess = lin.lam[0] + (target - u) / d if d > 0 else lin.lam[0]
                lam = np.array([guess, ax[1][j], fz, p_u])
                start = lin
                lin, n = _solve_ux(fwd, h, lam, target, start, (start.lam[0], hi), NODE_TOL * gap / span * abs(u1 - u0),
                                   prev=before, fx_range=(lo, hi))
                before = start
                n_solves += n
                a = i - 1
                solved[a, j] = True
                V[a, j], P[a, j], X[a, j] = lin.V, lin.sub_x, lin.x - fwd.fem.x_rest
                FX[a, j] = lin.lam[0]
                Q[a, j] = lo + span * (float(h @ (lin.x - fwd.fem.x_rest)) - u0) / (u1 - u0)
        except SolverError as exc:
            first_error = first_error or str(exc).splitlines()[0]
    return k, l, V, P, X, solved, first_error, time.process_time() - t0, FX, Q, n_solves


def fill_weights(solved: np.ndarray, axes: list[np.ndarray]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """How to fill the grid points that did not converge, so the tensor fit is defined: a list of
    (flat index, source flat indices, weights), to apply in order. Each unsolved point takes, along
    every axis where its line has known points, the linear interpolation between the nearest known
    points on either side, or else the linear extrapolation from the two nearest on one side (one:
    its value), averaged over those axes; points with no known point on any line wait for a
    later pass, which also uses the points filled before it.

    >>> s = np.array([True, True, True, False, False])
    >>> [(t, src.tolist(), w.round(3).tolist()) for t, src, w in fill_weights(s, [np.arange(5.0)])]
    [(3, [2, 1], [2.0, -1.0]), (4, [2, 1], [3.0, -2.0])]
    """
    shape = solved.shape
    known = solved.copy()
    if not known.any():
        raise SolverError("atlas: no grid point converged")
    out = []
    while not known.all():
        batch = []
        for idx in map(tuple, np.argwhere(~known)):
            terms: list[tuple[list[int], list[float]]] = []
            for a, xs in enumerate(axes):
                line = list(idx)
                have = [m for m in range(shape[a]) if known[tuple(line[:a] + [m] + line[a + 1:])]]
                if not have:
                    continue
                x = xs[idx[a]]
                below = [m for m in have if m < idx[a]]
                above = [m for m in have if m > idx[a]]
                if below and above:
                    m1, m2 = below[-1], above[0]
                    w2 = (x - xs[m1]) / (xs[m2] - xs[m1])
                    src, w = [m1, m2], [1 - w2, w2]
                else:
                    side = below[::-1] if below else above  # nearest first
                    if len(side) == 1:
                        src, w = side[:1], [1.0]
                    else:
                        m1, m2 = side[:2]
                        w2 = (x - xs[m1]) / (xs[m2] - xs[m1])
                        src, w = [m1, m2], [1 - w2, w2]
                flat = [int(np.ravel_multi_index(tuple(line[:a] + [m] + line[a + 1:]), shape)) for m in src]
                terms.append((flat, w))
            if terms:
                src = np.concatenate([np.array(f) for f, _ in terms])
                w = np.concatenate([np.array(w) for _, w in terms]) / len(terms)
                batch.append((int(np.ravel_multi_index(idx, shape)), src, w))
        for t, _, _ in batch:
            known.flat[t] = True
        out.extend(batch)
    return out


def _fill(values: np.ndarray, weights) -> np.ndarray:
    """``values`` (n_grid, m) with the unsolved rows filled in place by :func:`fill_weights`."""
    for t, src, w in weights:
        values[t] = w @ values[src]
    return values


@dataclass(frozen=True, eq=False)
class Atlas:
    """Tensor Chebyshev polynomials of the forward map over the envelope (see the module docstring).

    ``key`` the cache key; ``config`` the :class:`AtlasConfig`; ``cV`` (n1,n2,n3,n4,4) volume
    coefficients (m³); ``cP`` (n1,n2,n3,n4,k,3) tracked-point coefficients (m); ``cF``
    (n1,n2,n3,n4,r) field-mode coefficients; ``modes`` (3N,r) the POD basis (m); ``x_rest`` (3N,);
    ``build_s`` seconds of the build (wall); ``solves`` converged forward solves; ``field_rms_m``
    the RMS error of the POD truncation over the grid; ``build_cpu_s`` the CPU seconds of the
    forward solves (summed over the workers: independent of the machine's load); ``solved`` (n1,n2,n3,n4) bool, the grid
    points whose solve converged (the others were filled, see :func:`build_atlas`); ``cFx``
    (n1,n2,n3,n4,1) the coefficients of f_x (N) on a displacement-controlled x axis (empty on a
    force axis); ``q_nodes`` (n1,n2,n3,n4) the first coordinate of each grid point (the Lobatto
    node, or on a displacement axis where the point landed, :data:`NODE_TOL`); ``provenance`` what
    the atlas was built for and by (model, contact, tolerance, softphantom version, date: what
    ``softphantom atlas info`` shows and ``atlas verify`` recomputes the key from, :func:`provenance`).

    The polynomials take the atlas's coordinates λ = (q, f_y, f_z, p_u): ``q`` is f_x on a force
    axis and the patch displacement's N-equivalent on a displacement axis (``AtlasConfig.x_control``);
    :meth:`forces` gives the force at λ, :meth:`coords` the λ of a force.
    """

    key: str
    config: AtlasConfig
    cV: np.ndarray
    cP: np.ndarray
    cF: np.ndarray
    modes: np.ndarray
    x_rest: np.ndarray
    build_s: float
    solves: int
    field_rms_m: float
    solved: np.ndarray
    build_cpu_s: float = float("nan")
    cFx: np.ndarray | None = None
    q_nodes: np.ndarray | None = None
    provenance: dict | None = None

    def __post_init__(self) -> None:
        if self.config.f_y_splits_N:
            raise ValueError("an Atlas is one piece; a config with f_y_splits_N makes AtlasPatches")
        if self.cFx is None:
            if self.config.x_control != "force":
                raise ValueError("a displacement-controlled atlas needs its f_x coefficients cFx")
            object.__setattr__(self, "cFx", np.zeros((*self.config.shape, 0)))
        if self.q_nodes is None:  # the Lobatto nodes
            n = self.config.shape[0]
            q = self.config.axes()[0].reshape((n,) + (1,) * 3)
            object.__setattr__(self, "q_nodes", np.broadcast_to(q, self.config.shape).copy())
        ok = np.asarray(self.solved, bool)
        # a grid cell is inside the solved region when all its 16 corners converged
        cells = np.ones(tuple(n - 1 for n in ok.shape), bool)
        for corner in np.ndindex(*(2,) * ok.ndim):
            cells &= ok[tuple(slice(c, c + n - 1) for c, n in zip(corner, ok.shape))]
        object.__setattr__(self, "solved", ok)
        object.__setattr__(self, "_cells", cells)
        object.__setattr__(self, "_axes", self.config.axes())
        # solved_at runs per sample where the build left points unsolved: plain lists and bisect
        # (numpy's per-call overhead on 4 tiny axes was ≈ 15 % of a P2 step)
        object.__setattr__(self, "_axes_lists", [
            (xs.tolist(), float(xs[0] - 1e-9 * (1 + abs(xs[0]))), float(xs[-1] + 1e-9 * (1 + abs(xs[-1]))))
            for xs in self._axes])
        # the kernels' view (atlas_kernels): coefficients as (grid points, outputs), C order
        n = int(np.prod(self.config.shape))
        object.__setattr__(self, "_shape", np.array(self.config.shape, dtype=np.int64))
        object.__setattr__(self, "_lo", np.ascontiguousarray(self.config.lower))
        object.__setattr__(self, "_hi", np.ascontiguousarray(self.config.upper))
        object.__setattr__(self, "_wd", np.ascontiguousarray(self.config.stretch))
        for name in ("cV", "cP", "cF", "cFx"):
            c = getattr(self, name)
            object.__setattr__(self, "_k" + name, np.ascontiguousarray(c, dtype=float).reshape(n, -1))

    @property
    def unsolved(self) -> int:
        """Grid points whose forward solve did not converge (filled by extrapolation)."""
        return int(self.solved.size - np.count_nonzero(self.solved))

    def solved_at(self, lam) -> bool:
        """Whether ``lam`` lies in a grid cell whose corners all converged (False outside the box)."""
        idx = []
        for v, (xs, lo, hi) in zip(np.asarray(lam, float).tolist(), self._axes_lists):
            if not lo <= v <= hi:
                return False
            idx.append(min(max(bisect.bisect_left(xs, v) - 1, 0), len(xs) - 2))
        return bool(self._cells[tuple(idx)])

    # -- evaluation -------------------------------------------------------------------------------
    def volumes(self, lam) -> tuple[np.ndarray, np.ndarray]:
        """(V (4,) m³, J (4,4) ∂V/∂λ in m³/N, m³/Pa) at ``lam`` inside the envelope (one compiled
        pass over the coefficients; :meth:`volumes_reference` is the tensordot it is tested against)."""
        V, J = np.empty(4), np.empty((4, 4))
        ak.eval_vj(self._kcV, self._shape, self._lo, self._hi, self._wd, np.asarray(lam, float), V, J)
        return V, J

    def points(self, lam) -> np.ndarray:
        """(k,3) m tracked points (markers, then targets) at ``lam``."""
        out = np.empty(self._kcP.shape[1])
        ak.eval_value(self._kcP, self._shape, self._lo, self._hi, self._wd, np.asarray(lam, float), out)
        return out.reshape(-1, 3)

    def nodes(self, lam) -> np.ndarray:
        """(N,3) m node positions at ``lam`` (the POD field)."""
        coef = np.empty(self._kcF.shape[1])
        ak.eval_value(self._kcF, self._shape, self._lo, self._hi, self._wd, np.asarray(lam, float), coef)
        return (self.x_rest + self.modes @ coef).reshape(-1, 3)

    @property
    def displacement_x(self) -> bool:
        """Whether the first axis is the patch displacement (f_x an output), ``AtlasConfig.x_control``."""
        return self.config.x_control == "displacement"

    def forces(self, lam) -> np.ndarray:
        """(3,) N the force at the atlas coordinates ``lam`` (on a force axis: ``lam[:3]``)."""
        f = np.array(lam[:3], float)
        if self.displacement_x:
            out = np.empty(1)
            ak.eval_value(self._kcFx, self._shape, self._lo, self._hi, self._wd, np.asarray(lam, float), out)
            f[0] = out[0]
        return f

    def force_jacobian(self, lam) -> np.ndarray:
        """(3, 4) ∂f/∂λ at the atlas coordinates ``lam``: the identity's rows on a force axis; on a
        displacement axis row 0 is f_x's gradient (∂f_x/∂q > 0 where the map is stable)."""
        Jf = np.eye(3, 4)
        if self.displacement_x:
            V, J = np.empty(1), np.empty((1, 4))
            ak.eval_vj(self._kcFx, self._shape, self._lo, self._hi, self._wd, np.asarray(lam, float), V, J)
            Jf[0] = J[0]
        return Jf

    def by_force(self, lam, J: np.ndarray) -> np.ndarray:
        """A Jacobian ``J`` (m, 4) per unit of the atlas coordinates at ``lam`` as per unit of the
        loads (f, p_u) (N, Pa): on a displacement axis by the chain rule through q(f, p_u),
        ∂/∂f_x = ∂/∂q / (∂f_x/∂q) and ∂/∂λ_a −= ∂/∂f_x · ∂f_x/∂λ_a for the other loads."""
        if not self.displacement_x:
            return J
        a = self.force_jacobian(lam)[0]
        J = np.array(J, float)
        J[:, 0] /= a[0]
        J[:, 1:] -= np.outer(J[:, 0], a[1:])
        return J

    def coords(self, force, p_Pa: float, tol_N: float = 1e-10) -> np.ndarray:
        """(4,) the atlas coordinates of the force ``force`` (3,) N at urethra pressure ``p_Pa``: on a
        displacement axis the q whose f_x is ``force[0]`` (Newton, bracketed by the axis; a force
        beyond the envelope's f_x faces gives the face)."""
        lam = np.array([*np.asarray(force, float)[:3], float(p_Pa)])
        if not self.displacement_x:
            return lam
        target = lam[0]
        lo, hi = float(self.config.lower[0]), float(self.config.upper[0])
        q = min(max(target, lo), hi)
        for _ in range(60):
            lam[0] = q
            g = self.forces(lam)[0] - target
            if abs(g) <= tol_N:
                break
            if g < 0:
                lo = q
            else:
                hi = q
            d = self.force_jacobian(lam)[0, 0]
            q = q - g / d if d > 0 else math.nan
            if not lo <= q <= hi:
                q = 0.5 * (lo + hi)
            if hi - lo <= tol_N * 1e-3:
                break
        lam[0] = q
        return lam

    # the references: tensor contractions in numpy (the evaluation before the kernels)
    def _t(self, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(t, dt/dλ) per axis: the Chebyshev variable of each load (:func:`axis_t`)."""
        lo, hi, w = self.config.lower, self.config.upper, self.config.stretch
        return np.array([axis_t(float(x), a, b, c) for x, a, b, c in zip(np.asarray(lam, float), lo, hi, w)]).T

    def _bases(self, lam):
        t = self._t(lam)[0]
        return [cheb_basis(float(ti), n) for ti, n in zip(t, self.config.shape)]

    def volumes_reference(self, lam) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`volumes` by numpy tensor contractions (the reference of the kernel)."""
        (b1, d1), (b2, d2), (b3, d3), (b4, d4) = self._bases(lam)
        c = self.cV
        # contract the pressure axis first (value only needed there for the force columns)
        c4 = np.tensordot(c, np.stack([b4, d4]), axes=([3], [1]))  # (n1,n2,n3,4,2)
        c3 = np.tensordot(c4, np.stack([b3, d3]), axes=([2], [1]))  # (n1,n2,4,2,2)
        c2 = np.tensordot(c3, np.stack([b2, d2]), axes=([1], [1]))  # (n1,4,2,2,2)
        r = np.tensordot(np.stack([b1, d1]), c2, axes=([1], [0]))  # (2,4,2,2,2): a, out, d, c, b
        V = r[0, :, 0, 0, 0]
        scale = self._t(lam)[1]
        J = np.stack([r[1, :, 0, 0, 0], r[0, :, 0, 0, 1], r[0, :, 0, 1, 0], r[0, :, 1, 0, 0]], axis=1) * scale
        return V, J

    def _value(self, c: np.ndarray, lam) -> np.ndarray:
        """The polynomial with coefficients ``c`` at ``lam`` by numpy contractions (the reference
        of :meth:`points` and :meth:`nodes`)."""
        b = [bd[0] for bd in self._bases(lam)]
        r = c
        for v in b:
            r = np.tensordot(v, r, axes=([0], [0]))
        return r

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.cV, self.cP, self.cF, self.cFx, self.modes, self.x_rest)))

    @property
    def field_modes(self) -> int:
        """Modes of the POD field basis."""
        return int(self.modes.shape[1])

    # -- files ------------------------------------------------------------------------------------
    _ARRAYS = ("cV", "cP", "cF", "cFx", "q_nodes", "modes", "x_rest", "solved")

    def _digest(self) -> str:
        h = hashlib.sha256()
        for k in self._ARRAYS:
            h.update(np.ascontiguousarray(getattr(self, k)).tobytes())
        return h.hexdigest()

    def save(self, path) -> Path:
        """Write the atlas (npz; written to a temporary name, then renamed: never half a file)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {"format": FORMAT, "key": self.key, "config": self.config.as_dict(), "build_s": self.build_s,
                "solves": self.solves, "field_rms_m": self.field_rms_m, "build_cpu_s": self.build_cpu_s,
                "digest": self._digest(), "provenance": self.provenance or {}}
        buf = io.BytesIO()
        np.savez(buf, meta=np.array(json.dumps(meta)), **{k: getattr(self, k) for k in self._ARRAYS})
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(buf.getvalue())
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path, key: str | None = None) -> "Atlas":
        """Read an atlas. One-line errors naming the file and what is wrong with it:
        :class:`AtlasCorrupt` if it is unreadable (truncated, not an atlas) or its arrays do not
        match the digest it was written with (modified or damaged); :class:`AtlasMismatch` if it
        was written by a softphantom of another file format, or ``key`` is given and differs
        (another model, law, contact, envelope or grid)."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                fmt = meta.get("format")
                if fmt != FORMAT:
                    raise AtlasMismatch(f"{path}: atlas file format {fmt}, this softphantom reads format {FORMAT} "
                                        f"(written by another version): rebuild it (softphantom atlas build)")
                arrays = {k: z[k] for k in cls._ARRAYS}
            at = cls(key=meta["key"], config=AtlasConfig(**meta["config"]), build_s=float(meta["build_s"]),
                     solves=int(meta["solves"]), field_rms_m=float(meta["field_rms_m"]),
                     build_cpu_s=float(meta.get("build_cpu_s", "nan")), provenance=meta.get("provenance") or None,
                     **arrays)
            ok = at._digest() == meta["digest"]
        except AtlasMismatch:
            raise
        except Exception as exc:  # noqa: BLE001 - any unreadable file is corrupt
            raise AtlasCorrupt(f"{path}: not a readable atlas file, truncated or not an atlas "
                               f"({type(exc).__name__})") from None
        if not ok:
            raise AtlasCorrupt(f"{path}: atlas arrays do not match the digest they were written with "
                               f"(modified or damaged)")
        if key is not None and at.key != key:
            raise AtlasMismatch(f"{path}: atlas built for another model, law, contact or envelope "
                                f"(key {at.key[:12]}…, expected {key[:12]}…); rebuild it")
        return at


@dataclass(frozen=True)
class AtlasPatches:
    """An atlas piecewise along f_y (``AtlasConfig.f_y_splits_N``): ordinary :class:`Atlas` pieces
    over adjacent f_y ranges, each its own tensor polynomial, cached and built as any atlas.

    Why: one polynomial in f_y carries a sharp feature at one end of the range (the quadratic
    model's fold above ≈ 3.5 N, where the arm pair buckles) down to loads where the map is smooth
    and nearly symmetric, and there the yaw reads the back pair's volume difference at ≈ 1° per mm³
    (docs/estimation.md, Known limits). Neighbouring pieces share their f_y face, each solved by
    its own build, so the map is continuous there to the builds' tolerance. Evaluation picks the
    piece by f_y (a face belongs to the piece below it); :class:`AtlasEstimator` runs its
    Gauss–Newton in one piece and moves to the neighbour when it stops on the shared face.
    """

    config: AtlasConfig
    patches: tuple[Atlas, ...]

    def __post_init__(self) -> None:
        want = self.config.patches()
        if len(want) < 2 or len(self.patches) != len(want) or any(
                a.config.as_dict() != c.as_dict() for a, c in zip(self.patches, want)):
            raise ValueError("AtlasPatches: one piece per f_y range of the config, in order")
        object.__setattr__(self, "_splits", list(self.config.f_y_splits_N))

    def index(self, f_y: float) -> int:
        """The piece holding ``f_y`` (N); beyond the ends, the end piece."""
        return bisect.bisect_left(self._splits, float(f_y))

    def piece(self, lam) -> Atlas:
        return self.patches[self.index(lam[1])]

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(a.key for a in self.patches)

    @property
    def displacement_x(self) -> bool:
        return self.patches[0].displacement_x

    @property
    def unsolved(self) -> int:
        return sum(a.unsolved for a in self.patches)

    @property
    def solves(self) -> int:
        return sum(a.solves for a in self.patches)

    @property
    def build_s(self) -> float:
        return sum(a.build_s for a in self.patches)

    @property
    def build_cpu_s(self) -> float:
        return sum(a.build_cpu_s for a in self.patches)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.patches)

    @property
    def field_rms_m(self) -> float:
        return max(a.field_rms_m for a in self.patches)

    @property
    def field_modes(self) -> int:
        return max(a.field_modes for a in self.patches)

    def solved_at(self, lam) -> bool:
        return self.piece(lam).solved_at(lam)

    def volumes(self, lam):
        return self.piece(lam).volumes(lam)

    def volumes_reference(self, lam):
        return self.piece(lam).volumes_reference(lam)

    def points(self, lam) -> np.ndarray:
        return self.piece(lam).points(lam)

    def nodes(self, lam) -> np.ndarray:
        return self.piece(lam).nodes(lam)

    def forces(self, lam) -> np.ndarray:
        return self.piece(lam).forces(lam)

    def by_force(self, lam, J: np.ndarray) -> np.ndarray:
        return self.piece(lam).by_force(lam, J)

    def coords(self, force, p_Pa: float, tol_N: float = 1e-10) -> np.ndarray:
        return self.patches[self.index(np.asarray(force, float)[1])].coords(force, p_Pa, tol_N)


class AtlasCorrupt(UserError):
    """An atlas file that cannot be used (unreadable, or content not matching its digest)."""


class AtlasMismatch(UserError):
    """A readable atlas file that is not for this use (another file format, model or settings)."""


def provenance(model, fwd: ForwardModel) -> dict:
    """What an atlas records about its origin: enough to recompute its key from the model alone
    (the contact point and patch radius, the solver tolerance: :func:`softphantom.estimation.atlas_store.verify_atlas`)
    and to tell a user what it is (model name, nodes, element order, version, date)."""
    import datetime

    from softphantom import __version__

    c = fwd.config.contact
    return {"softphantom": __version__, "model": getattr(getattr(model, "design", None), "name", ""),
            "nodes": int(len(fwd.fem.x_rest) // 3), "element_order": int(fwd.fem.order),
            "contact": c if isinstance(c, str) else [float(v) for v in c],
            "contact_radius_m": float(fwd.config.contact_radius_m), "tol": float(fwd.config.tol),
            "built_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}


def build_atlas(model, config: EstimatorConfig | None = None, atlas: AtlasConfig | None = None, *,
                scheduler: str | None = None, n_workers: int | None = None, progress: bool = True,
                fwd: ForwardModel | None = None, processes: bool = True, log=print) -> Atlas | AtlasPatches:
    """Build the atlas of ``model`` (forward solves in parallel, a Dask local cluster by default or
    the one at ``scheduler``; ``processes=False``: worker threads, for small models and tests).
    ``atlas`` None: :func:`default_atlas_config` of the model's element order.

    A corner of the envelope box may be physically unreachable for the model (e.g. a large push
    with sideways force inverts an element under a point contact). Such grid points are recorded,
    not fatal: each plane walks outwards from zero load and does not try points beyond one that
    failed (:func:`_sweep`); the unsolved points are filled by linear extrapolation from their
    converged neighbours along the grid lines (:func:`fill_weights`) so the tensor fit is defined,
    and every grid cell with an unsolved corner is outside the envelope (``Atlas.solved_at``; the
    estimator's ``in_envelope`` is False there). ``log`` gets one line per plane with failures and
    a summary. Raises :class:`~softphantom.errors.SolverError` only if no point converged."""
    from softphantom.parallel import dask_client, map_tasks

    cfg = config or EstimatorConfig()
    fwd = fwd or ForwardModel(model, cfg)
    acfg = atlas or default_atlas_config(fwd.fem.order)
    if acfg.f_y_splits_N:  # one build per piece along f_y
        return AtlasPatches(acfg, tuple(
            build_atlas(model, cfg, sub, scheduler=scheduler, n_workers=n_workers, progress=progress, fwd=fwd,
                        processes=processes, log=log) for sub in acfg.patches()))
    t0 = time.perf_counter()
    key = atlas_key(fwd, acfg)
    n1, n2, n3, n4 = acfg.shape
    ndof = fwd.fem.n_dof
    k = fwd.probe.shape[0]
    V = np.empty((n1, n2, n3, n4, 4))
    P = np.empty((n1, n2, n3, n4, k, 3))
    X = np.empty((n1, n2, n3, n4, ndof), dtype=np.float64)
    solved = np.zeros((n1, n2, n3, n4), bool)
    FX = np.empty((n1, n2, n3, n4))
    QN = np.empty((n1, n2, n3, n4))  # the first coordinate of each point
    planes = [(i, l) for l in range(1 if acfg.linear_pressure else n4) for i in range(n1)]
    ax = acfg.axes()
    cpu_s = 0.0
    n_fwd = 0
    label = f"atlas: {acfg.n_solves} forward solves"
    offline = None
    with dask_client(scheduler, n_workers, processes=processes) as client:
        if acfg.offline == "rom":  # the grid by a reduced model (softphantom.estimation.offline)
            from softphantom.estimation.offline import rom_grid

            V, P, X, solved, FX, QN, cpu_s, n_fwd, offline = rom_grid(model, cfg, acfg, fwd, client,
                                                                      progress=progress, log=log)
            stages = []
        elif acfg.x_control == "force":
            stages = [(planes, label, False)]
        else:  # the f_x faces first: their patch displacements are the inner lines' ends
            faces = [(i, l) for i, l in planes if i in (0, n1 - 1)]
            stages = [(faces, f"{label}: the f_x faces", False),
                      ([(k, l) for l in range(n4) for k in range(n3)], f"{label}: lines between the faces", True)]
        for stage, what, between in stages:
            if between:
                h = x_patch(fwd)
                ux = {i: np.where(solved[i], X[i] @ h, np.nan) for i in (0, n1 - 1)}  # (n2, n3, n4) m
                args = [(model, cfg, acfg, kz, lp, (ux[0][:, kz, lp], ux[n1 - 1][:, kz, lp])) for kz, lp in stage]
                res = map_tasks(client, _lines, args, label=what, progress=progress)
                bad = [r for r in res if not r.ok]
                if bad:
                    kz, lp = args[bad[0].index][3:5]
                    raise SolverError(f"atlas: lines at f_z index {kz}, pressure index {lp} failed: {bad[0].error}")
                for r in res:
                    kz, lp, v, p, x, ok, err, cpu, fx, q, n_tried = r.value
                    cpu_s += cpu
                    n_fwd += n_tried
                    V[1:-1, :, kz, lp], P[1:-1, :, kz, lp], X[1:-1, :, kz, lp] = v, p, x
                    FX[1:-1, :, kz, lp], QN[1:-1, :, kz, lp], solved[1:-1, :, kz, lp] = fx, q, ok
                    if not ok.all():
                        log(f"atlas: lines at f_z {ax[2][kz]:+.2f} N, urethra {ax[3][lp] * 1e-3:.1f} kPa: "
                            f"{ok.size - ok.sum()} of {ok.size} points unreachable ({err or 'beyond a failed point'})")
                continue
            args = [(model, cfg, acfg, i, l) for i, l in stage]
            res = map_tasks(client, _sweep, args, label=what, progress=progress)
            bad = [r for r in res if not r.ok]
            if bad:  # not a solver failure (those are recorded): a bug or a lost worker
                i, l = args[bad[0].index][3:5]
                raise SolverError(f"atlas: plane f_x index {i}, pressure index {l} failed: {bad[0].error}")
            for r in res:
                i, l, v, p, x, ok, err, cpu, deriv, fx, q, n_tried = r.value
                cpu_s += cpu
                n_fwd += n_tried
                QN[i, :, :, l] = q
                if deriv is None:
                    V[i, :, :, l], P[i, :, :, l], X[i, :, :, l], FX[i, :, :, l] = v, p, x, fx
                    solved[i, :, :, l] = ok
                else:  # the tangent line in the pressure through the middle plane
                    half = 0.5 * (ax[3][-1] - ax[3][0])
                    for l, sgn in ((0, -half), (n4 - 1, half)):
                        V[i, :, :, l], P[i, :, :, l], X[i, :, :, l] = (a + sgn * d for a, d in zip((v, p, x), deriv))
                        FX[i, :, :, l], QN[i, :, :, l] = fx, q
                        solved[i, :, :, l] = ok
                if not ok.all():
                    p_u = 0.5 * (ax[3][0] + ax[3][-1]) if deriv is not None else ax[3][l]
                    log(f"atlas: plane {'f_x' if acfg.x_control == 'force' else 'q'} {ax[0][i]:+.2f} N, urethra "
                        f"{p_u * 1e-3:.1f} kPa: {ok.size - ok.sum()} of {ok.size} points unreachable "
                        f"({err or 'beyond a failed point'})")
    if acfg.x_control == "displacement" and offline is None:
        log(f"atlas: {n_fwd} converged forward solves for {int(solved.sum())} points (displacement axis: "
            f"{n_fwd - int(solved.sum())} more, the lines' faces solved again and the trials)")
    weights = fill_weights(solved, ax)
    for a in (V.reshape(solved.size, -1), P.reshape(solved.size, -1), X.reshape(solved.size, -1), FX.reshape(-1, 1)):
        _fill(a, weights)
    # POD of the displacement field: the Gram matrix of the snapshots (n_grid²) is small
    D = X.reshape(-1, ndof)
    del X
    G = D @ D.T
    w, Q = np.linalg.eigh(G)
    w, Q = w[::-1].clip(min=0.0), Q[:, ::-1]
    total = float(w.sum())
    tail = total - np.cumsum(w)
    r = int(min(FIELD_MAX_MODES, max(1, np.searchsorted(-tail, -FIELD_RTOL * total) + 1)))
    modes = D.T @ (Q[:, :r] / np.sqrt(np.maximum(w[:r], 1e-300)))  # (3N, r), orthonormal columns
    coef = D @ modes  # (n_grid, r)
    field_rms = float(np.sqrt(max(tail[r - 1], 0.0) / D.size))
    shape = acfg.shape
    # the first axis's Chebyshev variable at each point (a displacement axis's points are where
    # they landed: each line is fitted through its own, _to_chebyshev)
    tq = np.vectorize(axis_t)(QN, ax[0][0], ax[0][-1], acfg.stretch[0])[0]
    cV = _to_chebyshev(V.reshape(*shape, 4), shape, tq)
    cP = _to_chebyshev(P.reshape(*shape, k * 3), shape, tq).reshape(*shape, k, 3)
    cF = _to_chebyshev(coef.reshape(*shape, r), shape, tq)
    # f_x as an output: on a displacement axis the polynomial of the solved f_x; on a force axis
    # f_x is the axis variable itself (its polynomial is not needed, and not exact on a stretch)
    cFx = _to_chebyshev(FX[..., None], shape, tq) if acfg.x_control == "displacement" else np.zeros((*shape, 0))
    return Atlas(key=key, config=acfg, cV=cV, cP=cP, cF=cF, cFx=cFx, q_nodes=QN, modes=modes, x_rest=fwd.fem.x_rest.copy(),
                 build_s=time.perf_counter() - t0, solves=int(solved.sum()) * acfg.n_solves // solved.size,
                 field_rms_m=field_rms, solved=solved, build_cpu_s=cpu_s,
                 provenance={**provenance(model, fwd), **({"offline": offline} if offline else {})})


def atlas_path(model_dir, key: str) -> Path:
    """Where the atlas of key ``key`` lives next to a model directory."""
    return Path(model_dir) / "atlas" / f"{key[:32]}.npz"


def _solves(at: Atlas) -> str:
    if not at.unsolved:
        return f"{at.solves} forward solves"
    return (f"{at.solves} of {at.config.n_solves} forward solves converged ({at.unsolved} grid points unreachable: "
            f"filled, outside the envelope)")


def load_or_build(model, config: EstimatorConfig | None = None, atlas: AtlasConfig | None = None, *,
                  cache_dir=None, scheduler: str | None = None, n_workers: int | None = None,
                  progress: bool = True, log=print, fwd: ForwardModel | None = None,
                  rebuild: bool = False) -> Atlas | AtlasPatches:
    """The atlas of ``model`` from ``cache_dir`` (a model directory) if present and valid, else built
    and saved there. A cached file that is damaged, tampered with or of another format is an error
    (:class:`AtlasCorrupt` / :class:`AtlasMismatch`, one line naming the file, nothing overwritten)
    unless ``rebuild``, which builds and replaces it (``softphantom atlas build --rebuild``). With
    ``AtlasConfig.f_y_splits_N`` each piece is loaded or built (and cached) on its own. ``atlas``
    None: :func:`default_atlas_config` of the model's element order."""
    cfg = config or EstimatorConfig()
    fwd = fwd or ForwardModel(model, cfg)
    acfg = atlas or default_atlas_config(fwd.fem.order)
    if acfg.f_y_splits_N:
        return AtlasPatches(acfg, tuple(
            load_or_build(model, cfg, sub, cache_dir=cache_dir, scheduler=scheduler, n_workers=n_workers,
                          progress=progress, log=log, fwd=fwd, rebuild=rebuild) for sub in acfg.patches()))
    key = atlas_key(fwd, acfg)
    path = atlas_path(cache_dir, key) if cache_dir is not None else None
    if path is not None and path.is_file():
        try:
            at = Atlas.load(path, key)
            log(f"atlas: {path} ({at.nbytes / 1e6:.1f} MB, {_solves(at)}, built in {at.build_s:.0f} s)")
            return at
        except (AtlasCorrupt, AtlasMismatch) as exc:
            if not rebuild:
                raise type(exc)(f"{exc}; to build it again: softphantom atlas build --model {cache_dir} --rebuild") from None
            log(f"{exc}: rebuilding")
    elif path is not None and any(len(p.stem) == 32 and set(p.stem) <= set("0123456789abcdef")
                                  for p in Path(cache_dir).glob("*.npz")):
        # the atlas directory given for the model's (it holds atlas files, named by their key;
        # model.npz is the model's own): its atlases are never found, every run builds
        log(f"atlas: warning: {cache_dir} holds atlas files itself, but the cache is a model directory "
            f"(atlases in its atlas/ subdirectory): building into {path.parent}")
    at = build_atlas(model, cfg, acfg, scheduler=scheduler, n_workers=n_workers, progress=progress, fwd=fwd,
                     log=log)
    msg = (f"atlas: {_solves(at)} in {at.build_s:.0f} s ({at.build_cpu_s / at.config.n_solves:.2f} CPU-s a solve), "
           f"{at.nbytes / 1e6:.1f} MB")
    if path is not None:
        at.save(path)
        msg += f" → {path} ({path.stat().st_size / 1e6:.1f} MB on disk)"
    log(msg)
    return at


class AtlasEstimator(EstimatorState):
    """The real-time estimator on an :class:`Atlas` (see the module docstring): ``step(measurement)
    → Estimate`` with no background work; ``node_positions()`` the full field of the last estimate.

    ``Estimate.in_envelope`` is False when the measured pressure lies outside the atlas's range,
    when the best fit wants a force beyond an envelope face that is tighter than the configured
    force bounds (the estimate is then the best one clamped to the envelope), or when it lies in a
    grid cell the build could not solve (the estimate then comes from the extrapolated fill).
    """

    kind = "atlas"

    def __init__(self, model, config: EstimatorConfig | None = None,
                 atlas: Atlas | AtlasPatches | AtlasConfig | None = None,
                 *, cache_dir=None, scheduler: str | None = None, n_workers: int | None = None,
                 progress: bool = True, log=print) -> None:
        self.config = cfg = config or EstimatorConfig()
        self.model = model
        fwd = ForwardModel(model, cfg)
        self.forward = fwd
        if not isinstance(atlas, (Atlas, AtlasPatches)):
            atlas = load_or_build(model, cfg, atlas, cache_dir=cache_dir, scheduler=scheduler,
                                  n_workers=n_workers, progress=progress, log=log, fwd=fwd)
        pieces = atlas.patches if isinstance(atlas, AtlasPatches) else (atlas,)
        if any(a.key != atlas_key(fwd, a.config) for a in pieces):
            raise UserError("atlas built for another model, law, contact or envelope; rebuild it")
        self.atlas = atlas
        self._pieces = pieces
        self.marker_names, self.target_names = fwd.marker_names, fwd.target_names
        nm = fwd.n_markers
        self.rest_markers = fwd.rest.sub_x[:nm].copy()
        self.rest_targets = fwd.rest.sub_x[nm:].copy()
        elo, ehi = atlas.config.lower, atlas.config.upper
        ulo, uhi = np.array(cfg.force_min_N), np.array(cfg.force_max_N)
        self._lo = np.maximum(ulo, elo[:3])
        self._hi = np.minimum(uhi, ehi[:3])
        if np.any(self._lo > self._hi):
            raise UserError(f"force bounds {cfg.force_min_N}..{cfg.force_max_N} N do not meet the atlas "
                            f"envelope {atlas.config.force_min_N}..{atlas.config.force_max_N} N")
        self._bounds = (self._lo.tolist(), self._hi.tolist())
        self._env_lo = np.where(elo[:3] > ulo, self._lo, -np.inf)  # envelope faces inside the bounds
        self._env_hi = np.where(ehi[:3] < uhi, self._hi, np.inf)
        self._faces = list(zip(self._env_lo.tolist(), self._env_hi.tolist()))
        self._p_range = (float(elo[3]), float(ehi[3]))
        # each piece's force bounds: the estimator's, f_y cut to the piece's range
        self._piece_bounds = []
        for a in pieces:
            lo, hi = self._lo.copy(), self._hi.copy()
            lo[1], hi[1] = max(lo[1], a.config.force_min_N[1]), min(hi[1], a.config.force_max_N[1])
            self._piece_bounds.append((lo, hi))
        try:  # the rest markers centred once for the per-sample fit (rigid_fit checks they span a plane)
            rigid_fit(self.rest_markers, self.rest_markers)
            self._cp = self.rest_markers.mean(axis=0)
            self._P0 = np.ascontiguousarray(self.rest_markers - self._cp)
        except DegenerateMarkersError:
            self._cp = self._P0 = None
        ak.warm_up()
        self.reset()

    @property
    def lam(self) -> np.ndarray:
        """(4,) the current actuation estimate: force N (3), urethra pressure Pa (the atlas's
        coordinates of it are ``coords``)."""
        return np.r_[self.atlas.forces(self._lam), self._lam[3]]

    @property
    def coords(self) -> np.ndarray:
        """(4,) the last estimate in the atlas's coordinates (``Atlas.coords``)."""
        return self._lam.copy()

    def reset(self) -> None:
        """Back to rest."""
        self._lam = np.zeros(4)
        self._last = rest_estimate(self.target_names, self.atlas.volumes(self._lam)[1])

    def node_positions(self) -> np.ndarray:
        """(N,3) m node positions of the last estimate (the atlas's field; evaluated when asked,
        not per sample)."""
        return self.atlas.nodes(self._lam)

    def _start(self, p_Pa: float, start) -> tuple[np.ndarray, bool]:
        """The first iterate: the start's forces (default: the last estimate's) clipped to the
        bounds, the measured pressure clipped to the envelope; and whether the pressure was inside."""
        p_lo, p_hi = self._p_range
        p = min(max(float(p_Pa), p_lo), p_hi)
        f = (self._lam if start is None else np.asarray(start, float))[:3].tolist()
        lam = np.array([min(max(v, lo), hi) for v, lo, hi in zip(f, self._bounds[0], self._bounds[1])] + [p])
        return lam, p == float(p_Pa)

    def _inside(self, lam: np.ndarray, inside: bool) -> bool:
        tol = 1e-6
        for f, (lo, hi) in zip(lam[:3].tolist(), self._faces):
            if f <= lo + tol or f >= hi - tol:  # at an envelope face inside the bounds: clamped
                return False
        if inside and self.atlas.unsolved:
            return self.atlas.solved_at(lam)  # where the atlas was filled, not solved
        return inside

    def invert(self, dV, p_Pa: float, start=None) -> tuple[np.ndarray, str, bool, np.ndarray, np.ndarray, int]:
        """Loads that best explain the volumes ``dV`` (4,) m³ at urethra pressure ``p_Pa``:
        (λ (4,), QP status, in_envelope, V (4,), J (4,4) ∂V/∂λ, Gauss–Newton iterations), λ and
        ``start`` in the atlas's coordinates (:meth:`Atlas.coords`; the force is
        :meth:`Atlas.forces` of λ).

        Gauss–Newton from ``start`` (default: the last estimate) on the polynomial volumes, each
        step the volume QP with its exact Jacobian, a step that raises the misfit halved
        (:func:`~softphantom.estimation.atlas_kernels.gn_run`). With no force bound in the way the
        QP's minimizer is a 3 × 3 solve inside the kernel; an iteration whose step meets a bound is
        solved by the configured QP solver (``EstimatorConfig.qp_solver``).
        :meth:`invert_reference` is the same iteration in numpy, every step by the QP solver."""
        lam, inside = self._start(p_Pa, start)
        dV = np.asarray(dV, float)
        k = self._piece_index(lam[1])
        best, seen = None, set()
        while k not in seen:  # one piece, then its neighbour while the fit stops on their shared face
            seen.add(k)
            res = self._invert_piece(k, lam.copy(), dV)
            if best is not None and res[2] >= best[2]:
                break
            best = res
            lam = res[0]
            lo, hi = self._piece_bounds[k]
            if k > 0 and lam[1] <= lo[1] + FACE_TOL_N:
                k -= 1
            elif k < len(self._pieces) - 1 and lam[1] >= hi[1] - FACE_TOL_N:
                k += 1
        lam, code, _, V, J, it = best
        status = "gn:max_iter" if code == ak.MAX_ITER else "optimal"
        return lam, status, self._inside(lam, inside), V, J, it

    def _piece_index(self, f_y: float) -> int:
        return self.atlas.index(f_y) if len(self._pieces) > 1 else 0

    def _invert_piece(self, k: int, lam: np.ndarray, dV: np.ndarray):
        """Gauss–Newton on piece ``k`` from ``lam`` (f_y clamped into it): (λ, code, misfit m⁶, V, J, iterations)."""
        at = self._pieces[k]
        lo, hi = self._piece_bounds[k]
        lam[1] = min(max(lam[1], lo[1]), hi[1])
        V, J = np.empty(4), np.empty((4, 4))
        n3 = at._kcV.shape[0] // at.config.shape[3]
        poly = (np.empty((n3, 4)), np.empty((n3, 4)), at._shape, at._lo, at._hi, at._wd, lam, V, J)
        code, it, cost = ak.gn_run(at._kcV, *poly, 0.0, dV, lo, hi, GN_TOL_N, 0, GN_MAX_ITER)
        while code == ak.NEED_QP:  # a force bound is in the way of this iteration's step: the QP's
            qp = solve_volume_qp(J, V - dV, 0.0, lo - lam[:3], hi - lam[:3], self.config.qp_solver)
            if qp.status != "optimal":
                raise SolverError(f"QP {qp.status}")
            code, cost = ak.gn_update(*poly, cost, dV, qp.dlam[:3].copy(), lo, hi, GN_TOL_N)
            if code == ak.CONTINUE:
                code, it, cost = ak.gn_run(at._kcV, *poly, cost, dV, lo, hi, GN_TOL_N, it, GN_MAX_ITER)
        return lam, code, cost, V, J, it

    def invert_reference(self, dV, p_Pa: float, start=None):
        """:meth:`invert` as it was before the kernels (numpy evaluation, every Gauss–Newton step
        by the QP solver): the reference for the tests and ``bench_estimate.py``'s ratio."""
        at = self.atlas
        lam, inside = self._start(p_Pa, start)
        dV = np.asarray(dV, float)
        V, J = at.volumes_reference(lam)
        cost = float(np.sum((V - dV) ** 2))
        status = "gn:max_iter"
        it = 0
        for it in range(1, GN_MAX_ITER + 1):
            qp = solve_volume_qp(J, V - dV, 0.0, self._lo - lam[:3], self._hi - lam[:3], self.config.qp_solver)
            if qp.status != "optimal":
                raise SolverError(f"QP {qp.status}")
            step = qp.dlam[:3]
            # backtracking: Gauss–Newton on a mildly non-linear map; halve a step that raises the misfit
            for _ in range(ak.BACKTRACK_HALVINGS):
                trial = lam.copy()
                trial[:3] = np.clip(lam[:3] + step, self._lo, self._hi)
                Vt, Jt = at.volumes_reference(trial)
                ct = float(np.sum((Vt - dV) ** 2))
                if ct <= cost * (1 + 1e-12):
                    break
                step = 0.5 * step
            else:
                status = "optimal"  # no descent left: a (bounded) minimum at round-off
                break
            lam, V, J, cost = trial, Vt, Jt, ct
            if np.max(np.abs(step)) <= GN_TOL_N:
                status = "optimal"
                break
        return lam, status, self._inside(lam, inside), V, J, it

    def _pose(self, lam: np.ndarray):
        """(Pose6, target shifts) at ``lam``: the tracked points by the kernel, the markers' rigid
        fit by :func:`~softphantom.estimation.atlas_kernels.rigid_fit_pose`."""
        at = self._pieces[self._piece_index(lam[1])]
        if self._P0 is None:  # rest markers that rigid_fit refuses: let it raise its error, as before
            return pose_and_shifts(self.rest_markers, self.rest_targets, self.target_names, at.points(lam))
        pts, t, ypr = np.empty(at._kcP.shape[1]), np.empty(3), np.empty(3)
        ak.points_pose(at._kcP, at._shape, at._lo, at._hi, at._wd, lam, self._P0, self._cp, pts, t, ypr)
        shifts = pts.reshape(-1, 3)[len(self._P0):] - self.rest_targets
        return Pose6(t, ypr), dict(zip(self.target_names, shifts))

    def step(self, m, skipped: int = 0) -> Estimate:
        """Estimate the state for one measurement; a bad sample repeats the last state with
        ``status="rejected:<why>"`` (as the refresh estimator)."""
        return self._step(m, skipped, reference=False)

    def step_reference(self, m, skipped: int = 0) -> Estimate:
        """:meth:`step` as it was before the kernels (the same estimate to round-off; for
        ``bench_estimate.py``'s old/new ratio and the tests)."""
        return self._step(m, skipped, reference=True)

    def _step(self, m, skipped: int, reference: bool) -> Estimate:
        t0 = time.perf_counter()
        why = check_sample(m)
        if why:
            return repeat_last(self._last, m, f"rejected:{why}", t0, skipped)
        try:
            inv = self.invert_reference if reference else self.invert
            lam, status, inside, V, J, it = inv(m.dV, float(m.p_urethra))
        except SolverError as exc:
            return repeat_last(self._last, m, f"failed:{exc}", t0, skipped)
        at = self._pieces[self._piece_index(lam[1])]
        # the force and the sensitivity to the loads, whatever the atlas's first axis
        if reference:
            force, J = at.forces(lam), at.by_force(lam, J)
            pose, shifts = pose_and_shifts(self.rest_markers, self.rest_targets, self.target_names,
                                           at._value(at.cP, lam))
            cond = sensitivity_cond(J)
        else:
            force = lam[:3].copy()
            if at.displacement_x:
                ak.force_chain(at._kcFx, at._shape, at._lo, at._hi, at._wd, lam, J, force)
            pose, shifts = self._pose(lam)
            cond = float(ak.cond_force(J))
        dV = np.array(m.dV, float)
        est = Estimate(
            t=float(m.t), force=force, p_urethra=float(m.p_urethra), pose=pose, target_shift=shifts,
            volume_pred=V, volume_meas=dV, cond_W=cond, qp_status=status,
            step_time=time.perf_counter() - t0, skipped=int(skipped), in_envelope=inside,
            extra={"qp_residual_m3": math.dist(V, dV), "gn_iterations": it},
        )
        self._lam = lam
        self._last = est
        return est
