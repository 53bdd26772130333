"""How well the four arm volumes see the loads: singular values of their sensitivity (DESIGN.md §6).

``J = ∂(arm cavity volumes, mm³)/∂(f_x, f_y, f_z in N, p_u in kPa)`` is the estimator's ``W``
(:class:`~softphantom.estimation.linearization.Linearization`) in those units. Its columns carry
different units, so each is scaled by the range of its input over the load envelope (the
atlas's: f_x, f_z ±2 N, f_y −1…5.2 N, p_u −2…40 kPa): a singular value of ``J·diag(range)`` is
then the volume change (mm³, 2-norm over the four arms) that the load step of one envelope's
length along its right singular vector makes. The smallest one is how much the sensors see of the
load direction they see least; that direction, as a load step (N, N, N, kPa), is ``weakest``.

Two blocks: all four inputs (``sv_mm3``), and the force alone (``sv_force_mm3``, the three force
columns). The urethra pressure is measured by its own transducer (an equality of the estimator's
QP), so the force block is what decides whether the force can be estimated; on the default design
the four-input block's weakest direction is the urethra pressure itself (the arms barely feel it).

Verdicts, on the force block (:func:`layout_problem`, :func:`layout_warnings`):

* refused (rank-deficient): at rest, the smallest force singular value is below
  :data:`REFUSE_RATIO` of the largest. A layout with every arm and the contact point in one mirror
  plane of the bulb sees the force normal to that plane not at all (each volume is an even
  function of it); a mesh, never exactly symmetric, leaves 0.011–0.055 of the largest there
  (measured on 6–12 mm meshes), while tilting one arm pair 10° out of that plane already gives
  0.30–0.35 and the default design 0.58–0.64. Over the envelope the ratio is not a criterion: on
  the default design it is 0.03–0.06 at f_y = 5.2 N, where the back arm pair steps and the
  largest singular value is 10–25 times its value at rest.
* warned: anywhere (rest or loaded), the smallest force singular value is below
  :data:`WARN_COUNTS` counts of the pressure sensors: that direction is then resolved to no better
  than a tenth of the envelope. One count is the cavity volume change of the sensing chain's
  worst-case resolution, 11.3 Pa cavity-equivalent (DESIGN.md §3, eq. 2 with the default 12 m ×
  1.2 mm tube and OSR 100): ``δV = V_cavity · δp / P0`` = 486 mm³ · 11.3 Pa / 101 325 Pa =
  0.054 mm³ (:func:`count_volume_mm3`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from softphantom.errors import DesignError, SolverError, UserError

REFUSE_RATIO = 0.1
WARN_COUNTS = 10.0
LOAD_NAMES = ("f_x", "f_y", "f_z", "p_u")
LOAD_UNITS = ("N", "N", "N", "kPa")
_PER_REPORTED = np.array([1.0, 1.0, 1.0, 1e3])  # λ's SI units (N, N, N, Pa) per reported unit (N, N, N, kPa)


def _per_reported(n: int) -> np.ndarray:
    """:data:`_PER_REPORTED` for ``n`` loads (the force, then n − 3 pressures in kPa)."""
    return np.array([1.0, 1.0, 1.0] + [1e3] * (n - 3))


def _for_pressures(v4: np.ndarray, m: int) -> np.ndarray:
    """A 4-load vector of the BIP (force, urethra) widened to M pressures, each as the urethra's."""
    v4 = np.asarray(v4, float)
    return v4 if m == 1 else np.concatenate([v4[:3], np.full(m, v4[3])])


def count_volume_mm3(cavity_volumes_mm3: Sequence[float]) -> float:
    """mm³: the largest over the arms of the cavity volume change one count of the sensing chain
    reads (the budget's worst-case resolution, cavity-equivalent, times ``V_cavity / P0``).

    >>> round(count_volume_mm3([514.0, 514.0, 486.0, 486.0]), 4)
    0.0543
    """
    from softphantom.sensing.budget import BudgetParams, budget

    vols = tuple(float(v) * 1e-9 for v in cavity_volumes_mm3)
    p = BudgetParams(cavity_volumes_m3=vols, group_names=tuple(str(i) for i in range(len(vols))))
    return max(r.v_cavity_mm3 * r.resolution_Pa_paper / p.p0_Pa for r in budget(p))


