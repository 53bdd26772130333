"""Metrics of an estimate against the truth, per DoF, on the estimate's samples.

Errors are ``estimate − truth``; the truth is interpolated (linearly) at the estimate's times
shifted back by the lag, ``truth(t − lag)``; samples where the truth has a gap (lost frames
longer than 3 of its sample intervals) or lies outside the truth's time span are left out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softphantom.evaluation.files import Series6
from softphantom.records.names import SCENARIO_CLOCK
from softphantom.tracking.timing import LagResult, estimate_lag, shift_to_common_start

DOF_NAMES = ("x", "y", "z", "yaw", "pitch", "roll")
DOF_UNITS = ("mm", "mm", "mm", "deg", "deg", "deg")


@dataclass(frozen=True)
class ErrorStats:
    """Error statistics of one quantity (in ``unit``): RMSE, bias (mean error), max |error|,
    Pearson r of estimate vs truth (NaN if either is constant), ``lag_ms`` (this quantity alone;
    NaN where it does not move enough to tell), ``peak_truth`` max |truth|, ``n`` samples."""

    name: str
    unit: str
    rmse: float
    bias: float
    max_abs: float
    corr: float
    lag_ms: float
    peak_truth: float
    n: int


def error_stats(name: str, unit: str, est: np.ndarray, truth: np.ndarray, lag_ms: float = float("nan")) -> ErrorStats:
    """Statistics of ``est − truth`` (1-D arrays, same samples).

    >>> s = error_stats("y", "mm", np.array([1.0, 2.0, 4.0]), np.array([1.0, 1.0, 2.0]))
    >>> round(s.rmse, 6), s.bias, s.max_abs
    (1.290994, 1.0, 2.0)
    """
    est, truth = np.asarray(est, float), np.asarray(truth, float)
    e = est - truth
    if len(e) == 0:
        nan = float("nan")
        return ErrorStats(name, unit, nan, nan, nan, nan, lag_ms, nan, 0)
    corr = float("nan")
    if np.std(est) > 0 and np.std(truth) > 0:
        corr = float(np.corrcoef(est, truth)[0, 1])
    return ErrorStats(name, unit, float(np.sqrt(np.mean(e * e))), float(np.mean(e)), float(np.max(np.abs(e))),
                      corr, float(lag_ms), float(np.max(np.abs(truth))), len(e))


def resample_truth(t_truth: np.ndarray, values: np.ndarray, t: np.ndarray, max_gap_s: float | None = None):
    """Truth values at times ``t`` (linear); returns (values (m, d), mask of usable samples)."""
    t_truth = np.asarray(t_truth, float)
    values = np.asarray(values, float).reshape(len(t_truth), -1)
    if max_gap_s is None:
        max_gap_s = 3.0 * float(np.median(np.diff(t_truth))) if len(t_truth) > 1 else 0.0
    inside = (t >= t_truth[0]) & (t <= t_truth[-1])
    j = np.clip(np.searchsorted(t_truth, t), 1, len(t_truth) - 1)
    gap = (t_truth[j] - t_truth[j - 1]) > max_gap_s
    out = np.column_stack([np.interp(t, t_truth, values[:, k]) for k in range(values.shape[1])])
    return out, inside & ~gap


def signed(v: float, digits: int = 1) -> str:
    """``v`` with its sign, a true minus for negatives (for text a person reads).

    >>> signed(-148.23), signed(104.8), signed(0.0)
    ('−148.2', '+104.8', '+0.0')
    """
    return f"{v:+.{digits}f}".replace("-", "−")


def clock_name(meta: dict) -> str | None:
    """The clock a file's ``t_s`` runs on, where it names one (``meta["clock"]``) or its source
    implies one (``source = virtual:…``: the scenario clock); None when it does not say."""
    c = meta.get("clock")
    if c and c != "file t_s":  # "file t_s": what a CSV reader assumes for a file that says nothing
        return str(c)
    return SCENARIO_CLOCK if str(meta.get("source", "")).startswith("virtual:") else None


@dataclass(frozen=True)
class LagParts:
    """What the lag consists of: ``lag_ms`` = the estimator's own ``latency_ms`` − ``clock_offset_ms``
    (the truth's clock minus the estimate's at the same instant). ``clock_offset_ms`` None: not
    known (the files run on different or unnamed clocks and no offset was given); ``offset_source``
    how it is known; ``truth_clock``/``estimate_clock`` the clocks' names (None: not named);
    ``start_shift_ms`` what re-zeroing both files at their first sample added to the lag (0 when
    they were not re-zeroed)."""

    lag_ms: float
    clock_offset_ms: float | None
    offset_source: str
    truth_clock: str | None
    estimate_clock: str | None
    start_shift_ms: float = 0.0

    @property
    def latency_ms(self) -> float | None:
        if self.clock_offset_ms is None:
            return None
        return self.lag_ms + self.clock_offset_ms - self.start_shift_ms

    def explain(self) -> str:
        """One sentence: the lag and what it is made of."""
        clocks = (f"truth clock: {self.truth_clock or 'not named'}; estimate clock: "
                  f"{self.estimate_clock or 'not named'}")
        rezero = (f"; both files re-zeroed at their first sample, which adds {signed(self.start_shift_ms)} ms"
                  if self.start_shift_ms else "")
        if self.clock_offset_ms is None:
            return (f"lag {signed(self.lag_ms)} ms = the estimator's latency minus the offset between the two "
                    f"files' clocks, which is not known here ({clocks}{rezero}): the figure includes that offset. "
                    "Give --clock-offset-ms (truth clock − estimate clock) to separate them")
        if self.offset_source == "same clock":
            return (f"lag {signed(self.lag_ms)} ms = the estimator's latency (both files on the same clock: "
                    f"{self.truth_clock}{rezero})")
        return (f"lag {signed(self.lag_ms)} ms = the estimator's latency {signed(self.latency_ms)} ms − the clock "
                f"offset {signed(self.clock_offset_ms)} ms (truth clock − estimate clock, {self.offset_source}; "
                f"{clocks}{rezero})")


@dataclass(frozen=True)
class Evaluation:
    """Everything the report shows. ``lag`` the measured (or given) lag of the estimate behind the
    truth; ``clock_rezeroed`` True when the two files' clocks did not overlap and both were
    re-zeroed at their first sample; ``dof`` six :class:`ErrorStats` (mm, deg); ``force`` per
    component and magnitude (N) where the truth knows the force; ``targets`` the 3-D shift error
    of each target (mm); ``t_est`` the estimate times on the truth's clock, compensated
    (``t − lag``); ``mask`` the estimate samples compared; ``lag_parts`` what the lag consists of
    (the estimator's latency and the clock offset, :class:`LagParts`)."""

    lag: LagResult | None
    lag_ms: float
    lag_source: str
    clock_rezeroed: bool
    dof: tuple[ErrorStats, ...]
    force: tuple[ErrorStats, ...]
    targets: tuple[ErrorStats, ...]
    t_truth: np.ndarray
    t_est: np.ndarray
    mask: np.ndarray
    notes: tuple[str, ...] = field(default_factory=tuple)
    lag_parts: LagParts | None = None


def evaluate(truth: Series6, estimate: Series6, lag_ms: float | None = None, max_lag_s: float = 1.0,
             clock_offset_ms: float | None = None, offset_source: str = "given") -> Evaluation:
    """Compare an estimate with the truth. ``lag_ms`` None: measure it by cross-correlation of the
    six DoF (sign: positive = the estimate comes later than the truth). ``clock_offset_ms``: the
    truth's clock minus the estimate's at the same instant, if known (e.g. ``clock_offset_s`` of a
    virtual run's tracker); it splits the lag into that offset and the estimator's latency. When
    both files name the same clock the offset is 0. ``offset_source`` says where a given offset
    comes from (for the report)."""
    notes = [*truth.meta.get("warnings", ()), *estimate.meta.get("warnings", ())]  # e.g. an incomplete file
    if estimate.in_envelope is not None and not estimate.in_envelope.all():
        k, n = int(np.count_nonzero(~estimate.in_envelope)), len(estimate.in_envelope)
        notes.append(f"{k} of {n} estimates ({k / n:.0%}) at or beyond the estimator's load envelope, clamped "
                     f"(in_envelope 0; shaded in the plots): their errors include the clamp")
    t_truth, t_est, rezeroed = shift_to_common_start(truth.t, estimate.t)
    tc, ec = clock_name(truth.meta), clock_name(estimate.meta)
    if clock_offset_ms is not None:
        offset, how = float(clock_offset_ms), offset_source
    elif tc is not None and tc == ec:
        offset, how = 0.0, "same clock"
    else:
        offset, how = None, ""
    # re-zeroing moved the truth back by its first time and the estimate by its own
    shift_ms = ((truth.t[0] - t_truth[0]) - (estimate.t[0] - t_est[0])) * 1e3 if rezeroed else 0.0
    if rezeroed:
        notes.append("the truth and estimate clocks do not overlap: both re-zeroed at their first sample")
    vt, ve = truth.mm_deg(), estimate.mm_deg()
    lag = None
    if lag_ms is None:
        overlap = min(t_truth[-1], t_est[-1]) - max(t_truth[0], t_est[0])
        search = min(max_lag_s, 0.45 * overlap)
        try:
            lag = estimate_lag(t_truth, vt, t_est, ve, max_lag_s=search)
        except ValueError as exc:
            from softphantom.errors import UserError

            raise UserError(f"cannot measure the lag ({exc}); give it with --lag-ms") from None
        lag_s, source = lag.lag_s, "measured (cross-correlation of the 6 DoF)"
        if lag.at_edge:
            notes.append(f"the lag sits at the edge of the ±{search * 1e3:.0f} ms searched: it may be larger")
    else:
        lag_s, source = lag_ms * 1e-3, "given"
    t_cmp = t_est - lag_s
    tv, ok = resample_truth(t_truth, vt, t_cmp)
    if ok.sum() < 2:
        from softphantom.errors import UserError

        raise UserError("the estimate and the truth share fewer than 2 samples after alignment")
    dof = []
    for k, (name, unit) in enumerate(zip(DOF_NAMES, DOF_UNITS)):
        lk = float("nan")
        if lag is not None and np.std(vt[:, k]) > 0:
            try:
                r = estimate_lag(t_truth, vt[:, k], t_est, ve[:, k], max_lag_s=min(max_lag_s, 0.45 * (t_truth[-1] - t_truth[0])))
                if r.peak_corr > 0.8 and not r.at_edge:  # a DoF that hardly moves has no lag of its own
                    lk = r.lag_ms
            except ValueError:
                pass
        dof.append(error_stats(name, unit, ve[ok, k], tv[ok, k], lk))
    force = []
    if truth.force is not None and estimate.force is not None:
        fv, okf = resample_truth(t_truth, truth.force, t_cmp)
        m = ok & okf
        for k, a in enumerate("xyz"):
            force.append(error_stats(f"force_{a}", "N", estimate.force[m, k], fv[m, k]))
        force.append(error_stats("|force|", "N", np.linalg.norm(estimate.force[m], axis=1), np.linalg.norm(fv[m], axis=1)))
    elif estimate.force is not None:
        notes.append("the truth does not know the force: no force error")
    targets = []
    for name in sorted(set(truth.targets) & set(estimate.targets)):
        tt, okt = resample_truth(t_truth, truth.targets[name], t_cmp)
        m = ok & okt
        err = np.linalg.norm(estimate.targets[name][m] - tt[m], axis=1) * 1e3
        targets.append(ErrorStats(name, "mm", float(np.sqrt(np.mean(err**2))), float(np.mean(err)), float(np.max(err)),
                                  float("nan"), float("nan"), float(np.max(np.linalg.norm(tt[m], axis=1)) * 1e3), int(m.sum())))
    parts = LagParts(lag_s * 1e3, offset, how, tc, ec, float(shift_ms))
    return Evaluation(lag, lag_s * 1e3, source, rezeroed, tuple(dof), tuple(force), tuple(targets),
                      t_truth, t_cmp, ok, tuple(notes), parts)
