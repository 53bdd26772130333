"""The atlas: tensor Chebyshev polynomials of the forward map over the load envelope
(:class:`Atlas`, one piece; :class:`AtlasPatches`, pieces along f_y), evaluated by the compiled
kernels (:mod:`~softphantom.estimation.atlas.kernels`) through the public :class:`KernelView`.

Built by :func:`~softphantom.estimation.atlas.build.build_atlas`, stored by
:mod:`~softphantom.estimation.atlas.store`, inverted by
:class:`~softphantom.estimation.atlas.estimator.AtlasEstimator`.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from softphantom.estimation.atlas import kernels as ak
from softphantom.estimation.atlas.basis import axes_t, tensor_jacobian, tensor_value
from softphantom.estimation.atlas.config import AtlasConfig


@dataclass(frozen=True)
class KernelView:
    """An atlas piece as the compiled kernels take it: the box (``shape`` (4,) int64 terms per axis,
    ``lo`` / ``hi`` (4,) the envelope, ``wd`` (4,) the stretch widths, :attr:`box` the four in the
    kernels' argument order) and the coefficients of each output as (grid points, outputs), C order:
    ``V`` the volumes, ``P`` the tracked points, ``F`` the field modes, ``Fx`` f_x (no columns on a
    force axis)."""

    shape: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    wd: np.ndarray
    V: np.ndarray
    P: np.ndarray
    F: np.ndarray
    Fx: np.ndarray

    @property
    def box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.shape, self.lo, self.hi, self.wd

    @property
    def n_force_terms(self) -> int:
        """Coefficients per output once the pressure is contracted (``atlas.kernels.contract_pressure``)."""
        return self.V.shape[0] // int(self.shape[3])


@dataclass(frozen=True, eq=False)
class Atlas:
    """Tensor Chebyshev polynomials of the forward map over the envelope (:mod:`softphantom.estimation.atlas`).

    ``key`` the cache key; ``config`` the :class:`AtlasConfig`; ``cV`` (n1,n2,n3,n4,n_arms) volume
    coefficients (m³; the n are ``config.coef_shape``: twice the points on a Hermite axis); ``cP``
    (n1,n2,n3,n4,k,3) tracked-point coefficients (m); ``cF``
    (n1,n2,n3,n4,r) field-mode coefficients; ``modes`` (3N,r) the POD basis (m); ``x_rest`` (3N,);
    ``build_s`` seconds of the build (wall); ``solves`` converged forward solves; ``field_rms_m``
    the RMS error of the POD truncation over the grid; ``build_cpu_s`` the CPU seconds of the
    forward solves (summed over the workers: independent of the machine's load); ``solved`` (n1,n2,n3,n4) bool, the grid
    points whose solve converged (the others were filled, see
    :func:`~softphantom.estimation.atlas.build.build_atlas`); ``cFx``
    (n1,n2,n3,n4,1) the coefficients of f_x (N) on a displacement-controlled x axis (empty on a
    force axis); ``q_nodes`` (n1,n2,n3,n4) the first coordinate of each grid point (the Lobatto
    node, or on a displacement axis where the point landed, ``atlas.build.NODE_TOL``); ``provenance`` what
    the atlas was built for and by (model, contact, tolerance, softphantom version, date: what
    ``softphantom atlas info`` shows and ``atlas verify`` recomputes the key from,
    :func:`~softphantom.estimation.atlas.build.provenance`); ``kernel`` the :class:`KernelView` (derived).

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
    kernel: KernelView = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.config.f_y_splits_N:
            raise ValueError("an Atlas is one piece; a config with f_y_splits_N makes AtlasPatches")
        if self.cFx is None:
            if self.config.x_control != "force":
                raise ValueError("a displacement-controlled atlas needs its f_x coefficients cFx")
            object.__setattr__(self, "cFx", np.zeros((*self.config.coef_shape, 0)))
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
        # the kernels' view (atlas.kernels): coefficients as (terms, outputs), C order; the terms per
        # axis are the points', twice those on a Hermite axis (AtlasConfig.coef_shape)
        n = int(np.prod(self.config.coef_shape))
        c = {name: np.ascontiguousarray(getattr(self, name), dtype=float).reshape(n, -1)
             for name in ("cV", "cP", "cF", "cFx")}
        object.__setattr__(self, "kernel", KernelView(
            np.array(self.config.coef_shape, dtype=np.int64), np.ascontiguousarray(self.config.lower),
            np.ascontiguousarray(self.config.upper), np.ascontiguousarray(self.config.stretch),
            c["cV"], c["cP"], c["cF"], c["cFx"]))

    @property
    def draft(self) -> bool:
        """Whether this is a draft atlas (``AtlasConfig.draft``: a coarse grid, its held-out error
        in ``provenance["held_out"]``)."""
        return bool(self.config.draft)

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
        """(V (n_arms,) m³, J (n_arms,4) ∂V/∂λ in m³/N, m³/Pa) at ``lam`` inside the envelope (one
        compiled pass over the coefficients; :meth:`volumes_reference` is the reference it is tested against)."""
        m = self.kernel.V.shape[1]
        V, J = np.empty(m), np.empty((m, 4))
        ak.eval_vj(self.kernel.V, *self.kernel.box, np.asarray(lam, float), V, J)
        return V, J

    def points(self, lam) -> np.ndarray:
        """(k,3) m tracked points (markers, then targets) at ``lam``."""
        out = np.empty(self.kernel.P.shape[1])
        ak.eval_value(self.kernel.P, *self.kernel.box, np.asarray(lam, float), out)
        return out.reshape(-1, 3)

    def nodes(self, lam) -> np.ndarray:
        """(N,3) m node positions at ``lam`` (the POD field)."""
        coef = np.empty(self.kernel.F.shape[1])
        ak.eval_value(self.kernel.F, *self.kernel.box, np.asarray(lam, float), coef)
        return (self.x_rest + self.modes @ np.asarray(coef, dtype=self.modes.dtype)).reshape(-1, 3)

    def scaled(self, s: float, key: str) -> "Atlas":
        """This atlas for the same model with every modulus multiplied by ``s`` (law, ν, mesh and
        contact unchanged; ``key`` that model's key, :func:`~softphantom.estimation.atlas.store.atlas_key`
        with ``config.scaled(s)``). A hyperelastic law's energy is proportional to its moduli at
        fixed ν, so that model's equilibrium under loads λ is this one's under λ / s, exactly (the
        estimator's model has no gravity): the volumes, points and field are the same polynomials
        over the envelope times ``s`` (:meth:`AtlasConfig.scaled`), and f_x on a displacement axis
        is ``s`` times this one's. A new object; the coefficients are shared, not copied."""
        return Atlas(key=key, config=self.config.scaled(s), cV=self.cV, cP=self.cP, cF=self.cF, cFx=self.cFx * s,
                     q_nodes=self.q_nodes * s, modes=self.modes, x_rest=self.x_rest, build_s=self.build_s,
                     solves=self.solves, field_rms_m=self.field_rms_m, solved=self.solved,
                     build_cpu_s=self.build_cpu_s,
                     provenance={**(self.provenance or {}), "load_scale": {"factor": float(s), "from_key": self.key}})

    @property
    def displacement_x(self) -> bool:
        """Whether the first axis is the patch displacement (f_x an output), ``AtlasConfig.x_control``."""
        return self.config.x_control == "displacement"

    def forces(self, lam) -> np.ndarray:
        """(3,) N the force at the atlas coordinates ``lam`` (on a force axis: ``lam[:3]``)."""
        f = np.array(lam[:3], float)
        if self.displacement_x:
            out = np.empty(1)
            ak.eval_value(self.kernel.Fx, *self.kernel.box, np.asarray(lam, float), out)
            f[0] = out[0]
        return f

    def force_jacobian(self, lam) -> np.ndarray:
        """(3, 4) ∂f/∂λ at the atlas coordinates ``lam``: the identity's rows on a force axis; on a
        displacement axis row 0 is f_x's gradient (∂f_x/∂q > 0 where the map is stable)."""
        Jf = np.eye(3, 4)
        if self.displacement_x:
            V, J = np.empty(1), np.empty((1, 4))
            ak.eval_vj(self.kernel.Fx, *self.kernel.box, np.asarray(lam, float), V, J)
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

    # the references: numpy.polynomial evaluation (the kernels are tested against these)
    def volumes_reference(self, lam) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`volumes` by ``numpy.polynomial.chebyshev`` (the reference of the kernel)."""
        t, dt = axes_t(lam, self.config.lower, self.config.upper, self.config.stretch)
        return tensor_value(self.cV, t), tensor_jacobian(self.cV, t, dt)

    def value_reference(self, c: np.ndarray, lam) -> np.ndarray:
        """The polynomial with coefficients ``c`` (the grid's shape + outputs) at ``lam`` by
        ``numpy.polynomial.chebyshev`` (the reference of :meth:`points` and :meth:`nodes`)."""
        return tensor_value(c, axes_t(lam, self.config.lower, self.config.upper, self.config.stretch)[0])

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.cV, self.cP, self.cF, self.cFx, self.modes, self.x_rest)))

    @property
    def field_modes(self) -> int:
        """Modes of the POD field basis."""
        return int(self.modes.shape[1])


@dataclass(frozen=True)
class AtlasPatches:
    """An atlas piecewise along f_y (``AtlasConfig.f_y_splits_N``): ordinary :class:`Atlas` pieces
    over adjacent f_y ranges, each its own tensor polynomial, cached and built as any atlas.

    Why: one polynomial in f_y carries a sharp feature at one end of the range (the quadratic
    model's fold above ≈ 3.5 N, where the arm pair buckles) down to loads where the map is smooth
    and nearly symmetric, and there the yaw reads the back pair's volume difference at ≈ 1° per mm³
    (docs/estimation.md, Known limits). Neighbouring pieces share their f_y face, each solved by
    its own build, so the map is continuous there to the builds' tolerance. Evaluation picks the
    piece by f_y (a face belongs to the piece below it); :class:`~softphantom.estimation.atlas.estimator.AtlasEstimator` runs its
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
    def draft(self) -> bool:
        """Whether this is a draft atlas (``AtlasConfig.draft``)."""
        return bool(self.config.draft)

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



def lagrange_weights(x: float, nodes) -> np.ndarray:
    """(n,) the Lagrange basis of ``nodes`` at ``x``: the weights of the polynomial through the
    nodes' values; exactly one 1 and zeros at a node.

    >>> lagrange_weights(5.0, [0.0, 10.0, 20.0]).tolist()
    [0.375, 0.75, -0.125]
    >>> lagrange_weights(10.0, [0.0, 10.0, 20.0]).tolist() == [0.0, 1.0, 0.0]
    True
    """
    xs = [float(v) for v in nodes]
    x = float(x)
    out = np.empty(len(xs))
    for j, xj in enumerate(xs):
        w = 1.0
        for k, xk in enumerate(xs):
            if k != j:
                w *= (x - xk) / (xj - xk)
        out[j] = w
    return out


class MixedPiece:
    """One piece of an :class:`AtlasStack` at given further pressures: its levels' coefficients
    mixed by the further pressures' Lagrange weights, evaluated with λ (4,) = (q, f_y, f_z, p_1) as
    an :class:`Atlas` piece (its methods are Atlas's, on the mixed :class:`KernelView`). The
    displacement field is the weighted sum of the levels' fields (each has its own POD basis), made
    when asked for."""

    def __init__(self, parts: list[tuple[float, Atlas]]) -> None:
        a0 = parts[0][1]
        self.config = a0.config
        self._parts = parts
        k0 = a0.kernel

        def mix(name: str) -> np.ndarray:
            out = parts[0][0] * getattr(k0, name)
            for w, a in parts[1:]:
                out += w * getattr(a.kernel, name)
            return out

        V, P, Fx = mix("V"), mix("P"), mix("Fx")
        self.kernel = KernelView(k0.shape, k0.lo, k0.hi, k0.wd, V, P, np.zeros((V.shape[0], 0)), Fx)
        cs = self.config.coef_shape
        self.cV = V.reshape(*cs, V.shape[1])
        self.cP = P.reshape(*cs, -1, 3)

    displacement_x = Atlas.displacement_x
    volumes = Atlas.volumes
    points = Atlas.points
    forces = Atlas.forces
    force_jacobian = Atlas.force_jacobian
    by_force = Atlas.by_force
    coords = Atlas.coords
    volumes_reference = Atlas.volumes_reference
    value_reference = Atlas.value_reference

    def nodes(self, lam) -> np.ndarray:
        """(N,3) m node positions at ``lam``: the levels' fields, weighted."""
        out = self._parts[0][0] * self._parts[0][1].nodes(lam)
        for w, a in self._parts[1:]:
            out += w * a.nodes(lam)
        return out

    def solved_at(self, lam) -> bool:
        """Whether every level that counts solved the cell of ``lam``."""
        return all(a.solved_at(lam) for _, a in self._parts)


@dataclass(frozen=True, eq=False)
class AtlasStack:
    """The atlas of a design with M ≥ 2 actuated internal cavities: one 4-D atlas (an
    :class:`Atlas` or :class:`AtlasPatches`) per level of the further pressures p_2 … p_M
    (``AtlasConfig.levels``: a Chebyshev–Lobatto grid over each one's range, C order), each built
    with those pressures held. Evaluated at λ (3 + M,) = (q, f_y, f_z, p_1, p_2 … p_M): the levels'
    coefficients mixed by the Lagrange weights of λ[4:] (:meth:`piece_at`), which is the tensor
    interpolation of a (3 + M)-D atlas whose further axes have those levels — the polynomials are
    linear in their coefficients. So the per-sample Gauss–Newton runs on one mixed 4-D piece with
    the compiled kernels unchanged; at a level's node the stack is that level's atlas exactly."""

    config: AtlasConfig
    levels: tuple

    def __post_init__(self) -> None:
        want = self.config.levels()
        if not self.config.stacked or len(self.levels) != len(want) or any(
                lv.config.as_dict() != c.as_dict() for lv, c in zip(self.levels, want)):
            raise ValueError("AtlasStack: one atlas per level of the config, in order")
        pieces = tuple(lv.patches if isinstance(lv, AtlasPatches) else (lv,) for lv in self.levels)
        object.__setattr__(self, "_pieces", pieces)  # [level][piece]
        object.__setattr__(self, "_axes", [a.tolist() for a in self.config.further_axes()])
        object.__setattr__(self, "_ranges", [(lo * 1e3, hi * 1e3) for lo, hi in
                                             zip(self.config.further_min_kPa, self.config.further_max_kPa)])
        object.__setattr__(self, "_splits", list(self.config.f_y_splits_N))
        object.__setattr__(self, "_mixed", {})

    @property
    def all_pieces(self) -> tuple[Atlas, ...]:
        """Every ordinary atlas of the stack, as ``AtlasConfig.pieces`` orders them."""
        return tuple(a for lv in self._pieces for a in lv)

    @property
    def n_pieces(self) -> int:
        """Pieces along f_y of each level."""
        return len(self._pieces[0])

    def index(self, f_y: float) -> int:
        """The piece holding ``f_y`` (N), as :meth:`AtlasPatches.index`."""
        return bisect.bisect_left(self._splits, float(f_y))

    def weights(self, p_further) -> np.ndarray:
        """(levels,) the Lagrange weights of the further pressures ``p_further`` (M − 1,) Pa."""
        w = np.ones(1)
        for p, nodes in zip(np.asarray(p_further, float).tolist(), self._axes):
            w = np.outer(w, lagrange_weights(p, nodes)).ravel()
        return w

    def piece_at(self, k: int, p_further):
        """Piece ``k`` at the further pressures ``p_further`` (Pa): a level's own :class:`Atlas` at
        its node, else a :class:`MixedPiece` (the last few are kept: a sample's Gauss–Newton and
        pose evaluate one)."""
        key = (int(k), *np.asarray(p_further, float).tolist())
        got = self._mixed.get(key)
        if got is not None:
            return got
        w = self.weights(p_further)
        parts = [(float(v), lv[k]) for v, lv in zip(w.tolist(), self._pieces) if v != 0.0]
        got = parts[0][1] if len(parts) == 1 and parts[0][0] == 1.0 else MixedPiece(parts)
        if len(self._mixed) >= 4:
            self._mixed.clear()
        self._mixed[key] = got
        return got

    def piece(self, lam):
        """The (mixed) piece at λ (3 + M,)."""
        return self.piece_at(self.index(lam[1]), lam[4:])

    @property
    def draft(self) -> bool:
        """Whether this is a draft atlas (``AtlasConfig.draft``)."""
        return bool(self.config.draft)

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(a.key for a in self.all_pieces)

    @property
    def displacement_x(self) -> bool:
        return self.config.x_control == "displacement"

    @property
    def unsolved(self) -> int:
        return sum(a.unsolved for a in self.all_pieces)

    @property
    def solves(self) -> int:
        return sum(a.solves for a in self.all_pieces)

    @property
    def build_s(self) -> float:
        return sum(a.build_s for a in self.all_pieces)

    @property
    def build_cpu_s(self) -> float:
        return sum(a.build_cpu_s for a in self.all_pieces)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.all_pieces)

    @property
    def field_rms_m(self) -> float:
        return max(a.field_rms_m for a in self.all_pieces)

    @property
    def field_modes(self) -> int:
        return max(a.field_modes for a in self.all_pieces)

    def solved_at(self, lam) -> bool:
        """Whether λ (3 + M,) lies inside the further pressures' ranges and in a cell every level
        that counts there solved."""
        for p, (lo, hi) in zip(np.asarray(lam, float)[4:].tolist(), self._ranges):
            if not lo <= p <= hi:
                return False
        return self.piece(lam).solved_at(np.asarray(lam, float)[:4])

    def volumes(self, lam):
        return self.piece(lam).volumes(np.asarray(lam, float)[:4])

    def volumes_reference(self, lam):
        return self.piece(lam).volumes_reference(np.asarray(lam, float)[:4])

    def points(self, lam) -> np.ndarray:
        return self.piece(lam).points(np.asarray(lam, float)[:4])

    def nodes(self, lam) -> np.ndarray:
        return self.piece(lam).nodes(np.asarray(lam, float)[:4])

    def forces(self, lam) -> np.ndarray:
        return self.piece(lam).forces(np.asarray(lam, float)[:4])

    def by_force(self, lam, J: np.ndarray) -> np.ndarray:
        return self.piece(lam).by_force(np.asarray(lam, float)[:4], J)

    def coords(self, force, p_Pa, tol_N: float = 1e-10) -> np.ndarray:
        """(3 + M,) the atlas coordinates of ``force`` (3,) N at the pressures ``p_Pa`` (M,) Pa."""
        p = np.asarray(p_Pa, float)
        k = self.index(np.asarray(force, float)[1])
        return np.r_[self.piece_at(k, p[1:]).coords(force, float(p[0]), tol_N), p[1:]]


def pieces_of(atlas) -> tuple[Atlas, ...]:
    """The ordinary atlases an Atlas, AtlasPatches or AtlasStack is made of (its files, one each)."""
    return tuple(getattr(atlas, "all_pieces", None) or getattr(atlas, "patches", None) or (atlas,))


def regroup(acfg: AtlasConfig, found: dict):
    """The atlas of ``acfg`` from its pieces (``found``: index in ``acfg.pieces()`` → Atlas): an
    Atlas, an AtlasPatches, or a stack of either (:class:`AtlasStack`)."""
    levels, j = [], 0
    for lv in acfg.levels():
        n = len(lv.patches())
        got = [found[j + p] for p in range(n)]
        j += n
        levels.append(got[0] if n == 1 else AtlasPatches(lv, tuple(got)))
    return AtlasStack(acfg, tuple(levels)) if acfg.stacked else levels[0]
