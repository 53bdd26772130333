"""The atlas's settings: its envelope box, grid and first axis (:class:`AtlasConfig`), and the
default a model of each element order gets (:func:`default_atlas_config`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.atlas.basis import cheb_points

if TYPE_CHECKING:
    from softphantom.estimation.forward import ForwardModel

STRETCH_FX_N = 0.02  # the default f_x stretch width: the arm pair's step core at 3.5–5 N (docs/estimation.md)
STRETCH_MIN_POINTS = 9  # f_x points from which the default stretches f_x
STRETCH_Q = 0.3  # the default stretch of a displacement axis (N-equivalent; docs/estimation.md)
X_CONTROLS = ("displacement", "force")
OFFLINE = ("full", "rom")  # how the grid is solved: full solves, or a reduced model checked by full solves


@dataclass(frozen=True)
class AtlasConfig:
    """The envelope and the grid of the atlas.

    ``force_min_N`` / ``force_max_N`` (3,) the envelope box of the force components (the default
    covers the phantom's use with a margin: pushes mostly along +y, the needle axis, up to 5.2 N,
    ±2 N sideways — the paper's pushes and a lateral (1.5, 0.5, −1.0) N push, whose estimate runs
    ≈ 20 % above it on a stiffer model; a 6 N push with 1.4 N sideways does not converge on the
    default mesh, and corners the model cannot reach are flagged, :func:`~softphantom.estimation.atlas.build.build_atlas`);
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
    output (:meth:`~softphantom.estimation.atlas.map.Atlas.forces`). A stable equilibrium has ∂ū_x/∂f_x = H_xᵀK⁻¹H_x > 0, so ū_x is
    monotone in f_x, and where the arm pair steps (f_x moves a few hundredths of a newton while the
    state moves across) the displacement moves with the state: the outputs are smooth in q where
    they are steep in f_x (docs/estimation.md). The build solves the two faces first, then walks
    each line along q from face to face, each node's point one mixed-control solve (f_x an unknown
    fixed by ū_x: :class:`~softphantom.estimation.linearization.PatchControl`), force-controlled
    trials where that fails (:mod:`~softphantom.estimation.atlas.build`).
    The step is still the steepest part of the map in q, but far wider than in f_x: the default
    stretch of such an axis is :data:`STRETCH_Q` (N-equivalent); ``linear_pressure`` needs
    ``"force"`` (its tangent line is at fixed f_x).

    ``hermite_axis`` (None: every axis Lagrange): the index of one axis (0 f_x or q, 1 f_y, 2 f_z,
    3 p_u) interpolated by Hermite: each grid point's solve also gives the exact derivative of every
    output along that axis (GMRES on the tangent at the solution), so the n points of that axis
    determine a polynomial of degree 2n − 1 there
    (:func:`~softphantom.estimation.atlas.basis.to_chebyshev`): n Hermite points stand in for
    ≈ 2n Lagrange points at the cost of one sensitivity a point (on a displacement axis: along q,
    the patch displacement at fixed (f_y, f_z, p_u), the f_x column over ∂ū/∂f_x = H_xᵀK⁻¹H_x;
    along another load, at fixed q: two sensitivities, :func:`~softphantom.estimation.atlas.solves._axis_derivative`). The
    coefficient arrays are 2n long along it (:attr:`coef_shape`); the default stretch counts the
    polynomial's 2n terms (docs/atlas.md).

    ``draft``: a quick atlas (``softphantom atlas build --draft``, :func:`draft_atlas_config`'s
    coarse grid), its held-out error measured after the build and kept in its file; the estimator
    says "draft atlas" when it uses one, and ``--require-full`` refuses it. Part of the key, so a
    draft and a full atlas of the same grid are two files.

    A design of M ≥ 2 actuated internal cavities gets a *stack*: the atlas stays 4-D in (f, p_1)
    (p_1 the first actuated cavity's pressure) and ``further_min_kPa`` / ``further_max_kPa`` (M − 1,)
    give the ranges of p_2 … p_M, each sampled at ``n_further`` (1..9, or one per cavity)
    Chebyshev–Lobatto levels (one: the range's middle, the atlas constant in that pressure); one ordinary atlas is built per level with those pressures held
    (:meth:`levels`, each with its ``held_kPa``, which its cache key includes), and the estimator
    interpolates the levels' coefficients in the measured p_2 … p_M
    (:class:`~softphantom.estimation.atlas.map.AtlasStack`). Without ranges a model of M ≥ 2
    cavities takes p_1's range for each (:meth:`for_cavities`).

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
    hermite_axis: int | None = None
    further_min_kPa: tuple[float, ...] = ()
    further_max_kPa: tuple[float, ...] = ()
    n_further: int | tuple[int, ...] = 3
    held_kPa: tuple[float, ...] = ()
    draft: bool = False

    def __post_init__(self) -> None:
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
        h = self.hermite_axis
        if h is not None:
            if isinstance(h, bool) or int(h) != h or not 0 <= h <= 3:
                raise UserError(f"atlas hermite_axis: None or an axis index 0..3 (f_x, f_y, f_z, p_u), got {h!r}")
            object.__setattr__(self, "hermite_axis", int(h))
            for what, ok in (("offline 'full'", self.offline == "full"),
                             ("no linear_pressure", not self.linear_pressure)):
                if not ok:
                    raise UserError(f"atlas hermite_axis needs {what}")
        n = tuple(self.n_force) if np.ndim(self.n_force) else (self.n_force,) * 3
        if len(n) != 3 or any(int(v) != v or not (2 if a == h else 3) <= v <= 15 for a, v in enumerate(n)):
            on_h = "" if h is None else " (2..15 on the Hermite axis)"
            raise UserError(f"atlas n_force: each must be an integer in 3..15{on_h}, got {self.n_force}")
        object.__setattr__(self, "n_force", tuple(int(v) for v in n))
        if int(self.n_pressure) != self.n_pressure or not 2 <= self.n_pressure <= 15:
            raise UserError(f"atlas n_pressure must be an integer in 2..15, got {self.n_pressure}")
        if self.linear_pressure and self.n_pressure != 2:
            raise UserError(f"atlas linear_pressure needs n_pressure 2, got {self.n_pressure}")
        if self.offline not in OFFLINE:
            raise UserError(f"atlas offline: one of {', '.join(OFFLINE)}, got {self.offline!r}")
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
        self._check_stack()

    def _check_stack(self) -> None:
        """The further pressures' ranges and levels (a stack), or the pressures a level holds."""
        flo = tuple(float(v) for v in np.atleast_1d(self.further_min_kPa))
        fhi = tuple(float(v) for v in np.atleast_1d(self.further_max_kPa))
        if len(flo) != len(fhi) or not all(math.isfinite(a) and math.isfinite(b) and a < b for a, b in zip(flo, fhi)):
            raise UserError(f"atlas further_min_kPa / further_max_kPa: one range min < max per further cavity, "
                            f"got {self.further_min_kPa}..{self.further_max_kPa}")
        object.__setattr__(self, "further_min_kPa", flo)
        object.__setattr__(self, "further_max_kPa", fhi)
        n = self.n_further
        nt = tuple(n) if np.ndim(n) else (n,) * max(len(flo), 1)
        bad = any(isinstance(v, bool) or int(v) != v or not 1 <= v <= 9 for v in nt)
        if bad or (np.ndim(n) and len(nt) != len(flo)):
            raise UserError(f"atlas n_further: an integer in 1..9 (or one per further cavity), got {n!r}")
        object.__setattr__(self, "n_further", tuple(int(v) for v in nt) if flo else int(nt[0]))
        held = tuple(float(v) for v in np.atleast_1d(self.held_kPa))
        if not all(math.isfinite(v) for v in held):
            raise UserError(f"atlas held_kPa: finite pressures, got {self.held_kPa}")
        object.__setattr__(self, "held_kPa", held)
        if flo and held:
            raise UserError("atlas: a stack (further_min_kPa) is of levels, each holding its pressures (held_kPa): "
                            "not both")
        if flo and self.x_control != "force":
            # each level's q is its own patch displacement's map: mixing them is untested
            raise UserError(f"atlas x_control {self.x_control!r} with further pressures (a stack): not supported, "
                            f"use 'force' (--atlas-x-axis force)")
        if flo and self.offline != "full":
            raise UserError("atlas further_min_kPa (a stack) needs offline 'full' (the reduced model has one pressure)")

    @property
    def stacked(self) -> bool:
        """Whether this is a stack over further pressures (``further_min_kPa``): one atlas per level."""
        return bool(self.further_min_kPa)

    def for_cavities(self, m: int) -> "AtlasConfig":
        """This config for a model of ``m`` ≥ 1 actuated internal cavities: itself where it has
        one further range per cavity after the first (none for one cavity); a config with none
        gets the first pressure's range for each further one. Else one line naming the field.

        >>> c = AtlasConfig(p_min_kPa=-2, p_max_kPa=25).for_cavities(2)
        >>> c.further_min_kPa, c.further_max_kPa, c.n_further
        ((-2.0,), (25.0,), (3,))
        """
        m = int(m)
        if len(self.further_min_kPa if self.stacked else self.held_kPa) == m - 1:
            return self  # a stack, a level of one (built alone) or an atlas of one cavity
        if not self.stacked and not self.held_kPa and m > 1:
            return replace(self, further_min_kPa=(self.p_min_kPa,) * (m - 1),
                           further_max_kPa=(self.p_max_kPa,) * (m - 1))
        what = "further_min_kPa" if self.stacked or not self.held_kPa else "held_kPa"
        raise UserError(f"atlas {what}: one per actuated cavity after the first ({m - 1}), got "
                        f"{len(getattr(self, what))}")

    def _further_kPa(self) -> list[np.ndarray]:
        return [cheb_points(n, lo, hi, 0.0) if n > 1 else np.array([0.5 * (lo + hi)])
                for n, lo, hi in zip(self.n_further, self.further_min_kPa, self.further_max_kPa)]

    def further_axes(self) -> list[np.ndarray]:
        """The levels of each further pressure (Pa, the held pressures of :meth:`levels`):
        Chebyshev–Lobatto over its range; one level: its middle (the atlas then constant in that
        pressure over the range, for a cavity that stays near it)."""
        return [x * 1e3 for x in self._further_kPa()]

    def levels(self) -> tuple["AtlasConfig", ...]:
        """A stack's levels in C order over the further pressures' grid: each an ordinary atlas of
        this envelope and grid with the further pressures held at its node (``held_kPa``);
        ``(self,)`` for an atlas that is no stack.

        >>> [c.held_kPa for c in AtlasConfig(further_min_kPa=(0,), further_max_kPa=(20,)).levels()]
        [(0.0,), (10.0,), (20.0,)]
        """
        if not self.stacked:
            return (self,)
        nodes = self._further_kPa()
        base = replace(self, further_min_kPa=(), further_max_kPa=(), n_further=3)
        return tuple(replace(base, held_kPa=tuple(float(nodes[a][i]) for a, i in enumerate(idx)))
                     for idx in np.ndindex(*(len(x) for x in nodes)))

    def pieces(self) -> tuple["AtlasConfig", ...]:
        """Every ordinary atlas a build makes: each level's pieces along f_y, level by level
        (:meth:`levels`, :meth:`patches`); the pieces alone for an atlas that is no stack."""
        return tuple(p for lv in self.levels() for p in lv.patches())

    @property
    def cluster_N(self) -> tuple[float, float, float]:
        """The stretch widths per force axis: ``force_cluster_N``, or the default for this grid and
        first axis where it is None (the first axis stretched where there are enough points, above)."""
        if self.force_cluster_N is not None:
            return self.force_cluster_N
        stretch = self.coef_shape[0] >= STRETCH_MIN_POINTS and self.force_min_N[0] < 0 < self.force_max_N[0]
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
        if self.hermite_axis is None:
            del d["hermite_axis"]  # and an atlas of Lagrange axes
        if not self.stacked:  # and an atlas of one internal pressure
            del d["further_min_kPa"], d["further_max_kPa"], d["n_further"]
        if not self.held_kPa:
            del d["held_kPa"]
        if not self.draft:
            del d["draft"]  # a full atlas keeps the key it had before the field
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

    def scaled(self, s: float) -> "AtlasConfig":
        """The same grid over the loads times ``s`` (forces, pressure, stretch widths, splits): the
        envelope of :meth:`~softphantom.estimation.atlas.map.Atlas.scaled`.

        >>> c = AtlasConfig(f_y_splits_N=(3.3,)).scaled(1.5)
        >>> c.force_max_N, c.p_max_kPa, c.cluster_N, c.f_y_splits_N[0] == 1.5 * 3.3
        ((3.0, 7.800000000000001, 3.0), 60.0, (0.03, 0.0, 0.0), True)
        """
        s = float(s)
        if not (math.isfinite(s) and s > 0):
            raise UserError(f"atlas load scale: a finite factor > 0, got {s}")
        return replace(self, force_min_N=tuple(s * v for v in self.force_min_N),
                       force_max_N=tuple(s * v for v in self.force_max_N), p_min_kPa=s * self.p_min_kPa,
                       p_max_kPa=s * self.p_max_kPa, force_cluster_N=tuple(s * w for w in self.cluster_N),
                       f_y_splits_N=tuple(s * v for v in self.f_y_splits_N),
                       further_min_kPa=tuple(s * v for v in self.further_min_kPa),
                       further_max_kPa=tuple(s * v for v in self.further_max_kPa),
                       held_kPa=tuple(s * v for v in self.held_kPa))

    @property
    def lower(self) -> np.ndarray:
        return np.array([*self.force_min_N, self.p_min_kPa * 1e3])

    @property
    def upper(self) -> np.ndarray:
        return np.array([*self.force_max_N, self.p_max_kPa * 1e3])

    @property
    def stretch(self) -> np.ndarray:
        """(4,) the axes' stretch widths (N, N, N; the pressure axis 0: affine), :func:`~softphantom.estimation.atlas.basis.axis_t`."""
        return np.array([*self.cluster_N, 0.0])

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return (*self.n_force, int(self.n_pressure))

    @property
    def coef_shape(self) -> tuple[int, int, int, int]:
        """The Chebyshev coefficients per axis: :attr:`shape`, twice the points on the Hermite axis."""
        return tuple(2 * n if a == self.hermite_axis else n for a, n in enumerate(self.shape))

    @property
    def n_solves(self) -> int:
        """Forward solves of the build (one pressure plane with ``linear_pressure``; every level of a stack)."""
        return (math.prod(self.n_force) * (1 if self.linear_pressure else int(self.n_pressure))
                * (len(self.f_y_splits_N) + 1) * len(self.levels()))

    def axes(self) -> list[np.ndarray]:
        """The grid's load values per axis (N, N, N, Pa), from the lower bound up."""
        return [cheb_points(n, lo, hi, w) for n, lo, hi, w in zip(self.shape, self.lower, self.upper, self.stretch)]


# The quadratic (10-node) BIP model's atlas: its back arm pair snaps through above f_y ≈ 4.3 N (a fold
# in f_x, followed by the displacement axis) and one f_y polynomial over -1..5.2 N rings below it;
# pieces split at these forces keep each f_y polynomial smooth (measured: docs/estimation.md). f_z is
# smooth but strongly curved (the pitch turns ≈ 28° over ±2 N): 5 Hermite points along it, where 4
# Lagrange points missed by 0.19 mm (docs/atlas.md, "A Hermite axis").
P2_F_Y_SPLITS_N = (3.3,)
P2_N_FORCE = (11, 6, 5)
P2_HERMITE_AXIS = 2


def default_atlas_config(order: int = 1) -> AtlasConfig:
    """The atlas a model of element ``order`` gets when none is asked for: the linear model's
    :class:`AtlasConfig` defaults; for the quadratic model the displacement axis, in pieces along
    f_y (:data:`P2_F_Y_SPLITS_N`), each :data:`P2_N_FORCE` × 3 points, Hermite along f_z.

    >>> default_atlas_config(1) == AtlasConfig()
    True
    >>> c = default_atlas_config(2)
    >>> c.x_control, c.f_y_splits_N, c.shape, c.hermite_axis
    ('displacement', (3.3,), (11, 6, 5, 3), 2)
    """
    if int(order) == 2:
        return AtlasConfig(n_force=P2_N_FORCE, x_control="displacement", f_y_splits_N=P2_F_Y_SPLITS_N,
                           hermite_axis=P2_HERMITE_AXIS)
    return AtlasConfig()


# The draft atlas (``atlas build --draft``): the default envelope on a coarse grid in one piece, the
# quadratic model's on its displacement axis with Hermite f_z (docs/atlas.md, "A draft atlas").
DRAFT_N_FORCE = (5, 4, 3)
DRAFT_N_PRESSURE = 2


def draft_atlas_config(order: int = 1) -> AtlasConfig:
    """The draft atlas of a model of element ``order``: :func:`default_atlas_config`'s envelope and
    first axis on :data:`DRAFT_N_FORCE` × :data:`DRAFT_N_PRESSURE` points, one piece, ``draft``.

    >>> c = draft_atlas_config(2)
    >>> c.shape, c.x_control, c.f_y_splits_N, c.hermite_axis, c.draft, c.n_solves
    ((5, 4, 3, 2), 'displacement', (), 2, True, 120)
    """
    return replace(default_atlas_config(order), n_force=DRAFT_N_FORCE, n_pressure=DRAFT_N_PRESSURE,
                   f_y_splits_N=(), draft=True)


LOAD_SCALE_FILE = "load_scale.json"  # MODEL/atlas/: this model is another's with every modulus times a factor


def model_atlas_config(order: int, model_dir=None, draft: bool = False) -> AtlasConfig:
    """The atlas a model gets when none is asked for: :func:`default_atlas_config` of its element
    order, over loads scaled by the factor its directory records (``MODEL/atlas/load_scale.json``,
    written by ``softphantom calibrate`` for a uniform stiffness scale, whose atlas is the
    uncalibrated model's with the loads scaled: :meth:`~softphantom.estimation.atlas.map.Atlas.scaled`).
    ``draft``: :func:`draft_atlas_config` instead."""
    import json
    from pathlib import Path

    acfg = draft_atlas_config(order) if draft else default_atlas_config(order)
    if model_dir is None:
        return acfg
    f = Path(model_dir) / "atlas" / LOAD_SCALE_FILE
    if not f.is_file():
        return acfg
    try:
        s = float(json.loads(f.read_text())["factor"])
    except (OSError, ValueError, KeyError, TypeError):
        raise UserError(f"{f}: not a load-scale file (expected {{\"factor\": number}})") from None
    return acfg.scaled(s)


FIELD_MAX_MODES = 64  # the displacement field's POD modes at most
FIELD_RTOL = 1e-5  # POD truncation: dropped displacement energy below this fraction (≈ 3e-3 relative RMS)
# a displacement-controlled point is kept where it lands within this fraction of the distance to the
# next node along q (the fit takes each line's own nodes, to_chebyshev): a new solve costs more
# than the slightly moved node
NODE_TOL = 0.1

# how the build's solves are driven (the full build and the reduced model's snapshots and checks)
FALLBACK_MIN_LOAD_STEP = 1.0 / 32
VIA_TOL = 1e-3  # relative residual of the continuation steps between grid points (they only start the next)


def x_patch(fwd: ForwardModel) -> np.ndarray:
    """(3N,) the contact patch's x load vector H_x (per N of f_x): ū_x = H_xᵀ(x − x_rest) is the
    displacement work-conjugate to f_x, the first axis of a displacement-controlled atlas."""
    return np.asarray(fwd.H_f[:, 0].todense()).ravel()
