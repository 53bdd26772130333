"""Tetrahedral FEM (linear 4-node or quadratic 10-node) with material laws per element: free
functions over numpy arrays (DESIGN.md §5, docs/architecture.md "FEM").

Build a :class:`FemModel` once (:func:`build_fem`, :func:`fem_from_phantom`), then evaluate
:func:`internal_force` / :func:`tangent_stiffness`, actuators (:func:`force_actuator`,
:func:`pressure_load`), sensors (:func:`cavity_volume`, :func:`cavity_volume_gradient`) and solve
equilibrium with :func:`solve_static`. SI units: m, N, Pa.

Material laws (:mod:`softphantom.fem.laws`, one file each) are small frozen objects —
:class:`Corotational` (alias :class:`Material`, the paper's co-rotational Hooke), :class:`NeoHookean`,
:class:`Yeoh` — each carrying its one numba point function (W, P, dP/dF at a quadrature point)
that serves the force, tangent and energy paths; :data:`DEFAULT_LAW` is the default material.

    >>> from softphantom.design import BIPDesign, build_model          # doctest: +SKIP
    >>> model = build_model(BIPDesign())                               # doctest: +SKIP
    >>> fem = fem_from_phantom(model, NeoHookean(142.3e3, 0.45, 1070))  # doctest: +SKIP
"""

from softphantom.fem.contact import DEFAULT_CONTACT_RADIUS_M, ContactPatch, outer_surface
from softphantom.fem.actuators import (
    point_weights,
    cavity_volume,
    cavity_volume_gradient,
    force_actuator,
    gravity_load,
    pressure_load,
    pressure_load_tangent,
)
from softphantom.fem.corotational import (
    ElementInversionError,
    cauchy_stress,
    corotated_stress,
    deformation_gradient,
    force_and_energy,
    internal_force,
    linear_internal_force,
    polar_rotation,
    strain_energy,
    tangent_stiffness,
    von_mises,
)
from softphantom.fem.material import (
    DEFAULT_LAW,
    ECOFLEX_00_50,
    ECOFLEX_00_50_YEOH,
    LAWS,
    Corotational,
    Law,
    Material,
    NeoHookean,
    Yeoh,
    law_from_spec,
)
from softphantom.fem.model import FemModel, build_fem, fem_from_phantom, laws_of_design
from softphantom.fem.probes import probe_matrix, tet_volumes
from softphantom.fem.solve import (
    SparseSolver,
    StaticSolution,
    available_solvers,
    free_tangent,
    have_pardiso,
    indefinite_method,
    solve_static,
)

__all__ = [
    "ContactPatch",
    "DEFAULT_CONTACT_RADIUS_M",
    "cauchy_stress",
    "outer_surface",
    "point_weights",
    "Corotational",
    "DEFAULT_LAW",
    "ECOFLEX_00_50",
    "ECOFLEX_00_50_YEOH",
    "LAWS",
    "Law",
    "NeoHookean",
    "Yeoh",
    "law_from_spec",
    "laws_of_design",
    "ElementInversionError",
    "FemModel",
    "Material",
    "SparseSolver",
    "StaticSolution",
    "available_solvers",
    "have_pardiso",
    "indefinite_method",
    "build_fem",
    "cavity_volume",
    "cavity_volume_gradient",
    "corotated_stress",
    "deformation_gradient",
    "fem_from_phantom",
    "force_actuator",
    "force_and_energy",
    "free_tangent",
    "gravity_load",
    "internal_force",
    "linear_internal_force",
    "polar_rotation",
    "probe_matrix",
    "pressure_load",
    "pressure_load_tangent",
    "solve_static",
    "strain_energy",
    "tangent_stiffness",
    "tet_volumes",
    "von_mises",
]
