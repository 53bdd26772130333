"""Time alignment of two signals by cross-correlation.

Sign convention: the lag is positive when the signal comes *later* than the reference,
``signal(t) ≈ reference(t − lag)``. For ``evaluate``, reference = truth (tracker), signal =
estimate: a positive lag is the estimator's latency, and the estimate is compared at ``t − lag``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LagResult:
    """``lag_s`` (s, signal later than reference when > 0), ``peak_corr`` the normalized
    correlation at the peak (≈ Pearson r, 1 for identical shapes), ``dt_s`` the common grid step,
    ``at_edge`` True when the peak sits at ±max_lag (the true lag may be outside the search)."""

    lag_s: float
    peak_corr: float
    dt_s: float
    at_edge: bool

    @property
    def lag_ms(self) -> float:
        return self.lag_s * 1e3


def estimate_lag(
    t_ref: np.ndarray,
    ref: np.ndarray,
    t_sig: np.ndarray,
    sig: np.ndarray,
    *,
    max_lag_s: float = 1.0,
    dt_s: float | None = None,
    weights: np.ndarray | None = None,
) -> LagResult:
    """Lag of ``sig`` behind ``ref`` by cross-correlation on a common grid.

    ``ref`` (n,) or (n, d) sampled at ``t_ref``; ``sig`` (m,) or (m, d) at ``t_sig`` (any rates;
    NaN rows dropped). Both are resampled (linear) on a grid of step ``dt_s`` (default half the
    finer median sample interval) over their common time span. At every lag the Pearson
    correlation of the overlapping parts is computed (FFT for the products, cumulative sums for
    the means, so neither a pulse nor an offset biases the peak); the channels' curves are
    averaged with ``weights`` times each channel's signal-to-noise ratio ``r²/(1 − r²)`` (r its
    peak correlation); the peak within ``±max_lag_s`` is refined by a parabola through its
    three grid points.

    >>> t = np.arange(0, 10, 0.01); f = lambda t: np.exp(-((t - 5) / 0.5) ** 2)
    >>> r = estimate_lag(t, f(t), t, f(t - 0.123))
    >>> round(r.lag_ms, 1)
    123.0
    """
    t_ref, t_sig = np.asarray(t_ref, float), np.asarray(t_sig, float)
    ref = np.asarray(ref, float).reshape(len(t_ref), -1)
    sig = np.asarray(sig, float).reshape(len(t_sig), -1)
    if ref.shape[1] != sig.shape[1]:
        raise ValueError(f"reference has {ref.shape[1]} channels, signal {sig.shape[1]}")
    okr = np.isfinite(t_ref) & np.all(np.isfinite(ref), axis=1)
    oks = np.isfinite(t_sig) & np.all(np.isfinite(sig), axis=1)
    t_ref, ref, t_sig, sig = t_ref[okr], ref[okr], t_sig[oks], sig[oks]
    if len(t_ref) < 4 or len(t_sig) < 4:
        raise ValueError("too few finite samples to estimate a lag")
    ir, is_ = np.argsort(t_ref), np.argsort(t_sig)
    t_ref, ref, t_sig, sig = t_ref[ir], ref[ir], t_sig[is_], sig[is_]
    if dt_s is None:
        dt_s = 0.5 * min(np.median(np.diff(t_ref)), np.median(np.diff(t_sig)))
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"grid step {dt_s} s: the time stamps do not increase")
    lo, hi = max(t_ref[0], t_sig[0]), min(t_ref[-1], t_sig[-1])
    if hi - lo < 2 * max_lag_s:
        raise ValueError(
            f"the records overlap {max(hi - lo, 0):.3f} s, less than twice the lag searched ({max_lag_s:.3f} s):"
            " are both on the same clock?"
        )
    grid = np.arange(lo, hi, dt_s)
    n = len(grid)
    d = ref.shape[1]
    w = np.ones(d) if weights is None else np.asarray(weights, float)
    from scipy.signal import correlation_lags  # 1 s to import: only when aligning

    lags = correlation_lags(n, n)
    keep = np.abs(lags) * dt_s <= max_lag_s
    lags = lags[keep]
    total = np.zeros(len(lags))
    wsum = 0.0
    for k in range(d):
        a = np.interp(grid, t_ref, ref[:, k])
        b = np.interp(grid, t_sig, sig[:, k])
        if np.ptp(a) == 0 or np.ptp(b) == 0 or w[k] == 0:
            continue
        r = _pearson_at_lags(a, b, lags)
        # a channel counts by its signal-to-noise ratio r²/(1 − r²) at its peak: a DoF that
        # hardly moves (mostly tracker noise) must not pull the common peak
        rmax = float(np.clip(r.max(), 0.0, 0.9999))
        wk = w[k] * rmax**2 / (1.0 - rmax**2)
        total += wk * r
        wsum += wk
    if wsum == 0:
        raise ValueError("no channel varies (or correlates): nothing to correlate")
    total /= wsum
    i = int(np.argmax(total))
    at_edge = i == 0 or i == len(total) - 1
    delta = 0.0
    if not at_edge:
        y0, y1, y2 = total[i - 1], total[i], total[i + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            delta = 0.5 * (y0 - y2) / den
    return LagResult(float((lags[i] + delta) * dt_s), float(total[i]), float(dt_s), bool(at_edge))


def _pearson_at_lags(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Pearson r of the pairs ``(a[i], b[i + k])`` over their overlap, for each lag k."""
    n = len(a)
    a = a - a.mean()  # conditioning only; r is shift-invariant
    b = b - b.mean()
    from scipy.signal import correlate

    full = correlate(b, a, mode="full", method="fft")[lags + n - 1]  # Σ a[i]·b[i+k]
    ca, cb = np.concatenate([[0.0], np.cumsum(a)]), np.concatenate([[0.0], np.cumsum(b)])
    ca2, cb2 = np.concatenate([[0.0], np.cumsum(a * a)]), np.concatenate([[0.0], np.cumsum(b * b)])
    pos = lags >= 0
    a_lo, a_hi = np.where(pos, 0, -lags), np.where(pos, n - lags, n)
    b_lo, b_hi = np.where(pos, lags, 0), np.where(pos, n, n + lags)
    m = (n - np.abs(lags)).astype(float)
    sa, sb = ca[a_hi] - ca[a_lo], cb[b_hi] - cb[b_lo]
    saa, sbb = ca2[a_hi] - ca2[a_lo], cb2[b_hi] - cb2[b_lo]
    cov = full - sa * sb / m
    var = (saa - sa * sa / m) * (sbb - sb * sb / m)
    return np.where(var > 0, cov / np.sqrt(np.maximum(var, 1e-300)), 0.0)


def shift_to_common_start(t_a: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """If two clocks do not overlap at all (e.g. epoch seconds against seconds since start),
    re-zero both at their first sample; returns the times and whether it did so."""
    t_a, t_b = np.asarray(t_a, float), np.asarray(t_b, float)
    if np.nanmax(t_a) < np.nanmin(t_b) or np.nanmax(t_b) < np.nanmin(t_a):
        return t_a - np.nanmin(t_a), t_b - np.nanmin(t_b), True
    return t_a, t_b, False
