"""Co-rotational linear-tetrahedron FEM: free functions over numpy arrays (DESIGN.md §5).

Build a :class:`FemModel` once (:func:`build_fem`, :func:`fem_from_phantom`), then evaluate
:func:`internal_force` / :func:`tangent_stiffness`, actuators (:func:`force_actuator`,
:func:`pressure_load`), sensors (:func:`cavity_volume`, :func:`cavity_volume_gradient`) and solve
equilibrium with :func:`solve_static`. SI units: m, N, Pa.
"""

from softphantom.fem.actuators import (
    cavity_volume,
    cavity_volume_gradient,
    force_actuator,
    gravity_load,
    pressure_load,
    pressure_load_tangent,
)
from softphantom.fem.corotational import (
    ElementInversionError,
    corotated_stress,
    deformation_gradient,
    internal_force,
    linear_internal_force,
    polar_rotation,
    strain_energy,
    tangent_stiffness,
    von_mises,
)
from softphantom.fem.material import ECOFLEX_00_50, Material
from softphantom.fem.model import FemModel, build_fem, fem_from_phantom
from softphantom.fem.probes import probe_matrix, tet_volumes
from softphantom.fem.solve import (
    SparseSolver,
    StaticSolution,
    available_solvers,
    free_tangent,
    solve_static,
)

__all__ = [
    "ECOFLEX_00_50",
    "ElementInversionError",
    "FemModel",
    "Material",
    "SparseSolver",
    "StaticSolution",
    "available_solvers",
    "build_fem",
    "cavity_volume",
    "cavity_volume_gradient",
    "corotated_stress",
    "deformation_gradient",
    "fem_from_phantom",
    "force_actuator",
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
