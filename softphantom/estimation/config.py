"""Configuration of the estimator (a frozen value object; SI units)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.qp import QP_SOLVERS
from softphantom.fem.contact import DEFAULT_CONTACT_RADIUS_M

MODES = ("sync", "async")


def _vec3(name: str, v) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise UserError(f"{name}: expected 3 numbers, got {v!r}") from None
    if np.any(np.isnan(a)):
        raise UserError(f"{name}: NaN in {v!r}")
    return tuple(float(x) for x in a)


@dataclass(frozen=True)
class EstimatorConfig:
    """How the estimator runs.

    ``contact``: name of a ``PhantomModel.p_ext`` point (``"on-centre"``, ``"off-centre"``, or one
    of the design's ``[contacts]``) or an (x, y, z) point in m; ``contact_radius_m`` spreads the
    force as a uniform traction over the outer surface within that radius (:class:`~softphantom.fem.ContactPatch`, default
    :data:`~softphantom.fem.DEFAULT_CONTACT_RADIUS_M` = 4 mm, the same patch as ``simulate`` and the
    virtual truth; 0: a point load on the element containing the point, as the paper). ``force_min_N``/``force_max_N``:
    bounds on each force component (box; sign constraints are a zero bound), default ±10 N.
    ``qp_solver``: ``"daqp"`` or ``"quadprog"``. ``mode``: ``"sync"`` (equilibrium refreshed inside
    :meth:`~softphantom.estimation.Estimator.step`, deterministic) or ``"async"`` (a background
    thread refreshes it; the step only does the QP and the first-order update). In sync mode a
    refresh happens when the estimate has moved more than ``relinearize_N`` / ``relinearize_Pa``
    from the linearization point, or ``refresh_every`` samples after the last one (if it moved at
    all, beyond ``deadband_N``/``deadband_Pa``). Each refresh solves the equilibrium at the estimate,
but at most ``trust_N``/``trust_Pa`` times a scale from the previous linearization point (a trust
region against jumping into another basin of this non-linear map; off-centre pushes have a
spurious least-squares minimum). The scale (adaptive when ``trust_max_scale`` > 1, the
default: 8, measured to cut the real-time error on a 5 N ramp from 1.46 N / 2.4 mm to 0.28 N /
0.44 mm on the default mesh; 1 keeps it fixed) starts at ``trust_start_scale``, doubles, up to
``trust_max_scale``, after each refresh whose first-order prediction erred by less than 15 % of
the volume change it made and that needed no factorization, and halves (not below 1) after one
that erred by more than 30 % or needed a factorization (a big step costs more than two small ones). ``path_correction``: between refreshes, correct the first-order
model by the change of W and of the tracked points' sensitivities between the last two
linearizations (a quadratic along the path; it vanishes at the linearization point, so a
converged fixed point is unchanged). ``tol``: relative force residual of a converged
    equilibrium; ``refactor_rate``: chord contraction above which the tangent is refactored;
    ``max_iter``: chord iterations before the Newton/load-stepping fallback; ``sparse_solver``: see
    :class:`~softphantom.fem.SparseSolver`.

    >>> EstimatorConfig.box(5.0).force_max_N
    (5.0, 5.0, 5.0)
    >>> EstimatorConfig(qp_solver="osqp")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: qp_solver must be one of daqp, quadprog, got 'osqp'
    """

    contact: str | tuple[float, float, float] = "on-centre"
    contact_radius_m: float = DEFAULT_CONTACT_RADIUS_M
    force_min_N: tuple[float, float, float] = (-10.0, -10.0, -10.0)
    force_max_N: tuple[float, float, float] = (10.0, 10.0, 10.0)
    qp_solver: str = "daqp"
    mode: str = "sync"
    refresh_every: int = 8
    relinearize_N: float = 0.25
    relinearize_Pa: float = 500.0
    trust_N: float = 0.5
    trust_Pa: float = 1000.0
    trust_max_scale: float = 8.0
    trust_start_scale: float = 2.0
    path_correction: bool = True
    deadband_N: float = 1e-6
    deadband_Pa: float = 1e-3
    tol: float = 1e-8
    refactor_rate: float = 0.3
    max_iter: int = 12
    sparse_solver: str = "auto"

    def __post_init__(self) -> None:
        if self.qp_solver not in QP_SOLVERS:
            raise UserError(f"qp_solver must be one of {', '.join(QP_SOLVERS)}, got {self.qp_solver!r}")
        if self.mode not in MODES:
            raise UserError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        lo = _vec3("force_min_N", self.force_min_N)
        hi = _vec3("force_max_N", self.force_max_N)
        if any(a > b for a, b in zip(lo, hi)):
            raise UserError(f"force bounds: force_min_N {lo} exceeds force_max_N {hi}")
        object.__setattr__(self, "force_min_N", lo)
        object.__setattr__(self, "force_max_N", hi)
        if not isinstance(self.contact, str):
            object.__setattr__(self, "contact", _vec3("contact (m)", self.contact))
        for name in ("contact_radius_m", "relinearize_N", "relinearize_Pa", "trust_N", "trust_Pa", "deadband_N", "deadband_Pa"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise UserError(f"{name} must be a finite number >= 0, got {v}")
        if not (0 < self.tol < 1e-2):
            raise UserError(f"tol must be in (0, 1e-2), got {self.tol}")
        if not (0 < self.refactor_rate < 1):
            raise UserError(f"refactor_rate must be in (0, 1), got {self.refactor_rate}")
        if not (math.isfinite(float(self.trust_max_scale)) and self.trust_max_scale >= 1):
            raise UserError(f"trust_max_scale must be a finite number >= 1, got {self.trust_max_scale}")
        if int(self.refresh_every) < 1 or int(self.max_iter) < 1:
            raise UserError("refresh_every and max_iter must be >= 1")

    @classmethod
    def box(cls, max_force_N: float = 10.0, **kw) -> "EstimatorConfig":
        """Bounds |f_i| ≤ ``max_force_N`` on each component."""
        m = float(max_force_N)
        if not (math.isfinite(m) and m > 0):
            raise UserError(f"--max-force-N must be a positive number, got {max_force_N}")
        return cls(force_min_N=(-m, -m, -m), force_max_N=(m, m, m), **kw)