def load_names(pressure_names=("urethra",)) -> tuple[str, ...]:
    """The loads' names in the report: the force's three, then ``p_<cavity>`` per internal
    cavity (the BIP's urethra: ``p_u``).

    >>> load_names(), load_names(("collecting_system",))[3]
    (('f_x', 'f_y', 'f_z', 'p_u'), 'p_collecting_system')
    """
    pressure_names = tuple(pressure_names)
    if pressure_names == ("urethra",):
        return LOAD_NAMES
    return (*LOAD_NAMES[:3], *(f"p_{c}" for c in pressure_names))


def load_text(step: np.ndarray, pressure_names=None) -> str:
    """A load step (N, N, N, kPa; or the three forces) as text, the pressures named by
    ``pressure_names`` (default: the urethra for one, ``p_1…p_M`` for several).

    >>> load_text(np.array([0.0, -1.25, 4.0, 0.5]))
    'f_x +0.00 N, f_y -1.25 N, f_z +4.00 N, p_u +0.50 kPa'
    >>> load_text(np.array([0.0, 0.0, 1.0, 2.0, 3.0]), ("tumour", "breathing"))
    'f_x +0.00 N, f_y +0.00 N, f_z +1.00 N, p_tumour +2.00 kPa, p_breathing +3.00 kPa'
    """
    step = np.asarray(step, float)
    m = len(step) - 3
    if pressure_names is None:
        pressure_names = ("urethra",) if m <= 1 else tuple(str(i + 1) for i in range(m))
    names = load_names(pressure_names)
    units = (*LOAD_UNITS[:3], *["kPa"] * max(m, 0))
    return ", ".join(f"{n} {v:+.2f} {u}" for n, u, v in zip(names, units, step))


