"""Forward solves of the calibration: the phantom's equilibrium at one keyframe's loads for given
material scales, with the exact sensitivities the least squares needs.

At an equilibrium ``r(x; f, c) = f_int(x; c) − H f − p ∂Φ_u/∂x = 0`` the implicit function
theorem gives, with the tangent ``K = ∂r/∂x`` (one factorization):

* ``∂x/∂f = K⁻¹ H`` (3 columns);
* ``∂x/∂ln c_r = −K⁻¹ f_int,r(x)`` for the scale ``c_r`` of every modulus of region group ``r``:
  every law of :mod:`softphantom.fem` has a strain energy linear in its moduli, so the internal
  force of a group's elements is proportional to its scale;
* for a group whose law has a shape (its :attr:`~softphantom.fem.Law.ratios`, e.g. Yeoh's
  ``θ_i = C_i0 / C10``, ``C_i0 = c θ_i C10``): ``∂x/∂θ_i = −K⁻¹ ∂f_int/∂θ_i``, the internal force of
  the group's elements with every parameter zero but the ratio's column, ``c`` times the column it
  is a ratio of (the energy is linear in each column).

Readouts: arm-cavity volume changes (one per arm) and marker positions (k, 3). One task is a plain function
of picklable arguments (:func:`solve_keyframe`), so Dask ships it to any worker; each worker builds
the model from its directory once (:func:`_base`, a per-process cache keyed by path and contact).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.fem import (
    LAWS,
    Law,
    SparseSolver,
    cavity_volume,
    cavity_volume_gradient,
    fem_from_phantom,
    force_actuator,
    free_tangent,
    internal_force,
    probe_matrix,
    solve_static,
)
from softphantom.records.names import ARM_NAMES

#: Region groups whose stiffness the calibration can scale: the bulb, and the four arms together.
GROUPS = ("bulb", "arms")


def region_group(region: str) -> str:
    """The calibration group of a mesh region (``arm_*`` → ``arms``, other names themselves)."""
    return "arms" if region.startswith("arm_") else region


@dataclass(frozen=True)
class Base:
    """What a worker keeps per model: the phantom, the nominal FEM, the contact load matrix ``H``
    (3N, 3), the marker probe ``P`` (k, N), rest volumes and marker points, the tet masks of the
    groups."""

    model: object
    fem: object
    H: object
    P: object
    V0: np.ndarray
    rest_markers: np.ndarray
    group_tets: dict
    solver: object  # one SparseSolver per worker and model: the symbolic analysis is kept
    group_laws: dict  # group -> its one law with a shape (group_shapes)


#: The laws ``calibrate --law`` can fit a model under (:func:`design_with_law`): every registered law.
FIT_LAWS = tuple(LAWS)


def design_with_law(design, law: str | None):
    """``design`` with every material under ``law`` at its small-strain equivalent: the same E, ν
    and density (:meth:`~softphantom.fem.Law.from_small_strain`; Yeoh: C10 = μ/2, C20 = C30 = 0 —
    the decoupled neo-Hookean form, whose shape the calibration then fits). A material already under ``law``
    is kept as it is (a Yeoh material keeps its shape); a converted one is renamed
    ``<material>_<law>``. ``law`` None: ``design`` itself.

    Why: the compressible forms differ at finite strain with the same small-strain moduli — on the
    P2 12 mm nominal at 3 N a Yeoh phantom's expanding front arms change volume 6–10 % more than a
    neo-Hookean model's, a pattern only the per-arm gains could take (docs/calibration.md)."""
    from softphantom.design.params import MATERIAL_PRESETS, MaterialSpec
    from softphantom.fem.material import law_from_spec

    if law is None:
        return design
    if law not in FIT_LAWS:
        raise UserError(f"--law {law!r}: not a law the calibration can fit (have {', '.join(FIT_LAWS)})")
    specs = {m.name: m for m in design.materials}
    used = [MATERIAL_PRESETS[n] for n in dict.fromkeys(n for _, n in design.region_materials)
            if n not in specs and n in MATERIAL_PRESETS]  # a preset named without a [materials] table
    renamed, mats = {}, []
    for m in (*design.materials, *used):
        if m.law == law:
            mats.append(m)
            continue
        now = law_from_spec(m.law, dict(m.values), f"materials.{m.name}")
        vals = LAWS[law].from_small_strain(now.E_Pa, now.nu, now.density_kg_m3).design_values()
        renamed[m.name] = f"{m.name}_{law.replace('-', '_')}"
        mats.append(MaterialSpec(renamed[m.name], law, vals))
    return dataclasses.replace(design, materials=tuple(mats),
                               region_materials=tuple((r, renamed.get(n, n)) for r, n in design.region_materials))


