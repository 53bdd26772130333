"""The calibration's least squares: model parameters, sensor parameters, registration and lag,
jointly with the (unknown or measured) load at every keyframe.

Unknowns ``z``: the global parameters (:data:`PARAMETERS`; stiffness scales as logarithms) and a
force (3,) N per keyframe. Residuals, each divided by its standard deviation:

* per keyframe, the arm pressures: ``g_i · boyle_dp(ΔV_i, V_cav,i + τ·V_tube,i) + o_i + d_s·t``
  against the recording (tube lag undone), ΔV from the FEM at the keyframe's load (the force on
  the contact and the recorded pressure of every internal cavity), ``d_s`` the
  session's common pressure drift (the trapped air's temperature: P0/T ≈ 350 Pa per kelvin, so
  0.05 K/min is 0.3 Pa/s, 9 Pa over 30 s — several times the rest noise), ``t`` from the
  recording's start;
* per keyframe, the 6-DoF pose of the tracked body: the FEM's marker motion seen in the body's frame
  (axes rotated by the registration rotation, origin at the pivot) against the take at ``t + lag``;
* per keyframe with known loads, the force against the measurement;
* a weak Gaussian prior on every global parameter (its nominal value and plausible spread), which
  keeps the problem well posed when the data cannot tell a parameter — and is how such a
  parameter is recognised: its posterior spread stays close to its prior spread.

Levenberg–Marquardt with the exact Jacobian: the FEM sensitivities come with each keyframe's solve
(:mod:`softphantom.calibration.forward`), the rest by short finite differences of cheap closed
forms. Confidence intervals from the Gauss–Newton covariance at the optimum, the data's part
scaled by their residual variance (:func:`posterior_covariance`); correlations from the same matrix.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from softphantom.calibration.forward import ARM_NAMES, GROUPS, KeyframeSolution
from softphantom.calibration.session import Session, cavity_pressures
from softphantom.errors import SolverError, UserError
from softphantom.fem import LAWS
from softphantom.pose import rigid_fit, ypr_from_matrix
from softphantom.records.names import BIP_CAVITIES
from softphantom.sensing.pneumatics import boyle_dp

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Parameter:
    """A global parameter: ``name`` (unit in it), display ``unit``, ``nominal`` (internal units),
    ``prior_sd`` (internal), ``log``: internal value is ln of the displayed factor; ``ratio``
    (group, law name, k) for the k-th of a group's law's :attr:`~softphantom.fem.Law.ratios`."""

    name: str
    nominal: float
    prior_sd: float
    log: bool = False
    scale: float = 1.0  # displayed = internal * scale (or exp(internal) when log)
    ratio: tuple[str, str, int] | None = None

    def show(self, v: float) -> float:
        return math.exp(v) if self.log else v * self.scale

    def internal(self, shown: float) -> float:
        """The internal value of a displayed one (inverse of :meth:`show`)."""
        return math.log(shown) if self.log else shown / self.scale

    def measured(self, value: float, sd: float | None) -> "Parameter":
        """This parameter with a bench measurement ``value`` ± ``sd`` (displayed units) as its
        nominal value and prior (``sd`` None: the prior is kept; the caller holds it fixed)."""
        if not math.isfinite(value) or (self.log and value <= 0):
            raise UserError(f"--measured {self.name}: value must be {'> 0' if self.log else 'finite'}, got {value}")
        if sd is not None and not (math.isfinite(sd) and sd > 0):
            raise UserError(f"--measured {self.name}: standard deviation must be > 0, got {sd}")
        if sd is None:
            prior = self.prior_sd
        else:  # a log parameter's sd is relative: d ln v = dv / v
            prior = sd / value if self.log else sd / self.scale
        return dataclasses.replace(self, nominal=self.internal(value), prior_sd=prior)


def ratio_name(law: str, ratio: str, group: str) -> str:
    """The parameter name of a group's law's ratio (``yeoh_C20_C10_bulb``)."""
    return f"{law.replace('-', '_')}_{ratio}_{group}"


def _ratio_names(groups=GROUPS) -> dict[str, tuple[str, type, int]]:
    """name -> (group, law class, k) of every registered law's ratios in ``groups``."""
    return {ratio_name(c.name, r.name, g): (g, c, k) for c in LAWS.values() for k, r in enumerate(c.ratios)
            for g in groups}


def ratio_names(groups=GROUPS) -> set[str]:
    """The names every registered law's ratios would have in ``groups``."""
    return set(_ratio_names(groups))


def fitted_ratios(values: dict[str, float]) -> dict[str, tuple[type, tuple[float, ...]]]:
    """group -> (law class, its ratios) from calibrated parameter values by name."""
    found: dict[str, tuple[type, dict[int, float]]] = {}
    for name, (g, law, k) in _ratio_names().items():
        if name in values:
            found.setdefault(g, (law, {}))[1][k] = float(values[name])
    return {g: (law, tuple(v[k] for k in sorted(v))) for g, (law, v) in found.items()}


