"""What every material law is: :class:`Law`, a frozen value object carrying its parameters (SI, the
unit in each name), their validation, its small-strain moduli, and its numba point function — the
strain energy density, its gradient (first Piola–Kirchhoff stress) and its Hessian (tangent) at
one deformation gradient, the one function the FEM's force, energy and tangent kernels inline.

The point function of a law, ``point(prm, e, F, P, D, need, s0, …, s9) -> W``: from F (3,3) and row
``e`` of the parameter array ``prm`` (the rows of :meth:`Law.params`), W (J/m³); P (3,3) if
``need >= 1``; D (9,9) = dP/dF if ``need >= 2``, row-major over (i, j): ``D[3i+j, 3k+l] =
∂P_ij/∂F_kl`` (``need == 3``: the law's approximate tangent, where it has one). ``s0``..``s9``:
(3,3) scratch (passed one by one and inlined: no per-call tuple or view). Decorate it with
:data:`point_function`.

Contract the FEM and the calibration rely on (checked for every registered law by
tests/test_fem_law_registry.py): det F > 0 at every call; P = ∂W/∂F and D = ∂P/∂F; W(R F) = W(F)
for rotations R; the parameter row holds moduli (Pa) in which W is linear (a stiffness factor c
multiplies the row and W), and it is affine in the law's :attr:`Law.ratios`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, fields, replace
from typing import ClassVar

import numpy as np

from softphantom.errors import DesignError, UserError
from softphantom.fem._numba import njit

N_PARAMS = 4  # columns of the per-element parameter array
N_WORK = 10  # (3,3) scratch matrices a point function may use

#: The decorator of a point function: compiled where it is inlined (into the cached element loops).
point_function = njit(fastmath=False, nogil=True, inline="always")


def check(cond: bool, field: str, value: float, limit: str) -> None:
    """Raise the one-line :class:`UserError` ``"<field> = <value> must be <limit>"`` unless ``cond``."""
    if not cond:
        raise UserError(f"{field} = {value:.6g} must be {limit}")


@dataclass(frozen=True)
class Ratio:
    """A dimensionless ratio of two of a law's moduli, ``field / of`` (e.g. Yeoh's C20/C10): the
    shape of the law at a given stiffness, which the calibration may fit around the design's value
    with the prior spread ``prior_sd``. ``name`` is its parameter name without group (``C20_C10``);
    ``column`` and ``of_column`` are the two moduli's columns in the parameter row
    (``row[column] = ratio · row[of_column]``)."""

    name: str
    field: str
    of: str
    column: int
    of_column: int
    prior_sd: float


@dataclass(frozen=True)
class Law:
    """Base of the laws. A subclass is a frozen dataclass of its parameters (SI, unit in the name:
    ``E_Pa``, ``nu``, ``density_kg_m3``, …) that sets ``name`` (the design file's ``law = ...``),
    ``point`` (its point function, see the module docstring), implements :meth:`params`,
    :attr:`mu_Pa`, :attr:`lambda_Pa`, ``E_Pa``, ``nu``, ``density_kg_m3`` (fields or properties)
    and :meth:`from_small_strain`, validates in
    ``__post_init__`` (a one-line :class:`UserError` naming the field), and may list ``ratios``.
    Registered in :data:`softphantom.fem.laws.REGISTRY`, which sets ``law_id``."""

    name: ClassVar[str]
    point: ClassVar[object]
    law_id: ClassVar[int] = -1
    ratios: ClassVar[tuple[Ratio, ...]] = ()

    # --- what each law provides ------------------------------------------------------------------
    def params(self) -> np.ndarray:
        """The row of ``N_PARAMS`` moduli (Pa) the point function reads."""
        raise NotImplementedError

    @property
    def mu_Pa(self) -> float:
        """Small-strain shear modulus."""
        raise NotImplementedError

    @property
    def lambda_Pa(self) -> float:
        """Small-strain first Lamé constant."""
        raise NotImplementedError

    @classmethod
    def from_small_strain(cls, E_Pa: float, nu: float, density_kg_m3: float) -> Law:
        """The law with small-strain Young's modulus ``E_Pa`` and Poisson ratio ``nu`` (its other
        parameters at their neutral values)."""
        raise NotImplementedError

    # --- common to every law -------------------------------------------------------------------
    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The parameters (SI names), in order."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def design_keys(cls) -> tuple[tuple[str, bool], ...]:
        """The design file's keys (``_Pa`` fields in kPa: ``E_kPa``) and whether each is required."""
        return tuple((design_key(f.name), f.default is MISSING and f.default_factory is MISSING)
                     for f in fields(cls))

    @classmethod
    def from_design(cls, values: Mapping[str, float], where: str) -> Law:
        """The law of a design-file material: ``values`` in the units of their keys (``E_kPa``, ``nu``,
        …). Errors are one-line :class:`DesignError` naming ``where`` and the field in the file's unit."""
        keys = cls.design_keys()
        names = [k for k, _ in keys]
        for k in values:
            if k not in names:
                raise DesignError(f"{where}.{k}: not a parameter of law {cls.name!r} (its fields: {', '.join(names)})")
        required = [k for k, req in keys if req]
        for k in required:
            if k not in values:
                raise DesignError(f"{where}.{k}: missing (law {cls.name!r} needs {', '.join(required)})")
        si = {}
        for k, v in values.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise DesignError(f"{where}.{k} = {v!r}: expected a finite number")
            si[k.replace("_kPa", "_Pa")] = float(v) * (1e3 if k.endswith("_kPa") else 1.0)
        try:
            return cls(**si)
        except UserError as exc:
            # name the field in the file's units: "E_Pa = -1000 must be > 0" -> "materials.x.E_kPa = -1 ..."
            msg = str(exc)
            field = msg.split(" ", 1)[0]
            if field.endswith("_Pa") and field in si:
                kfield = design_key(field)
                rest = msg.split(" must ", 1)[1] if " must " in msg else msg
                raise DesignError(f"{where}.{kfield} = {values[kfield]:.6g} must {rest}") from None
            raise DesignError(f"{where}.{msg}") from None

    def design_values(self) -> tuple[tuple[str, float], ...]:
        """The parameters as a design file writes them (``(key, value)`` in the key's unit)."""
        return tuple((design_key(n), getattr(self, n) / (1e3 if n.endswith("_Pa") else 1.0))
                     for n in self.field_names())

    def scaled(self, factor: float) -> Law:
        """This law with every modulus (``_Pa`` field) multiplied by ``factor`` (W scales with it)."""
        return replace(self, **{n: getattr(self, n) * factor for n in self.field_names() if n.endswith("_Pa")})

    def ratio_values(self) -> tuple[float, ...]:
        """The current value of each of :attr:`ratios`."""
        return tuple(getattr(self, r.field) / getattr(self, r.of) for r in self.ratios)

    def with_ratios(self, values) -> Law:
        """This law with ``ratios[i].field = values[i] · ratios[i].of`` (a :class:`UserError` if
        that makes the law invalid)."""
        return replace(self, **{r.field: float(v) * getattr(self, r.of) for r, v in zip(self.ratios, values)})

    @classmethod
    def feasible_ratios(cls, values, free) -> tuple[float, ...]:
        """``values`` of :attr:`ratios` moved (only where ``free``) into the set where the law is
        valid: how a calibration step that left it is projected back. Default: unchanged."""
        return tuple(values)

    # --- FElupe-style evaluation from Python (the compiled point function) -----------------------
    def energy(self, F) -> float:
        """Strain energy density W (J/m³) at the deformation gradient ``F`` (3,3)."""
        return self.evaluate(F, 0)[0]

    def gradient(self, F) -> np.ndarray:
        """First Piola–Kirchhoff stress P = ∂W/∂F (3,3) Pa."""
        return self.evaluate(F, 1)[1]

    def hessian(self, F) -> np.ndarray:
        """Tangent ∂P/∂F (9,9) Pa, row-major over (i, j) and (k, l)."""
        return self.evaluate(F, 2)[2]

    def evaluate(self, F, need: int = 2) -> tuple[float, np.ndarray, np.ndarray]:
        """(W, P, D) at ``F`` (``need`` as the point function's): the law's own point function,
        the one the element kernels inline."""
        P, D = np.zeros((3, 3)), np.zeros((9, 9))
        prm = np.zeros((1, N_PARAMS))
        row = np.asarray(self.params(), float)
        prm[0, :row.size] = row
        work = [np.empty((3, 3)) for _ in range(N_WORK)]
        W = type(self).point(prm, 0, np.ascontiguousarray(F, dtype=np.float64), P, D, int(need), *work)
        return float(W), P, D