@functools.lru_cache(maxsize=4)
def _base(model_dir: str, contact: tuple[float, float, float], radius_m: float, law: str | None = None) -> Base:
    from softphantom.design import load_model

    model = load_model(Path(model_dir))
    if law is not None:
        model = dataclasses.replace(model, design=design_with_law(model.design, law))
    fem = fem_from_phantom(model)
    pt = np.asarray(contact, float)
    # on a coarse mesh a small patch may hold no node: widen it to the 3 nearest surface nodes
    surf = np.unique(fem.boundary_faces)
    r3 = float(np.sort(np.linalg.norm(fem.nodes[surf] - pt, axis=1))[2]) * 1.001
    H = force_actuator(fem, pt, radius=max(radius_m, r3))
    names = list(model.markers)
    P = probe_matrix(fem, np.array([model.markers[k] for k in names]))
    x0 = fem.nodes
    V0 = np.array([cavity_volume(x0, fem.cavities[a]) for a in model.design.sensing_names])
    id_to_group = {rid: region_group(name) for name, rid in model.regions.items()}
    reg = np.asarray(model.tet_region)
    groups: dict[str, np.ndarray] = {}
    for rid, g in id_to_group.items():
        groups.setdefault(g, np.zeros(reg.size, bool))
        groups[g] |= reg == rid
    return Base(model, fem, H, P, V0, np.asarray(P @ x0), groups, SparseSolver("auto"), group_shapes(model))


def group_shapes(model) -> dict[str, Law]:
    """Group -> its law, for each group of :data:`GROUPS` whose regions all use one law that has a
    shape (:attr:`~softphantom.fem.Law.ratios`, e.g. Yeoh's C20/C10, C30/C10): what the calibration
    may fit besides the stiffness; other laws have none."""
    from softphantom.fem.model import laws_of_design

    laws = laws_of_design(model.design, model.regions)
    out = {}
    for g in GROUPS:
        mine = {laws[r] for r in model.regions if region_group(r) == g}
        if len(mine) == 1 and (law := next(iter(mine))).ratios:
            out[g] = law
    return out


def _group_elements(fem, group_tets, law: Law, g: str) -> np.ndarray:
    return group_tets[g] & (np.asarray(fem.law_id) == law.law_id)


def shaped_fem(fem, group_tets: dict[str, np.ndarray], group_laws: dict[str, Law], shape: dict[str, tuple]):
    """A new FemModel whose elements of each group of ``shape`` have their law's ratios at
    ``shape[group]`` (Yeoh: C20 = θ2 C10, C30 = θ3 C10). An invalid law (e.g. a Yeoh set that is not
    stable) raises :class:`SolverError`: a trial step there is rejected like one whose solve fails."""
    if not shape:
        return fem
    prm = np.array(fem.params, dtype=float)
    for g, values in shape.items():
        law = group_laws[g]
        try:
            law.with_ratios(values)
        except UserError as exc:
            shown = ", ".join(f"{r.name} = {v:.4g}" for r, v in zip(law.ratios, values))
            raise SolverError(f"{law.name} shape of {g}: {shown} gives an invalid law ({exc})") from None
        sel = _group_elements(fem, group_tets, law, g)
        for r, v in zip(law.ratios, values):
            prm[sel, r.column] = float(v) * prm[sel, r.of_column]
    return dataclasses.replace(fem, params=_frozen(prm))


def scaled_fem(fem, tet_scale: np.ndarray):
    """A new FemModel whose element moduli are multiplied by ``tet_scale`` (M,)."""
    s = np.asarray(tet_scale, float)
    kw = dict(mu=fem.mu * s, lam=fem.lam * s)
    if getattr(fem, "params", None) is not None:  # a law's parameter row: all moduli (Pa)
        kw["params"] = _frozen(np.asarray(fem.params) * s[:, None])
    return dataclasses.replace(fem, **kw)