def _scaled_svd(J: np.ndarray, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Singular values of ``J·diag(ranges)``, the weakest direction as a load step (the right
    singular vector times the ranges, its largest component positive) and the condition number."""
    _, s, Vt = np.linalg.svd(J * ranges)
    v = Vt[-1] * ranges
    v = v if v[np.argmax(np.abs(v))] >= 0 else -v
    return s, v, float(s[0] / s[-1]) if s[-1] > 0 else np.inf


@dataclass(frozen=True, eq=False)
class ObservedState:
    """The sensitivity at one load state.

    ``lam`` (4,) the loads (N, N, N, kPa); ``J`` (n_arms, 4) mm³/N (force columns) and mm³/kPa
    (urethra pressure), rows in the design's arm (sensor) order; ``sv_mm3`` (4,) the
    singular values over the envelope (see the module docstring), ``weakest`` (4,) the load step
    (N, N, N, kPa) of the smallest, ``cond`` their ratio; ``sv_force_mm3`` (3,), ``weakest_force``
    (3,) N and ``cond_force`` the same for the force columns alone."""

    lam: np.ndarray
    J: np.ndarray
    sv_mm3: np.ndarray
    weakest: np.ndarray
    cond: float
    sv_force_mm3: np.ndarray
    weakest_force: np.ndarray
    cond_force: float


def observed_state(lin, ranges: np.ndarray) -> ObservedState:
    """The :class:`ObservedState` of a :class:`~softphantom.estimation.linearization.Linearization`
    (its ``W``, m³/N and m³/Pa) with the inputs' ``ranges`` (4,) N, N, N, kPa."""
    ranges = np.asarray(ranges, float)
    per = _per_reported(len(lin.lam))
    J = np.asarray(lin.W, float) * 1e9 * per
    s, v, c = _scaled_svd(J, ranges)
    sf, vf, cf = _scaled_svd(J[:, :3], ranges[:3])
    return ObservedState(np.asarray(lin.lam, float) / per, J, s, v, c, sf, vf, cf)


@dataclass(frozen=True, eq=False)
class Observability:
    """The sensitivities at rest and at loaded states over the envelope (:func:`observability`).

    ``ranges`` (4,) N, N, N, kPa: the envelope's ranges that scale the columns; ``rest`` and
    ``loaded`` :class:`ObservedState`; ``failed``: the loads (N, N, N, kPa) whose equilibrium did
    not converge, each with the solver's reason; ``count_mm3``: one count of the sensors
    (:func:`count_volume_mm3`); ``pressure_names`` the internal cavities whose pressures are the
    loads after the force; ``measured_names`` the measured cavities among the rows (after the arms)."""

    ranges: np.ndarray
    rest: ObservedState
    loaded: tuple[ObservedState, ...]
    failed: tuple[tuple[np.ndarray, str], ...]
    count_mm3: float
    pressure_names: tuple[str, ...] = ("urethra",)
    measured_names: tuple[str, ...] = ()

    def text(self, step) -> str:
        """:func:`load_text` with this design's pressure names."""
        return load_text(step, self.pressure_names)

    @property
    def rows(self) -> str:
        """What the rows are, for the report's sentences."""
        return "arm volumes" if not self.measured_names else \
            f"volume channels (the arms and the measured {', '.join(self.measured_names)})"

    @property
    def states(self) -> tuple[ObservedState, ...]:
        return (self.rest, *self.loaded)

    @property
    def weakest_state(self) -> ObservedState:
        """The state whose smallest force singular value is the smallest."""
        return min(self.states, key=lambda s: s.sv_force_mm3[-1])


def envelope_ranges(acfg=None, m: int = 1) -> np.ndarray:
    """(3 + m,) N, N, N, kPa: the ranges of the loads over the envelope ``acfg`` (an
    :class:`~softphantom.estimation.atlas.config.AtlasConfig`, default the default envelope; each of
    ``m`` internal cavities over the urethra's range).

    >>> envelope_ranges().round(3).tolist()
    [4.0, 6.2, 4.0, 42.0]
    """
    from softphantom.estimation.atlas.config import AtlasConfig

    acfg = acfg or AtlasConfig()
    return _for_pressures((acfg.upper - acfg.lower) / _PER_REPORTED, m)


def envelope_loads(acfg=None, m: int = 1) -> list[np.ndarray]:
    """The loaded states (N, N, N, Pa): each load at either end of the envelope's range, the
    others zero (the centres of the envelope's faces seen from rest); ``acfg`` an
    :class:`~softphantom.estimation.atlas.config.AtlasConfig` (default: the default envelope).

    >>> [lam.tolist() for lam in envelope_loads()][:2]
    [[-2.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]]
    """
    from softphantom.estimation.atlas.config import AtlasConfig

    acfg = acfg or AtlasConfig()
    lower, upper = _for_pressures(acfg.lower, m), _for_pressures(acfg.upper, m)
    out = []
    for i in range(3 + m):
        for v in (lower[i], upper[i]):
            lam = np.zeros(3 + m)
            lam[i] = v
            out.append(lam)
    return out


def observability(model, forward=None, acfg=None, loaded: bool = True) -> Observability:
    """The :class:`Observability` of ``model`` (a :class:`~softphantom.design.model.PhantomModel`)
    at rest and, with ``loaded``, at :func:`envelope_loads` (converged equilibria from rest, their
    exact linearizations); ``forward`` a :class:`~softphantom.estimation.forward.ForwardModel`
    of it (default: the estimator's, on-centre contact, 4 mm patch); ``acfg`` the envelope
    (default: the atlas's for the model's element order)."""
    from softphantom.estimation.atlas.config import default_atlas_config
    from softphantom.estimation.forward import ForwardModel

    fm = forward if forward is not None else ForwardModel(model)
    acfg = acfg or default_atlas_config(fm.fem.order)
    m = len(fm.eq.pressure_names)
    ranges = envelope_ranges(acfg, m)
    states, failed = [], []
    for lam in envelope_loads(acfg, m) if loaded else ():
        try:
            states.append(observed_state(fm.solve(lam), ranges))
        except SolverError as exc:
            failed.append((lam / _per_reported(3 + m), str(exc).splitlines()[0]))
    count = count_volume_mm3(list(model.design.sensing_volumes_mm3()))  # the volume channels (W's rows)
    measured = tuple(n for n in fm.eq.arm_names if n in getattr(model.design, "measured_cavity_names", ()))
    return Observability(ranges, observed_state(fm.rest, ranges), tuple(states), tuple(failed), count,
                         tuple(fm.eq.pressure_names), measured)


def observability_at_rest(model, W, acfg=None) -> Observability:
    """The :class:`Observability` of ``model`` at rest from its rest sensitivity ``W`` (volume
    channels × loads, m³/N and m³/Pa; what :func:`observability` solves for): for a model whose
    ``W`` ships with it (:data:`REST_FILE`), no solve."""
    from types import SimpleNamespace

    from softphantom.estimation.atlas.config import default_atlas_config

    design = model.design
    acfg = acfg or default_atlas_config(int(getattr(model, "element_order", 1)))
    names = tuple(design.pressure_names)
    W = np.asarray(W, float)
    if W.shape != (len(design.sensing_names), 3 + len(names)):
        raise UserError(f"rest sensitivity: shape {W.shape}, the model has {len(design.sensing_names)} volume channels "
                        f"and {3 + len(names)} loads")
    ranges = envelope_ranges(acfg, len(names))
    rest = observed_state(SimpleNamespace(W=W, lam=np.zeros(3 + len(names))), ranges)
    count = count_volume_mm3(list(design.sensing_volumes_mm3()))
    return Observability(ranges, rest, (), (), count, names, tuple(design.measured_cavity_names))


# the rest sensitivity a shipped model carries (its model directory): `design` reads it, no solve
REST_FILE = "observability.json"


def shipped_rest_W(model_dir) -> np.ndarray | None:
    """The rest sensitivity W (m³/N, m³/Pa) stored in a (shipped) model directory, or None."""
    import json
    from pathlib import Path

    f = Path(model_dir) / REST_FILE
    if not f.is_file():
        return None
    return np.array(json.loads(f.read_text())["W_rest_m3_per_N_Pa"], float)


def layout_problem(obs: Observability) -> str:
    """Why the arm layout is refused ('' if it is not): the force block is rank-deficient at rest
    (smallest singular value below :data:`REFUSE_RATIO` of the largest). One line naming ``arms``."""
    r = obs.rest
    ratio = r.sv_force_mm3[-1] / r.sv_force_mm3[0]
    if ratio >= REFUSE_RATIO:
        return ""
    return (f"arms: the layout cannot see a force step ({obs.text(r.weakest_force)}) at rest: it changes the "
            f"{obs.rows} by {r.sv_force_mm3[-1]:.3g} mm³, {ratio:.3f} of the best-seen direction (refused below "
            f"{REFUSE_RATIO:g}); e.g. move an arm out of the plane of the others")


def layout_warnings(obs: Observability) -> list[str]:
    """One line per concern: the weakest force direction below :data:`WARN_COUNTS` counts, loads
    that did not converge."""
    lines = []
    w = obs.weakest_state
    counts = w.sv_force_mm3[-1] / obs.count_mm3
    if counts < WARN_COUNTS:
        at = "at rest" if w is obs.rest else f"at {obs.text(w.lam)}"
        lines.append(f"arms: the force step {obs.text(w.weakest_force)} {at} changes the {obs.rows} by "
                     f"{w.sv_force_mm3[-1]:.3g} mm³, {counts:.1f} counts of {obs.count_mm3:.3g} mm³ (warned below "
                     f"{WARN_COUNTS:g}): that direction is poorly observable")
    for lam, why in obs.failed:
        lines.append(f"observability: no equilibrium at {obs.text(lam)} ({why})")
    return lines


def check_layout(obs: Observability, force: bool = False) -> list[str]:
    """Raise :class:`~softphantom.errors.DesignError` for a refused layout (unless ``force``: then
    its reason is the first warning); return the warnings."""
    problem = layout_problem(obs)
    if problem and not force:
        raise DesignError(problem)
    return ([problem] if problem else []) + layout_warnings(obs)


def observability_md(obs: Observability) -> str:
    """The design report's section: the singular values at rest and over the envelope (min, max
    per column), the weakest directions, the verdict's figures."""
    def row(label: str, sv: np.ndarray, svf: np.ndarray, c: float, cf: float) -> str:
        cells = [f"{v:.3g}" for v in (*sv, c, *svf, cf)]
        return f"| {label} | " + " | ".join(cells) + " |"

    states = obs.states
    sv = np.array([s.sv_mm3 for s in states])
    svf = np.array([s.sv_force_mm3 for s in states])
    cond = np.array([s.cond for s in states])
    condf = np.array([s.cond_force for s in states])
    r = obs.rest
    w = obs.weakest_state
    names = load_names(obs.pressure_names)
    units = (*LOAD_UNITS[:3], *["kPa"] * len(obs.pressure_names))
    env = ", ".join(f"{n} {x:g} {u}" for n, x, u in zip(names, obs.ranges, units))
    k = len(r.sv_mm3)  # min(rows, loads)
    bip = obs.pressure_names == ("urethra",)
    m = len(obs.pressure_names)
    pressures = ("urethra pressure" if bip else f"the pressure of {obs.pressure_names[0]}" if m == 1 else
                 f"the pressures of {', '.join(obs.pressure_names)}" if m else "no pressure")
    lines = [
        "## Observability",
        "",
        f"Singular values of the sensitivity of the {obs.rows} to the loads, each input scaled by its range over "
        f"the load envelope ({env}): the volume change (mm³) of a load step one envelope long. "
        f"`sv1..{k}`: force and {pressures}; `force_sv1..3`: the force alone"
        + (f" (the {'urethra pressure is' if bip else 'pressure is' if m == 1 else 'pressures are'} measured)."
           if m else "."),
        "",
        "| state | " + " | ".join(f"sv{i + 1}_mm3" for i in range(k))
        + " | cond | force_sv1_mm3 | force_sv2_mm3 | force_sv3_mm3 | force_cond |",
        "| --- | " + " | ".join(["---:"] * (k + 5)) + " |",
        row("rest", r.sv_mm3, r.sv_force_mm3, r.cond, r.cond_force),
    ]
    if obs.loaded:
        lines += [row("envelope min", sv.min(0), svf.min(0), cond.min(), condf.min()),
                  row("envelope max", sv.max(0), svf.max(0), cond.max(), condf.max())]
    lines += [
        "",
        f"- weakest direction at rest (all inputs): {obs.text(r.weakest)}",
        f"- weakest force direction at rest: {obs.text(r.weakest_force)} "
        f"({r.sv_force_mm3[-1] / r.sv_force_mm3[0]:.3f} of the best-seen; refused below {REFUSE_RATIO:g})",
        f"- weakest force direction over the envelope: {obs.text(w.weakest_force)} at "
        f"{'rest' if w is r else obs.text(w.lam)}: {w.sv_force_mm3[-1]:.3g} mm³ = "
        f"{w.sv_force_mm3[-1] / obs.count_mm3:.0f} counts of {obs.count_mm3:.3g} mm³ (warned below {WARN_COUNTS:g})",
    ]
    if obs.loaded:
        lines.append(f"- envelope: rest and {len(obs.loaded)} loaded states, each load at either end of its range "
                     "and the others zero (min and max per column)"
                     + (f"; {len(obs.failed)} more did not converge" if obs.failed else ""))
    return "\n".join(lines + [""])