def design_key(name: str) -> str:
    """The design file's key of a parameter: ``_Pa`` fields in kPa (``C10_Pa`` -> ``C10_kPa``)."""
    return name[:-3] + "_kPa" if name.endswith("_Pa") else name


@dataclass(frozen=True)
class Isotropic(Law):
    """A law given by Young's modulus (Pa), Poisson ratio and density, whose parameter row is
    (μ, λ, 0, 0) Pa."""

    E_Pa: float
    nu: float
    density_kg_m3: float = 1000.0

    def __post_init__(self) -> None:
        check(math.isfinite(self.E_Pa) and self.E_Pa > 0, "E_Pa", self.E_Pa, "> 0")
        check(-1.0 < self.nu < 0.5, "nu", self.nu, "in (-1, 0.5) (compressible)")
        check(self.density_kg_m3 >= 0, "density_kg_m3", self.density_kg_m3, ">= 0")

    @property
    def mu_Pa(self) -> float:
        """Small-strain shear modulus μ = E / (2(1+ν))."""
        return self.E_Pa / (2.0 * (1.0 + self.nu))

    @property
    def lambda_Pa(self) -> float:
        """Small-strain first Lamé constant λ = Eν / ((1+ν)(1−2ν))."""
        return self.E_Pa * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    def params(self) -> np.ndarray:
        """(μ, λ, 0, 0) Pa."""
        return np.array([self.mu_Pa, self.lambda_Pa, 0.0, 0.0])

    @classmethod
    def from_small_strain(cls, E_Pa: float, nu: float, density_kg_m3: float) -> Law:
        return cls(E_Pa=E_Pa, nu=nu, density_kg_m3=density_kg_m3)


@point_function
def det_inv(F, Finv):
    """det F, and F⁻¹ into Finv (if det != 0)."""
    c00 = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    c01 = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    c02 = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    det = F[0, 0] * c00 + F[0, 1] * c01 + F[0, 2] * c02
    if det == 0.0:
        return det
    idet = 1.0 / det
    Finv[0, 0] = c00 * idet
    Finv[1, 0] = c01 * idet
    Finv[2, 0] = c02 * idet
    Finv[0, 1] = (F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]) * idet
    Finv[1, 1] = (F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]) * idet
    Finv[2, 1] = (F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]) * idet
    Finv[0, 2] = (F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]) * idet
    Finv[1, 2] = (F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]) * idet
    Finv[2, 2] = (F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) * idet
    return det