def _frozen(a: np.ndarray) -> np.ndarray:
    """Read-only, as every FemModel array: the kernels then keep the one numba specialization they
    were compiled (or cached) for instead of compiling another mid-run (≈ 14 CPU-s a process)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def _tet_scale(base: Base, scales: dict[str, float]) -> np.ndarray:
    s = np.ones(len(base.fem.tets))
    for g, c in scales.items():
        if g not in base.group_tets:
            raise UserError(f"calibration: no region group {g!r} in the model (have {sorted(base.group_tets)})")
        if not (np.isfinite(c) and c > 0):
            raise UserError(f"calibration: stiffness scale of {g} must be > 0, got {c}")
        s[base.group_tets[g]] = c
    return s


@dataclass(frozen=True, eq=False)
class KeyframeSolution:
    """A keyframe's equilibrium: ``x`` (3N,) m, ``dV`` (arms,) m³ arm-cavity volume changes,
    ``markers`` (k, 3) m; sensitivities ``dV_df`` (arms, 3) m³/N, ``dV_dlnc`` (arms, G) m³,
    ``dM_df`` (k, 3, 3) m/N, ``dM_dlnc`` (k, 3, G) m (G = ``groups``); ``iterations`` Newton
    iterations; ``converged``; ``status``; ``shape_cols`` ((group, k), …) the ratios solved for
    (``k`` indexes the group's law's :attr:`~softphantom.fem.Law.ratios`), ``dV_dshape`` (arms, S) m³
    and ``dM_dshape`` (k, 3, S) m per unit ratio."""

    x: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    dV_df: np.ndarray
    dV_dlnc: np.ndarray
    dM_df: np.ndarray
    dM_dlnc: np.ndarray
    groups: tuple[str, ...]
    iterations: int
    converged: bool
    status: str
    shape_cols: tuple[tuple[str, int], ...] = ()
    dV_dshape: np.ndarray | None = None
    dM_dshape: np.ndarray | None = None


def keyframe_pressures(model, pressures_Pa) -> dict[str, float] | None:
    """The internal-cavity loads of a keyframe for :func:`~softphantom.fem.solve_static`: the
    nonzero ones of ``pressures_Pa`` (Pa; a mapping cavity name -> p naming every internal cavity
    of ``model`` (its layout's ``actuated``), or one number for
    a model with one, the BIP's urethra; 0 for none) in the model's load order; None if all are 0.

    >>> from softphantom.design import BIPDesign
    >>> from types import SimpleNamespace
    >>> bip = SimpleNamespace(layout=BIPDesign().channel_layout)
    >>> keyframe_pressures(bip, 5e3), keyframe_pressures(bip, {"urethra": 0.0}), keyframe_pressures(bip, 0.0)
    ({'urethra': 5000.0}, None, None)
    >>> keyframe_pressures(bip, {"tumour": 1e3})
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: keyframe pressures of tumour: the model's internal cavities are urethra
    """

    names = model.layout.actuated
    if isinstance(pressures_Pa, dict):
        if set(pressures_Pa) != set(names):
            raise UserError(f"keyframe pressures of {', '.join(pressures_Pa) or 'no cavity'}: the model's internal "
                            f"cavities are {', '.join(names) or 'none'}")
        given = {n: float(pressures_Pa[n]) for n in names}
    elif not pressures_Pa:
        given = {}
    elif len(names) == 1:
        given = {names[0]: float(pressures_Pa)}
    else:
        raise UserError(f"keyframe pressure {pressures_Pa} Pa: the model has internal cavities "
                        f"{', '.join(names) or 'none'}: name each")
    loads = {n: p for n, p in given.items() if p}
    return loads or None


def solve_keyframe(model_dir: str, contact: tuple[float, float, float], radius_m: float,
                   scales: dict[str, float], force_N, pressures_Pa: dict[str, float] | float,
                   x0: np.ndarray | None = None, min_load_step: float = 1.0 / 1024,
                   shape: dict[str, tuple[float, float]] | None = None, tol: float = 1e-9,
                   law: str | None = None) -> KeyframeSolution:
    """Equilibrium and sensitivities at force ``force_N`` (3,) on the contact patch and the
    internal cavities' pressures ``pressures_Pa`` (:func:`keyframe_pressures`: name -> Pa, or one
    number for a model of one internal cavity), with the moduli of each group in ``scales`` multiplied by its value
    (groups not named keep their nominal moduli), and the groups in ``shape`` given their law's
    ratios (:func:`shaped_fem`). ``x0`` warm start (3N,); ``min_load_step`` the
    smallest load increment the solve may cut to (:func:`~softphantom.fem.solve_static`) before it
    gives up with :class:`SolverError`. ``law``: every material under that law instead of the
    design's (:func:`design_with_law`)."""
    base = _base(str(model_dir), tuple(float(v) for v in contact), float(radius_m), law)
    groups = tuple(scales)
    shape = dict(shape or {})
    shape_cols = tuple((g, k) for g in shape for k in range(len(base.group_laws[g].ratios)))
    fem0 = shaped_fem(base.fem, base.group_tets, base.group_laws, shape)
    ts = _tet_scale(base, scales)
    fem = scaled_fem(fem0, ts)
    f = np.asarray(force_N, float)
    pressures = keyframe_pressures(base.model, pressures_Pa)
    solver = base.solver
    sol = solve_static(fem, base.H @ f, pressures=pressures, x0=x0, tol=tol, solver=solver,
                       min_load_step=min_load_step)
    if not sol.converged:
        shown = ", ".join(f"{n} {p / 1e3:.3g} kPa" for n, p in (pressures or {}).items()) or "no internal pressure"
        raise SolverError(f"keyframe at force {np.round(f, 3).tolist()} N, {shown}: {sol.status}")
    x = sol.x.reshape(-1)
    n = fem.n_dof
    free = fem.free_dofs
    K = free_tangent(fem, x, pressures)
    solver.factorize(K)
    G = len(groups)
    B = np.empty((fem.n_free, 3 + G + len(shape_cols)))
    B[:, :3] = base.H.toarray()[free] if hasattr(base.H, "toarray") else base.H[free]
    for j, g in enumerate(groups):
        only = np.where(base.group_tets[g], ts, 0.0)
        B[:, 3 + j] = -internal_force(scaled_fem(fem0, only), x)[free]
    for j, (g, k) in enumerate(shape_cols):  # ∂f_int/∂θ_k: only the ratio's column, c × its base column
        r = base.group_laws[g].ratios[k]
        prm = np.zeros_like(np.asarray(fem0.params, dtype=float))
        sel = _group_elements(fem0, base.group_tets, base.group_laws[g], g)
        prm[sel, r.column] = ts[sel] * np.asarray(fem0.params)[sel, r.of_column]
        B[:, 3 + G + j] = -internal_force(dataclasses.replace(fem0, params=_frozen(prm)), x)[free]
    U = np.zeros((n, B.shape[1]))
    U[free] = solver.solve(B)
    arms = base.model.design.sensing_names  # the volume channels: the arms, then the measured cavities
    dV = np.empty(len(arms))
    dV_d = np.empty((len(arms), B.shape[1]))
    for i, a in enumerate(arms):
        tri = fem.cavities[a]
        dV[i] = cavity_volume(x, tri) - base.V0[i]
        dV_d[i] = cavity_volume_gradient(x, tri, fem.n_nodes) @ U
    X = x.reshape(-1, 3)
    markers = np.asarray(base.P @ X)
    Uk = U.reshape(-1, 3, U.shape[1])  # (N, 3, cols)
    dM = np.einsum("kn,nic->kic", base.P.toarray() if hasattr(base.P, "toarray") else base.P, Uk)
    return KeyframeSolution(x, dV, markers, dV_d[:, :3], dV_d[:, 3:3 + G], dM[:, :, :3], dM[:, :, 3:3 + G],
                            groups, sol.iterations, True, sol.status, shape_cols, dV_d[:, 3 + G:], dM[:, :, 3 + G:])


def rest_markers(model_dir: str, contact, radius_m: float) -> np.ndarray:
    """The marker points as the mesh carries them at rest (k, 3) m."""
    return _base(str(model_dir), tuple(float(v) for v in contact), float(radius_m)).rest_markers