def parameter_set(groups=GROUPS, measured: tuple[tuple[str, float, float | None], ...] = (),
                  shapes: dict | None = None, arm_names: tuple[str, ...] = ARM_NAMES) -> tuple[Parameter, ...]:
    """Every global parameter the calibration knows, in order; those named in ``measured``
    ((name, value, sd) in displayed units, see :class:`FitOptions`) centred on their measurement;
    ``shapes`` (group -> its law, :func:`~softphantom.calibration.forward.group_shapes`) adds those
    groups' ratios (:func:`ratio_name`) at the design's values with the law's prior spreads; a
    gain and an offset per arm of ``arm_names`` (the model's, in the sensor order).

    >>> p = {q.name: q for q in parameter_set(measured=(("gain_back_xpos", 1.05, 0.01),
    ...                                                  ("stiffness_bulb_factor", 1.3, 0.13)))}
    >>> p["gain_back_xpos"].nominal, p["gain_back_xpos"].prior_sd
    (1.05, 0.01)
    >>> round(p["stiffness_bulb_factor"].show(p["stiffness_bulb_factor"].nominal), 12), p["stiffness_bulb_factor"].prior_sd
    (1.3, 0.1)
    """
    ps = _parameters(groups, arm_names)
    ps[len(groups):len(groups)] = [
        Parameter(ratio_name(law.name, r.name, g), float(v), r.prior_sd, ratio=(g, law.name, k))
        for g, law in (shapes or {}).items() for k, (r, v) in enumerate(zip(law.ratios, law.ratio_values()))]
    names = [p.name for p in ps]
    seen = set()
    for name, value, sd in measured:
        if name not in names:
            raise UserError(f"--measured: unknown parameter {name!r}; have {', '.join(names)}")
        if name in seen:
            raise UserError(f"--measured: {name} given twice")
        seen.add(name)
        i = names.index(name)
        ps[i] = ps[i].measured(float(value), None if sd is None else float(sd))
    return tuple(ps)


def gain_arms(names) -> tuple[str, ...]:
    """The arms of a parameter set, from the names of its per-arm gains (``gain_<arm>``), in order.

    >>> gain_arms(["stiffness_bulb_factor", "gain_a", "gain_b", "offset_a_Pa"])
    ('a', 'b')
    """
    return tuple(n[len("gain_"):] for n in names if n.startswith("gain_"))


def _parameters(groups, arm_names: tuple[str, ...] = ARM_NAMES) -> list[Parameter]:
    ps = [Parameter(f"stiffness_{g}_factor", 0.0, math.log(2.0), log=True) for g in groups]
    # MPXV7002 full-scale span 3.5–4.5 V around 4.0 V (±12.5 %): taken as ±2σ
    ps += [Parameter(f"gain_{a}", 1.0, 0.0625) for a in arm_names]
    ps += [Parameter(f"offset_{a}_Pa", 0.0, 300.0) for a in arm_names]
    ps += [Parameter("tube_volume_factor", 1.0, 0.3)]
    ps += [Parameter(f"registration_rot_{a}_deg", 0.0, math.radians(5.0), scale=180 / math.pi) for a in "xyz"]
    ps += [Parameter(f"pivot_{a}_mm", 0.0, 0.02, scale=1e3) for a in "xyz"]
    return ps


#: The smallest load increment a trial step's forward solve may cut to (three halvings) before the
#: step is rejected like one that raises the cost: an equilibrium that needs deeper continuation from
#: the last accepted one lies outside the region where the linearisation holds (the default
#: co-rotational model's first step against a neo-Hookean truth: solves at 1/64 increments with
#: inverting elements, 20 min without finishing the step). The first evaluation is not limited.
TRIAL_MIN_LOAD_STEP = 1.0 / 8


