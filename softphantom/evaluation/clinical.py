"""Table I of the paper: prostate motion during brachytherapy needle insertion in the literature
(Lagerburg et al., Stone et al., Podder et al.: the paper's refs. 22–24), and how a run compares.

Statistic: the peak excursion from rest, ``max |Δ|`` over the run, per DoF — what the paper compares
("maximal y displacements of ≈ 6 mm"). A clinical figure given as ``±a`` is the range [0, a] of
|Δ|; a mean with a spread ``m (lo–hi)`` is [lo, hi]; ``m ± sd`` is [m − sd, m + sd].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClinicalRange:
    """One entry of Table I: ``dof`` (yaw, pitch, x, y, z), ``unit``, ``study``, the published
    figure as ``text``, and the range [lo, hi] of |Δ| it stands for."""

    dof: str
    unit: str
    study: str
    text: str
    lo: float
    hi: float


TABLE_I: tuple[ClinicalRange, ...] = (
    ClinicalRange("yaw", "deg", "Lagerburg et al.", "±13", 0.0, 13.0),
    ClinicalRange("pitch", "deg", "Lagerburg et al.", "±8", 0.0, 8.0),
    ClinicalRange("x", "mm", "Stone et al.", "3.6 (1–5.5)", 1.0, 5.5),
    ClinicalRange("x", "mm", "Podder et al.", "1.4 ± 0.6", 0.8, 2.0),
    ClinicalRange("y", "mm", "Stone et al.", "15 (0–30)", 0.0, 30.0),
    ClinicalRange("y", "mm", "Podder et al. (17G)", "12.6 ± 4.5", 8.1, 17.1),
    ClinicalRange("y", "mm", "Podder et al. (18G)", "6.6 ± 1.01", 5.59, 7.61),
    ClinicalRange("z", "mm", "Stone et al.", "6.8 (4.3–8.1)", 4.3, 8.1),
)

_DOF_INDEX = {"x": 0, "y": 1, "z": 2, "yaw": 3, "pitch": 4, "roll": 5}


@dataclass(frozen=True)
class ClinicalRow:
    """``observed`` max |Δ| of the truth, ``estimated`` that of the estimate (NaN if absent);
    ``flag`` "within", "below" or "above" the range for the observed value."""

    ref: ClinicalRange
    observed: float
    estimated: float
    flag: str


def _flag(v: float, lo: float, hi: float) -> str:
    if not np.isfinite(v):
        return "n/a"
    return "below" if v < lo else "above" if v > hi else "within"


def compare_table_i(truth_mm_deg: np.ndarray, estimate_mm_deg: np.ndarray | None = None) -> tuple[ClinicalRow, ...]:
    """Compare a run's peak excursions with Table I. Inputs (n, 6): x, y, z mm; yaw, pitch, roll deg.

    >>> v = np.zeros((3, 6)); v[1] = [1.0, -6.0, 0.5, 2.0, -9.0, 0.0]
    >>> [(r.ref.dof, r.ref.study, r.observed, r.flag) for r in compare_table_i(v)][:2]
    [('yaw', 'Lagerburg et al.', 2.0, 'within'), ('pitch', 'Lagerburg et al.', 9.0, 'above')]
    """
    obs = np.nanmax(np.abs(np.asarray(truth_mm_deg, float)), axis=0)
    est = np.full(6, np.nan) if estimate_mm_deg is None else np.nanmax(np.abs(np.asarray(estimate_mm_deg, float)), axis=0)
    rows = []
    for r in TABLE_I:
        k = _DOF_INDEX[r.dof]
        rows.append(ClinicalRow(r, float(obs[k]), float(est[k]), _flag(float(obs[k]), r.lo, r.hi)))
    return tuple(rows)
