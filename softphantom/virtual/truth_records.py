"""What a solved truth of the virtual phantom holds (virtual/truth.py solves it; see its
docstring): its settings (:class:`TruthConfig`), each event's keyframes (:class:`EventTruth`), each
group's (:class:`GroupTruth`), the whole (:class:`Truth`) and its samples at given times
(:class:`TruthSamples`), interpolated by PCHIP in the load levels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator

from softphantom.design import PhantomModel
from softphantom.errors import UserError
from softphantom.fem import Corotational, NeoHookean
from softphantom.fem.model import laws_of_design
from softphantom.pose import Pose6, pose_of_markers
from softphantom.virtual.scenario import Event, Scenario

TRUTH_LAWS = ("neo-hookean", "model")


def truth_laws(model: PhantomModel, law: str) -> dict:
    """Region name -> the truth's law object: the design's laws, co-rotational ones replaced by
    their neo-Hookean twin (same E, ν, density) unless ``law == "model"``."""
    by_region = laws_of_design(model.design, model.regions)
    if law == "model":
        return by_region
    return {k: NeoHookean(v.E_Pa, v.nu, v.density_kg_m3) if isinstance(v, Corotational) else v
            for k, v in by_region.items()}


@dataclass(frozen=True)
class TruthConfig:
    """``mesh_scale`` truth node spacing / the model's (:func:`truth_model`); ``levels`` keyframes per push ramp (interpolated
    between: at 3, the P2 Yeoh calibration truth's yaw is off by up to 0.16° mid-ramp, at 9 by
    0.01°; docs/calibration.md);
    ``tol`` Newton's relative residual; ``inflate_steps`` pressure steps up to the limit;
    ``law``: ``"neo-hookean"`` (co-rotational regions become compressible neo-Hookean with the
    same E, ν, density) or ``"model"`` (the design's own laws, as the estimator); ``order``: the
    truth's element order, 2 (10-node tets, the default) or 1 (4-node, e.g. for fast tests).

    >>> TruthConfig(order=3)
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: truth order must be 1 or 2, got 3
    """

    mesh_scale: float = 0.75
    levels: int = 3
    tol: float = 1e-8
    inflate_steps: int = 10
    law: str = "neo-hookean"
    order: int = 2

    def __post_init__(self) -> None:
        if self.law not in TRUTH_LAWS:
            raise UserError(f"truth law must be one of {', '.join(TRUTH_LAWS)}, got {self.law!r}")
        if isinstance(self.order, bool) or self.order not in (1, 2):
            raise UserError(f"truth order must be 1 or 2, got {self.order!r}")


@dataclass(frozen=True, eq=False)
class EventTruth:
    """Keyframes of one event: ``s`` (K,) levels from 0 to 1; ``dV`` (K, cavities) m³ cavity volume
    changes (the arms, then the internal cavities); ``markers`` (K, k, 3) m positions; ``targets``
    (K, t, 3) m displacements; ``bulb_dV`` (K,) m³ change of the volume the outer surface encloses;
    peak load ``force`` (3,) N and ``p_Pa``, the gauge pressure of the inflated cavity
    (``cavity``; 0 for a push); ``x_peak`` (N, 3) truth-mesh nodes at s = 1; ``iterations``
    Newton iterations; ``note`` what happened (e.g. a limit reached)."""

    event: Event
    s: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    targets: np.ndarray
    bulb_dV: np.ndarray
    force: np.ndarray
    p_Pa: float
    x_peak: np.ndarray
    iterations: int
    note: str = ""

    @property
    def cavity(self) -> str | None:
        """The internal cavity the event inflates (None for a push)."""
        return self.event.cavity if self.event.kind == "inflate" else None

    @property
    def p_urethra(self) -> float:
        """The urethra's peak gauge pressure (Pa) in this event."""
        return self.p_Pa if self.cavity == "urethra" else 0.0

    def _interp(self, arr: np.ndarray, s: np.ndarray) -> np.ndarray:
        f = PchipInterpolator(self.s, arr.reshape(len(self.s), -1), axis=0)
        return f(np.clip(s, 0.0, 1.0)).reshape((len(s),) + arr.shape[1:])


def pchip_rows(x: np.ndarray, Y: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Row n of ``Y`` (n, K, D) interpolated at ``q[n]`` by the monotone cubic through (``x``,
    Y[n]) (scipy's :class:`~scipy.interpolate.PchipInterpolator`, one per row, vectorized; linear
    for K = 2); ``q`` clipped to [x0, x_K-1]. (n, D).

    >>> x = np.array([0.0, 0.5, 1.0]); Y = np.array([[[0.0], [1.0], [4.0]], [[2.0], [2.0], [0.0]]])
    >>> pchip_rows(x, Y, np.array([0.25, 1.0])).ravel().tolist() == [
    ...     float(PchipInterpolator(x, Y[0, :, 0])(0.25)), 0.0]
    True
    """
    x = np.asarray(x, float)
    Y = np.asarray(Y, float)
    q = np.clip(np.asarray(q, float), x[0], x[-1])
    h = np.diff(x)
    m = np.diff(Y, axis=1) / h[None, :, None]  # (n, K-1, D) secant slopes
    d = np.empty_like(Y)
    if len(x) == 2:
        d[:] = m
    else:
        # interior: weighted harmonic mean of equal-signed neighbouring slopes, else 0 (Fritsch–Butland)
        w1 = (2 * h[1:] + h[:-1])[None, :, None]
        w2 = (h[1:] + 2 * h[:-1])[None, :, None]
        same = (np.sign(m[:, :-1]) == np.sign(m[:, 1:])) & (m[:, :-1] != 0) & (m[:, 1:] != 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            whm = (w1 / m[:, :-1] + w2 / m[:, 1:]) / (w1 + w2)
            d[:, 1:-1] = np.where(same, 1.0 / whm, 0.0)

        def edge(h0, h1, m0, m1):
            e = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
            e = np.where(np.sign(e) != np.sign(m0), 0.0, e)
            return np.where((np.sign(m0) != np.sign(m1)) & (np.abs(e) > 3 * np.abs(m0)), 3 * m0, e)

        d[:, 0] = edge(h[0], h[1], m[:, 0], m[:, 1])
        d[:, -1] = edge(h[-1], h[-2], m[:, -1], m[:, -2])
    k = np.clip(np.searchsorted(x, q, side="right") - 1, 0, len(x) - 2)
    r = np.arange(len(q))
    hk = h[k][:, None]
    t = ((q - x[k]) / h[k])[:, None]
    return ((2 * t**3 - 3 * t**2 + 1) * Y[r, k] + (t**3 - 2 * t**2 + t) * hk * d[r, k]
            + (-2 * t**3 + 3 * t**2) * Y[r, k + 1] + (t**3 - t**2) * hk * d[r, k + 1])


@dataclass(frozen=True, eq=False)
class GroupTruth:
    """Keyframes of two events acting at once (``pair``: their indices in the scenario's events):
    on the tensor grid of their levels ``s1`` × ``s2`` ((L+1,) each, from 0 to 1), ``dV`` (L+1,
    L+1, cavities) m³, ``markers`` (L+1, L+1, k, 3) m, ``targets`` (L+1, L+1, t, 3) m, ``bulb_dV``
    (L+1, L+1) m³; row 0 and column 0 are the other event alone. At (1, 1): ``force`` (3,) N the
    sum of the peak forces, ``pressures_Pa`` {cavity: Pa}, ``x_peak`` (N, 3) truth-mesh nodes;
    ``solves``, ``iterations`` Newton's for the L² inner keyframes."""

    pair: tuple[int, int]
    events: tuple[Event, Event]
    s1: np.ndarray
    s2: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    targets: np.ndarray
    bulb_dV: np.ndarray
    force: np.ndarray
    pressures_Pa: dict
    x_peak: np.ndarray
    solves: int
    iterations: int

    def interp(self, arr: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``arr`` (a grid of this group) at levels (a, b) (n,): PCHIP along s1, then along s2."""
        n1, n2 = len(self.s1), len(self.s2)
        rows = PchipInterpolator(self.s1, arr.reshape(n1, -1), axis=0)(np.clip(a, 0.0, 1.0))
        out = pchip_rows(self.s2, rows.reshape(len(a), n2, -1), b)
        return out.reshape((len(a),) + arr.shape[2:])


@dataclass(frozen=True, eq=False)
class TruthSamples:
    """The truth at times ``t`` (n,) s (scenario clock): ``force`` (n, 3) N, ``pressures`` (n, M)
    Pa gauge of the actuated internal cavities ``cavity_names``, ``dV`` (n, cavities) m³ (the arms,
    then every internal cavity, actuated or measured), ``markers`` (n, k, 3) m, ``targets`` (n, t, 3) m displacement,
    ``pose`` of the marker rigid body relative to rest."""

    t: np.ndarray
    force: np.ndarray
    pressures: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    targets: np.ndarray
    pose: Pose6
    cavity_names: tuple[str, ...] = ("urethra",)

    @property
    def p_urethra(self) -> np.ndarray:
        """(n,) Pa, the urethra's gauge pressure (NaN without a urethra)."""
        if "urethra" not in self.cavity_names:
            return np.full(len(self.t), np.nan)
        return self.pressures[:, self.cavity_names.index("urethra")]


@dataclass(frozen=True, eq=False)
class Truth:
    """The solved truth of a scenario on ``model`` (the truth mesh): ``rest_markers`` (k, 3) m,
    ``marker_names``, ``target_names``, ``rest_volumes`` (cavities,) m³, ``events`` keyframes,
    ``solve_s`` wall time, ``config``."""

    scenario: Scenario
    model: PhantomModel
    marker_names: tuple[str, ...]
    target_names: tuple[str, ...]
    rest_markers: np.ndarray
    rest_volumes: np.ndarray
    events: tuple[EventTruth, ...]
    solve_s: float
    config: TruthConfig = field(default_factory=TruthConfig)
    groups: tuple[GroupTruth, ...] = ()
    cached: bool = False  # read from the truth cache (solve_s: the solve that wrote it)

    def sample(self, t) -> TruthSamples:
        """The truth at times ``t`` (s), interpolated in load level (see the module docstring)."""
        t = np.atleast_1d(np.asarray(t, float))
        n, k, nt = len(t), len(self.marker_names), len(self.target_names)
        cav = tuple(self.model.design.pressure_names)  # the loads; a measured cavity is read, in dV
        force = np.zeros((n, 3))
        p = np.zeros((n, len(cav)))
        dV = np.zeros((n, len(self.model.design.cavity_names)))  # the arms, then the internal cavities
        markers = np.broadcast_to(self.rest_markers, (n, k, 3)).copy()
        targets = np.zeros((n, nt, 3))
        for et in self.events:
            e = et.event
            sel = e.acting(t)
            if not sel.any():
                continue
            s = e.level(t[sel])
            force[sel] = s[:, None] * et.force
            if et.cavity is not None:
                p[sel, cav.index(et.cavity)] = s * et.p_Pa
            dV[sel] = et._interp(et.dV, s)
            markers[sel] = et._interp(et.markers, s)
            targets[sel] = et._interp(et.targets, s)
        for g in self.groups:  # both events acting: the group's two-parameter path
            e1, e2 = g.events
            sel = e1.acting(t) & e2.acting(t)
            if not sel.any():
                continue
            a, b = e1.level(t[sel]), e2.level(t[sel])
            force[sel] = 0.0
            p[sel] = 0.0
            for e, lv in ((e1, a), (e2, b)):
                if e.kind == "push":
                    force[sel] += lv[:, None] * np.asarray(e.force_N, float)
                else:
                    p[sel, cav.index(e.cavity)] += lv * e.p_kPa * 1e3
            dV[sel] = g.interp(g.dV, a, b)
            markers[sel] = g.interp(g.markers, a, b)
            targets[sel] = g.interp(g.targets, a, b)
        pose = pose_of_markers(self.rest_markers, markers)
        return TruthSamples(t, force, p, dV, markers, targets, pose, cav)

    def peak_event(self) -> EventTruth | GroupTruth:
        """The event (or group, at both peaks) whose peak moves the markers most (for the snapshot
        at peak load)."""
        def shift(x):
            peak = x.markers[-1, -1] if isinstance(x, GroupTruth) else x.markers[-1]
            return float(np.abs(peak - self.rest_markers).max())

        return max((*self.events, *self.groups), key=shift)

    def summary(self) -> dict:
        """Peak figures per event (mm, N, kPa, % bulb growth), JSON-able."""
        out = []
        cav = tuple(self.model.design.pressure_names)
        for et in self.events:
            # the BIP's figures as they were; another design's name the inflated cavity and its pressure
            p = (dict(p_urethra_kPa=round(et.p_urethra / 1e3, 3)) if cav == ("urethra",) else
                 dict(cavity=et.cavity, p_kPa=round(et.p_Pa / 1e3, 3)) if et.cavity else {})
            d = dict(kind=et.event.kind, start_s=et.event.start_s,
                     force_N=[round(float(f), 4) for f in et.force], **p,
                     peak_marker_shift_mm=round(float(np.linalg.norm(et.markers[-1] - self.rest_markers, axis=1).max()) * 1e3, 3),
                     peak_dV_mm3={c: round(float(v) * 1e9, 3) for c, v in zip(self.model.design.cavity_names,
                                                                                et.dV[-1])},
                     bulb_growth_percent=round(float(et.bulb_dV[-1] / self.model.bulb_volume()) * 100, 3),
                     keyframes=len(et.s) - 1, newton_iterations=et.iterations)
            for name, dsp in zip(self.target_names, et.targets[-1]):
                d[f"{name}_shift_mm"] = round(float(np.linalg.norm(dsp)) * 1e3, 3)
            if et.note:
                d["note"] = et.note
            if et.event.repeat > 1:
                d.update(repeat=et.event.repeat, period_s=et.event.period_s)
            out.append(d)
        laws = sorted({law.name for law in truth_laws(self.model, self.config.law).values()})
        extra = {"groups": [self._group_summary(g) for g in self.groups]} if self.groups else {}
        return {"truth_mesh": {"nodes": len(self.model.nodes), "tets": len(self.model.tets),
                               "mesh_size_mm": self.model.design.mesh.size_mm,
                               "element_order": self.model.element_order},
                "law": "+".join(laws), "patch_radius_mm": self.scenario.patch_radius_mm,
                "solve_s": round(self.solve_s, 2), **({"cached": True} if self.cached else {}), "events": out,
                **extra}

    def _group_summary(self, g: GroupTruth) -> dict:
        """A group's figures at both peaks (levels (1, 1)), JSON-able."""
        d = dict(events=[f"{e.kind}" + (f" {e.cavity}" if e.kind == "inflate" else "") + f" at {e.start_s:g} s"
                         for e in g.events],
                 force_N=[round(float(f), 4) for f in g.force],
                 p_kPa={c: round(v / 1e3, 3) for c, v in g.pressures_Pa.items()},
                 peak_marker_shift_mm=round(float(np.linalg.norm(g.markers[-1, -1] - self.rest_markers,
                                                                 axis=1).max()) * 1e3, 3),
                 peak_dV_mm3={c: round(float(v) * 1e9, 3) for c, v in zip(self.model.design.cavity_names,
                                                                            g.dV[-1, -1])},
                 bulb_growth_percent=round(float(g.bulb_dV[-1, -1] / self.model.bulb_volume()) * 100, 3),
                 keyframes=g.solves, newton_iterations=g.iterations)
        for name, dsp in zip(self.target_names, g.targets[-1, -1]):
            d[f"{name}_shift_mm"] = round(float(np.linalg.norm(dsp)) * 1e3, 3)
        return d