@dataclass(frozen=True)
class FitOptions:
    """``sigma_dp_Pa``, ``sigma_mm``, ``sigma_deg``, ``sigma_force_N``: the residuals' scales
    (``sigma_dp_Pa`` None: each session's measured rest noise per arm);
    ``fix``: names of parameters held at their nominal value; ``measured``: parameters measured on
    the bench apart from the session — a transducer's gain against a reference gauge, the tube's
    volume — as (name, value, sd) in displayed units: the measurement becomes the parameter's
    nominal value and prior (sd None: held at the value); ``max_iter``; ``tol`` relative cost change
    that ends the iterations (the last step's, or the Gauss–Newton model's prediction for the next
    one); ``radius_m`` the contact patch radius; ``lag_prior_s``, ``drift_prior_Pa_per_s`` the
    priors' spreads of each session's clock lag and pressure drift (``fix`` names ``lag`` and
    ``drift`` hold every session's at its first guess, resp. 0); ``law`` the law the model is
    fitted under (None: the design's; else every material converted at its small-strain E, ν,
    :func:`~softphantom.calibration.forward.design_with_law`)."""

    sigma_dp_Pa: float | None = None
    sigma_mm: float = 0.2
    sigma_deg: float = 0.2
    sigma_force_N: float = 0.02
    fix: tuple[str, ...] = ()
    measured: tuple[tuple[str, float, float | None], ...] = ()
    max_iter: int = 20
    tol: float = 1e-5
    radius_m: float = 4e-3
    lag_prior_s: float = 1.0
    drift_prior_Pa_per_s: float = 1.0
    law: str | None = None


@dataclass(frozen=True, eq=False)
class Keyframes:
    """All keyframes: ``session`` index, ``t`` s (recording clock), ``dp`` (K, arms) Pa,
    ``p_urethra`` (K,) Pa, ``contact`` (K, 3) m, ``known`` (K, 3) N (NaN where unknown),
    ``dp_rate`` (K, arms) Pa/s the readings' rate (None: 0), what a tube time constant other than the
    recording's changes ``dp`` by (:meth:`Problem.measured_dp`); ``cavity_names`` the internal
    cavities in the model's load order and ``pressures`` (K, M) Pa their gauge pressures (None:
    ``p_urethra`` as the urethra's; :attr:`cavity_pressures_Pa` either way)."""

    session: np.ndarray
    t: np.ndarray
    dp: np.ndarray
    p_urethra: np.ndarray
    contact: np.ndarray
    known: np.ndarray
    dp_rate: np.ndarray | None = None
    cavity_names: tuple[str, ...] = BIP_CAVITIES
    pressures: np.ndarray | None = None

    @property
    def cavity_pressures_Pa(self) -> np.ndarray:
        """(K, M) Pa the internal cavities' gauge pressures, in :attr:`cavity_names` order."""
        return cavity_pressures(self.p_urethra, self.pressures, self.cavity_names)

    def loads_Pa(self, k: int) -> dict[str, float]:
        """Keyframe ``k``'s internal pressures by cavity name (Pa), the solve's ``pressures_Pa``."""
        return dict(zip(self.cavity_names, (float(p) for p in self.cavity_pressures_Pa[k])))

    @staticmethod
    def of(sessions: list[Session], times: list[np.ndarray]) -> "Keyframes":
        names = sessions[0].cavity_names if sessions else BIP_CAVITIES
        for se in sessions:
            if tuple(se.cavity_names) != tuple(names):
                raise UserError(f"session {se.name}: internal cavities {', '.join(se.cavity_names) or 'none'}, "
                                f"session {sessions[0].name}: {', '.join(names) or 'none'}")
        s, t, dp, pu, c, kn, rate, pc = [], [], [], [], [], [], [], []
        for i, (se, tt) in enumerate(zip(sessions, times)):
            tt = np.asarray(tt, float)
            s.append(np.full(tt.size, i))
            t.append(tt)
            na = se.dp.shape[1]  # the arms
            dp.append(np.stack([np.interp(tt, se.t, se.dp[:, k]) for k in range(na)], axis=1))
            rate.append(np.zeros((tt.size, na)) if se.dp_rate is None else
                        np.stack([np.interp(tt, se.t, se.dp_rate[:, k]) for k in range(na)], axis=1))
            pu.append(np.interp(tt, se.t, se.p_urethra))
            sp = se.cavity_pressures_Pa
            pc.append(np.stack([np.interp(tt, se.t, sp[:, j]) for j in range(sp.shape[1])], axis=1).reshape(tt.size, -1))
            c.append(np.broadcast_to(se.contact, (tt.size, 3)))
            k = se.known_at(tt)
            kn.append(np.full((tt.size, 3), np.nan) if k is None else k)
        return Keyframes(np.concatenate(s), np.concatenate(t), np.concatenate(dp), np.concatenate(pu),
                         np.concatenate(c), np.concatenate(kn), np.concatenate(rate), tuple(names),
                         np.concatenate(pc))

    def __len__(self) -> int:
        return len(self.t)


def rotvec_matrix(rho: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rho, float)).as_matrix()


