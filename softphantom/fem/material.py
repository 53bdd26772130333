"""Linear-elastic (Hooke) materials for the co-rotational model."""

from __future__ import annotations

from dataclasses import dataclass

from softphantom.errors import UserError


@dataclass(frozen=True)
class Material:
    """Isotropic Hooke material: Young's modulus (Pa), Poisson ratio, density (kg/m³).

    >>> m = Material(E_Pa=3.0e3, nu=0.25, density_kg_m3=1000.0)
    >>> round(m.mu_Pa, 6), round(m.lambda_Pa, 6)
    (1200.0, 1200.0)
    """

    E_Pa: float
    nu: float
    density_kg_m3: float = 1000.0

    def __post_init__(self) -> None:
        if not self.E_Pa > 0:
            raise UserError(f"Material E_Pa must be > 0, got {self.E_Pa}")
        if not -1.0 < self.nu < 0.5:
            raise UserError(f"Material nu must lie in (-1, 0.5), got {self.nu}")
        if not self.density_kg_m3 >= 0:
            raise UserError(f"Material density_kg_m3 must be >= 0, got {self.density_kg_m3}")

    @property
    def mu_Pa(self) -> float:
        """Shear modulus μ = E / (2(1+ν))."""
        return self.E_Pa / (2.0 * (1.0 + self.nu))

    @property
    def lambda_Pa(self) -> float:
        """First Lamé constant λ = Eν / ((1+ν)(1−2ν))."""
        return self.E_Pa * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))


def _ecoflex_00_50() -> Material:
    # Smooth-On's datasheet gives the 100 % modulus: nominal stress 83 kPa at stretch 2 in uniaxial
    # tension. Incompressible neo-Hookean uniaxial nominal stress: P = μ(λ − λ⁻²), so at λ = 2
    # μ = 83 kPa / 1.75 = 47.4 kPa, and its small-strain Young's modulus is E = 3μ = 142 kPa.
    # We keep that uniaxial stiffness E and take ν = 0.45 (a compromise against locking of linear
    # tets, DESIGN.md §5), so the model's shear modulus is E / 2.9 = 49 kPa.
    mu = 83.0e3 / (2.0 - 2.0**-2)
    return Material(E_Pa=3.0 * mu, nu=0.45, density_kg_m3=1070.0)


ECOFLEX_00_50 = _ecoflex_00_50()
"""Ecoflex 00-50: E = 3μ = 142 kPa from the neo-Hookean fit μ = 83 kPa / 1.75 of the datasheet's
100 % modulus (nominal stress 83 kPa at stretch 2: P = μ(λ − λ⁻²)); ν = 0.45; 1070 kg/m³."""