def body_pose(rest_markers: np.ndarray, markers: np.ndarray, rho: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(6,) the marker body's motion relative to rest as the tracker reports it: translation of the
    pivot and rotation, both in the body's axes (model axes rotated by ``rho``); m and rad."""
    T = rigid_fit(rest_markers, markers)
    A = rotvec_matrix(rho)
    Rb = A.T @ T.R @ A
    tb = A.T @ (T.R @ pivot + T.t - pivot)
    return np.concatenate([tb, ypr_from_matrix(Rb)])


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass
class Problem:
    """The least-squares problem (see the module docstring); ``solve_many`` maps keyframe solve
    tasks (argument tuples of :func:`solve_keyframe`) to :class:`KeyframeSolution` s."""

    model_dir: str
    sessions: list[Session]
    frames: Keyframes
    rest_markers: np.ndarray
    solve_many: Callable[[list[tuple]], list[KeyframeSolution]]
    options: FitOptions = field(default_factory=FitOptions)
    params: tuple[Parameter, ...] = field(default_factory=parameter_set)
    lag0_s: np.ndarray | None = None
    drift0: np.ndarray | None = None  # Pa/s per session (nominal 0)
    x_warm: list = field(default_factory=list)
    solves: int = 0
    pose_rows: np.ndarray | None = None  # keyframes whose take sample exists (fixed at the start)
    use_pose: bool = True  # False: forces from the pressures alone (held-out prediction)
    use_known: bool = True

    def __post_init__(self) -> None:
        names = [p.name for p in self.params]
        bad = [f for f in self.options.fix if f not in names and not f.startswith(("lag", "drift"))]
        if bad:
            raise UserError(f"--fix: unknown parameter(s) {', '.join(bad)}; have {', '.join(names)}")
        if self.lag0_s is None:
            self.lag0_s = np.zeros(len(self.sessions))
        if self.drift0 is None:
            self.drift0 = np.zeros(len(self.sessions))
        if not self.x_warm:
            self.x_warm = [None] * len(self.frames)
        if self.pose_rows is None:
            fr = self.frames
            self.pose_rows = np.array([
                bool(np.all(np.isfinite(self.sessions[int(fr.session[k])].pose_at(fr.t[k] + self.lag0_s[int(fr.session[k])]))))
                for k in range(len(fr))])

    @property
    def arm_names(self) -> tuple[str, ...]:
        """The model's arms in the sensor order, as the parameters name them (the pressures' rows)."""
        return gain_arms(p.name for p in self.params)

    # --- layout of z ---------------------------------------------------------------------------
    @property
    def n_global(self) -> int:
        return len(self.params) + 2 * len(self.sessions)  # + one lag and one drift per session

    def names(self) -> list[str]:
        return ([p.name for p in self.params] + [f"lag_{s.name}_ms" for s in self.sessions]
                + [f"drift_{s.name}_Pa_per_s" for s in self.sessions])

    def nominal(self) -> np.ndarray:
        z = np.concatenate([[p.nominal for p in self.params], self.lag0_s, self.drift0])
        return z

    def prior_sd(self) -> np.ndarray:
        n = len(self.sessions)
        return np.concatenate([[p.prior_sd for p in self.params], np.full(n, self.options.lag_prior_s),
                               np.full(n, self.options.drift_prior_Pa_per_s)])

    def free_mask(self) -> np.ndarray:
        fix = set(self.options.fix) | {n for n, _, sd in self.options.measured if sd is None}
        n = len(self.sessions)
        m = np.array([p.name not in fix for p in self.params] + ["lag" not in fix] * n + ["drift" not in fix] * n)
        return m

    def _idx(self, name: str) -> int:
        return [p.name for p in self.params].index(name)

    def unpack(self, g: np.ndarray) -> dict:
        P = {p.name: g[i] for i, p in enumerate(self.params)}
        return dict(
            scales={gr: math.exp(P[f"stiffness_{gr}_factor"]) for gr in GROUPS},
            shape=self.shape(g),
            gain=np.array([P[f"gain_{a}"] for a in self.arm_names]),
            offset=np.array([P[f"offset_{a}_Pa"] for a in self.arm_names]),
            tube=P["tube_volume_factor"],
            rho=np.array([P[f"registration_rot_{a}_deg"] for a in "xyz"]),
            pivot=np.array([P[f"pivot_{a}_mm"] for a in "xyz"]),
            lag=g[len(self.params):len(self.params) + len(self.sessions)],
            drift=g[len(self.params) + len(self.sessions):],
        )

    def _ratio_index(self) -> dict[str, tuple[str, list[int]]]:
        """group -> (law name, positions in ``z`` of its ratios, in the law's order)."""
        out: dict[str, tuple[str, list[int]]] = {}
        for i, p in enumerate(self.params):
            if p.ratio is not None:
                g, law, k = p.ratio
                out.setdefault(g, (law, []))[1].append(i)
        return out

    def shape(self, g: np.ndarray) -> dict[str, tuple[float, ...]]:
        """group -> its law's ratios in the global parameters ``g``."""
        return {gr: tuple(float(g[i]) for i in idx) for gr, (_, idx) in self._ratio_index().items()}

    def feasible(self, z: np.ndarray) -> np.ndarray:
        """``z`` with each group's free ratios moved into the set where its law is valid
        (:meth:`~softphantom.fem.Law.feasible_ratios`; Yeoh: the stable set, projected back rather
        than rejected)."""
        z = z.copy()
        free = self.free_mask()
        for law, idx in self._ratio_index().values():
            if any(free[i] for i in idx):
                z[idx] = LAWS[law].feasible_ratios(z[idx], [bool(free[i]) for i in idx])
        return z

    # --- forward ---------------------------------------------------------------------------------
    def solve(self, g: np.ndarray, forces: np.ndarray, trial: bool = False) -> list[KeyframeSolution]:
        """Every keyframe's solve; a ``trial`` (a step not yet accepted) gives up early
        (:data:`TRIAL_MIN_LOAD_STEP`)."""
        u = self.unpack(g)
        fr = self.frames
        mls = TRIAL_MIN_LOAD_STEP if trial else 1.0 / 1024
        tasks = [(self.model_dir, tuple(fr.contact[k]), self.options.radius_m, u["scales"], forces[k],
                  fr.loads_Pa(k), self.x_warm[k], mls, u["shape"], 1e-9, self.options.law)
                 for k in range(len(fr))]
        sols = self.solve_many(tasks)
        self.solves += len(tasks)
        return sols

    def since_start(self, k: int) -> float:
        """Keyframe ``k``'s time from its recording's start (s): what the drift multiplies."""
        return float(self.frames.t[k] - self.sessions[int(self.frames.session[k])].t[0])

    def measured_dp(self, tube: float) -> tuple[np.ndarray, np.ndarray]:
        """The keyframes' cavity pressures (K, arms) Pa as the recordings give them once the tube lag
        is undone with the time constant of a tube whose volume is ``tube`` × the recording's
        (:meth:`Session.tau_s`: the factor taken as the length), and their derivative wrt ``tube``.
        The sessions were de-lagged with the recording's tube: ``dp + (τ(tube) − τ(1))·rate``.
        Without it a tube 10 % longer than recorded left the pressures ≈ 20 ms late against the
        known loads (a quarter of the cost, at the ramps' keyframes)."""
        fr = self.frames
        if fr.dp_rate is None:
            return fr.dp, np.zeros_like(fr.dp)
        h = 1e-4
        tau = {}
        for i, se in enumerate(self.sessions):
            t0, tp, tm = se.tau_s(1.0), se.tau_s(tube + h), se.tau_s(tube - h)
            tau[i] = (se.tau_s(tube) - t0, (tp - tm) / (2 * h))
        s = fr.session.astype(int)
        d_tau = np.array([tau[i][0] for i in s])
        dd_tau = np.array([tau[i][1] for i in s])
        return fr.dp + d_tau * fr.dp_rate, dd_tau * fr.dp_rate

    def pressures(self, u: dict, dV: np.ndarray, session: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted dp (K, arms) Pa and its derivatives wrt ΔV (K, arms) and the tube factor (K, arms)."""
        out, d_dV, d_tube = [], [], []
        for k in range(dV.shape[0]):
            se = self.sessions[int(session[k])]
            vt = se.tube_m3
            VT = se.cavity_m3 + u["tube"] * vt
            p = boyle_dp(dV[k], VT, se.p0_Pa)
            # dp = P0 (VT/(VT+dV) − 1): ∂/∂dV = −P0 VT/(VT+dV)², ∂/∂VT = P0 dV/(VT+dV)²
            den = (VT + dV[k]) ** 2
            out.append(u["gain"] * p + u["offset"] + u["drift"][int(session[k])] * self.since_start(k))
            d_dV.append(u["gain"] * (-se.p0_Pa * VT / den))
            d_tube.append(u["gain"] * (se.p0_Pa * dV[k] / den) * vt)
        return np.array(out), np.array(d_dV), np.array(d_tube)

    def residuals(self, z: np.ndarray, want_jac: bool = True, trial: bool = False):
        """Residual vector, Jacobian (dense) and the solutions, at ``z`` (``trial``: see :meth:`solve`)."""
        ng, K = self.n_global, len(self.frames)
        g, forces = z[:ng], z[ng:].reshape(K, 3)
        u = self.unpack(g)
        sols = self.solve(g, forces, trial)
        o = self.options
        fr = self.frames
        dV = np.array([s.dV for s in sols])
        dp, dp_dV, dp_dtube = self.pressures(u, dV, fr.session)
        meas_dp, dmeas_dtube = self.measured_dp(u["tube"])
        rows_r, rows_J = [], []
        nz = z.size
        iG = {name: i for i, name in enumerate(self.names())}
        scale_cols = [iG[f"stiffness_{gr}_factor"] for gr in GROUPS]
        ratio_col = {gr: idx for gr, (_, idx) in self._ratio_index().items()}
        # pressures
        arms = self.arm_names
        na = len(arms)
        for k in range(K):
            sdp = self.sessions[int(fr.session[k])].dp_noise_Pa if o.sigma_dp_Pa is None else np.full(na, o.sigma_dp_Pa)
            r = (dp[k] - meas_dp[k]) / sdp
            J = np.zeros((na, nz))
            s = sols[k]
            J[:, ng + 3 * k: ng + 3 * k + 3] = dp_dV[k][:, None] * s.dV_df / sdp[:, None]
            for j, gr in enumerate(s.groups):
                J[:, scale_cols[GROUPS.index(gr)]] = dp_dV[k] * s.dV_dlnc[:, j] / sdp
            for j, (gr, i) in enumerate(s.shape_cols):
                J[:, ratio_col[gr][i]] = dp_dV[k] * s.dV_dshape[:, j] / sdp
            p_lin = (dp[k] - u["offset"] - u["drift"][int(fr.session[k])] * self.since_start(k)) / u["gain"]
            for i, a in enumerate(arms):
                J[i, iG[f"gain_{a}"]] = p_lin[i] / sdp[i]
                J[i, iG[f"offset_{a}_Pa"]] = 1.0 / sdp[i]
            J[:, iG["tube_volume_factor"]] = (dp_dtube[k] - dmeas_dtube[k]) / sdp
            J[:, ng - len(self.sessions) + int(fr.session[k])] = self.since_start(k) / sdp
            rows_r.append(r)
            rows_J.append(J)
        # poses
        pose_keys = range(K) if self.use_pose else ()
        sd6 = np.array([o.sigma_mm * 1e-3] * 3 + [math.radians(o.sigma_deg)] * 3)
        h_m, h_par = 1e-7, 1e-6
        for k in pose_keys:
            se = self.sessions[int(fr.session[k])]
            lag = u["lag"][int(fr.session[k])]
            if not self.pose_rows[k]:
                continue
            meas = se.pose_at(fr.t[k] + lag)[0]
            J = np.zeros((6, nz))
            if not np.all(np.isfinite(meas)):  # the lag moved this keyframe out of the take
                rows_r.append(np.zeros(6))
                rows_J.append(J)
                continue
            s = sols[k]
            pred = body_pose(self.rest_markers, s.markers, u["rho"], u["pivot"])
            r = np.concatenate([pred[:3] - meas[:3], _wrap(pred[3:] - meas[3:])]) / sd6
            if want_jac:
                # pose wrt marker positions (central differences of the rigid fit)
                M = s.markers
                D = np.zeros((6, M.size))
                for c in range(M.size):
                    Mp, Mm = M.copy().reshape(-1), M.copy().reshape(-1)
                    Mp[c] += h_m
                    Mm[c] -= h_m
                    dp_ = body_pose(self.rest_markers, Mp.reshape(M.shape), u["rho"], u["pivot"])
                    dm_ = body_pose(self.rest_markers, Mm.reshape(M.shape), u["rho"], u["pivot"])
                    D[:, c] = np.concatenate([dp_[:3] - dm_[:3], _wrap(dp_[3:] - dm_[3:])]) / (2 * h_m)
                J[:, ng + 3 * k: ng + 3 * k + 3] = D @ s.dM_df.reshape(M.size, 3) / sd6[:, None]
                for j, gr in enumerate(s.groups):
                    J[:, scale_cols[GROUPS.index(gr)]] = D @ s.dM_dlnc[:, :, j].reshape(M.size) / sd6
                for j, (gr, i) in enumerate(s.shape_cols):
                    J[:, ratio_col[gr][i]] = D @ s.dM_dshape[:, :, j].reshape(M.size) / sd6
                for a_i, a in enumerate("xyz"):
                    for name, vec, h in ((f"registration_rot_{a}_deg", "rho", h_par), (f"pivot_{a}_mm", "pivot", h_par * 1e-2)):
                        up, um = dict(u), dict(u)
                        up[vec] = u[vec].copy()
                        um[vec] = u[vec].copy()
                        up[vec][a_i] += h
                        um[vec][a_i] -= h
                        pp = body_pose(self.rest_markers, M, up["rho"], up["pivot"])
                        pm = body_pose(self.rest_markers, M, um["rho"], um["pivot"])
                        J[:, iG[name]] = np.concatenate([pp[:3] - pm[:3], _wrap(pp[3:] - pm[3:])]) / (2 * h) / sd6
                h_t = 2e-3
                mp, mm = se.pose_at(fr.t[k] + lag + h_t)[0], se.pose_at(fr.t[k] + lag - h_t)[0]
                if np.all(np.isfinite(mp)) and np.all(np.isfinite(mm)):
                    dmeas = np.concatenate([mp[:3] - mm[:3], _wrap(mp[3:] - mm[3:])]) / (2 * h_t)
                    J[:, len(self.params) + int(fr.session[k])] = -dmeas / sd6
            rows_r.append(r)
            rows_J.append(J)
        # known loads
        for k in range(K if self.use_known else 0):
            if np.all(np.isfinite(fr.known[k])):
                rows_r.append((forces[k] - fr.known[k]) / o.sigma_force_N)
                J = np.zeros((3, nz))
                J[:, ng + 3 * k: ng + 3 * k + 3] = np.eye(3) / o.sigma_force_N
                rows_J.append(J)
        # priors on the global parameters
        sd = self.prior_sd()
        rows_r.append((g - self.nominal()) / sd)
        Jp = np.zeros((ng, nz))
        Jp[:, :ng] = np.diag(1.0 / sd)
        rows_J.append(Jp)
        r = np.concatenate(rows_r)
        J = np.vstack(rows_J)
        return r, J, sols


@dataclass(frozen=True, eq=False)
class FitResult:
    """``z`` the optimum; ``names``; ``value`` displayed values of the global parameters;
    ``ci95`` (n, 2) their 95 % intervals (displayed units); ``sd`` internal standard deviations;
    ``prior_sd``; ``correlation`` (n, n); ``identifiable`` (n,) bool; ``history`` cost per
    iteration; ``cost0``/``cost`` initial and final ½‖r‖²; ``forces`` (K, 3) N; ``solutions``;
    ``solves`` forward solves spent; ``seconds``; ``warnings``."""

    z: np.ndarray
    names: list[str]
    value: np.ndarray
    nominal: np.ndarray
    ci95: np.ndarray
    sd: np.ndarray
    prior_sd: np.ndarray
    correlation: np.ndarray
    identifiable: np.ndarray
    history: list[float]
    forces: np.ndarray
    solutions: list
    solves: int
    seconds: float
    warnings: tuple[str, ...]
    free: np.ndarray


def _display(problem: Problem, g: np.ndarray) -> np.ndarray:
    vals = [p.show(v) for p, v in zip(problem.params, g)]
    u = problem.unpack(g)
    return np.array(vals + list(u["lag"] * 1e3) + list(u["drift"]))


def posterior_covariance(J: np.ndarray, r: np.ndarray, n_prior: int) -> tuple[np.ndarray, float]:
    """Gauss–Newton covariance of the unknowns at the optimum, and the data's residual variance
    ``s2``; ``J`` (m, n), ``r`` (m,) with the priors' ``n_prior`` rows last (as
    :meth:`Problem.residuals` builds them).

    The data's information is scaled by 1/s2 (their residual variance over the effective degrees
    of freedom, ≥ 1: a misfit larger than the noise widens what the data say); the priors' is not —
    they are not observations whose misfit the data measure. So a parameter the data do not see
    keeps its prior spread exactly, and no posterior spread exceeds its prior's (scaling the whole
    matrix would: spreads of 114–146 % of the prior's).
    """
    Jd, Jp, rd = J[: J.shape[0] - n_prior], J[J.shape[0] - n_prior:], r[: r.size - n_prior]
    Ad, Ap = Jd.T @ Jd, Jp.T @ Jp
    A_pinv = np.linalg.pinv(Ad + Ap)
    n_eff = float(np.trace(A_pinv @ Ad))  # the unknowns the data determine (hat matrix's trace)
    s2 = max(float(rd @ rd) / max(rd.size - n_eff, 1.0), 1.0)
    return (A_pinv if s2 == 1.0 else np.linalg.pinv(Ad / s2 + Ap)), s2


def fit(problem: Problem, forces0: np.ndarray, identifiable_ratio: float = 0.5,
        level: int = logging.INFO) -> FitResult:
    """Levenberg–Marquardt from the nominal parameters and ``forces0`` (K, 3) N.

    Logs ``iteration N: cost …`` at ``level`` after each accepted or rejected step. A parameter is
    reported identifiable when the data shrank its spread below ``identifiable_ratio`` of its prior
    spread and it is free; the warnings name the others and the pairs correlated beyond 0.95.

    Written here rather than :func:`scipy.optimize.least_squares` because a round of residuals is a
    forward solve of every keyframe, and least_squares spends more of them for the same optimum
    (``benchmarks/research/diag_calibrate/least_squares.py``; docs/calibration.md): its ``ftol`` test needs an
    evaluated step's actual reduction — one round only to confirm convergence, which the
    Gauss–Newton model's predicted reduction saves here —, its trust region grows from ``x_scale``
    by doubling, and a law's valid set (Yeoh's stability) is not a box bound it could keep."""
    t0 = time.perf_counter()
    ng = problem.n_global
    free_g = problem.free_mask()
    free = np.concatenate([free_g, np.ones(forces0.size, bool)])
    z = np.concatenate([problem.nominal(), np.asarray(forces0, float).reshape(-1)])
    r, J, sols = problem.residuals(z)
    problem.x_warm = [s.x for s in sols]
    cost = 0.5 * float(r @ r)
    history = [cost]
    lam = 1e-3
    it = 0
    while it < problem.options.max_iter:
        it += 1
        Jf = J[:, free]
        A = Jf.T @ Jf
        b = -Jf.T @ r
        # the Gauss–Newton model's own promise, ½ bᵀA⁺b (its undamped step's predicted reduction):
        # if even it is below tol, a round of forward solves would only confirm convergence
        # (MINPACK's ftol test on the predicted reduction)
        if 0.5 * float(b @ np.linalg.lstsq(A, b, rcond=None)[0]) < problem.options.tol * cost:
            break
        step_ok, rel = False, 0.0
        for _ in range(8):
            try:
                dz = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), b)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            z_try = z.copy()
            z_try[free] += dz
            z_try = problem.feasible(z_try)
            try:
                r_try, J_try, sols_try = problem.residuals(z_try, trial=True)
            except SolverError:
                lam *= 10
                _say(level, it, cost, lam, problem.solves)
                continue
            c_try = 0.5 * float(r_try @ r_try)
            if c_try < cost:
                rel = (cost - c_try) / max(cost, 1e-300)
                z, r, J, cost = z_try, r_try, J_try, c_try
                problem.x_warm = [s.x for s in sols_try]
                sols = sols_try
                lam = max(lam / 3, 1e-9)
                step_ok = True
                break
            lam *= 4
            _say(level, it, cost, lam, problem.solves)
        history.append(cost)
        _say(level, it, cost, lam, problem.solves)
        if not step_ok or rel < problem.options.tol:
            break
    return fit_result(problem, z, r, J, sols, free, history, t0, identifiable_ratio)


def _say(level: int, it: int, cost: float, lam: float, solves: int) -> None:
    logger.log(level, f"iteration {it}: cost {cost:.6g} (λ {lam:.2g}), {solves} forward solves")


def fit_result(problem: Problem, z: np.ndarray, r: np.ndarray, J: np.ndarray, sols: list, free: np.ndarray,
               history: list[float], t0: float, identifiable_ratio: float = 0.5) -> FitResult:
    """The :class:`FitResult` at the optimum ``z`` (residuals ``r``, Jacobian ``J``, solutions
    ``sols``; ``free`` the mask of the unknowns fitted; ``t0`` the start's ``perf_counter``):
    covariance, intervals, identifiability and the warnings (see :func:`fit`)."""
    ng = problem.n_global
    free_g = free[:ng]
    cov_f, _ = posterior_covariance(J[:, free], r, ng)
    cov = np.zeros((z.size, z.size))
    idx = np.flatnonzero(free)
    cov[np.ix_(idx, idx)] = cov_f
    cg = cov[:ng, :ng]
    sd = np.sqrt(np.clip(np.diag(cg), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cg / np.outer(sd, sd)
    corr[~np.isfinite(corr)] = 0.0
    prior = problem.prior_sd()
    ratio = sd / prior
    names = problem.names()
    # a measured parameter's prior is the measurement: it is known whatever the session adds
    by_measure = np.isin(names, [n for n, _, sd in problem.options.measured if sd is not None])
    ident = free_g & ((ratio < identifiable_ratio) | by_measure)
    g = z[:ng]
    lo = g - 1.96 * sd
    hi = g + 1.96 * sd
    value = _display(problem, g)
    ci = np.stack([_display(problem, lo), _display(problem, hi)], axis=1)
    warns = []
    for i, nm in enumerate(names):
        if free_g[i] and not ident[i]:
            warns.append(f"{nm} is not identifiable from these data (its spread is {ratio[i]:.0%} of the prior's): "
                         "add known loads or other pushes, or --fix it")
    for i in range(ng):
        for j in range(i + 1, ng):
            if free_g[i] and free_g[j] and abs(corr[i, j]) > 0.95:
                warns.append(f"{names[i]} and {names[j]} are correlated ({corr[i, j]:+.2f}): the data tell their "
                             "combination, not each")
    return FitResult(z, names, value, _display(problem, problem.nominal()), ci, sd, prior, corr, ident, history,
                     z[ng:].reshape(-1, 3), sols, problem.solves, time.perf_counter() - t0, tuple(warns), free_g)
