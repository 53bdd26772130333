"""Resolution budget of an arm's sensing chain (paper Sec. III-D, eq. 1–2), and how it moves.

Definitions (docs/sensing.md has the derivation):

* V_tube = π/4·d²·L; V_total = V_cavity + V_tube; loss factor LF = V_total / V_cavity: the
  pressure a cavity volume change produces at the transducer, divided by what it would produce
  in the cavity alone ("cavity-equivalent" pressure).
* effective bits (eq. 1) = w + log4(OSR): summing OSR noisy readings gains log4(OSR) bits,
  2^(w + log4 OSR) = 2^w·√OSR levels over the ADC's range.
* digital span (eq. 2) = 2^(w + log4 OSR) · P_active / (LF · P_measure): how many effective
  levels the cavity-equivalent active span (−7…+10 kPa = 17 kPa) covers once divided by LF,
  with the paper taking P_measure = 4 kPa (the MPXV7002's ±2 kPa) as the span of the ADC.
  The datasheet transfer function puts ±2 kPa on 0.1…0.9·VS, so the ADC's full range is
  1/0.2 = 5 kPa: the "datasheet" figures use 5 kPa instead of 4 (a 0.8 × smaller span).
* worst-case resolution = P_active / digital span (cavity-equivalent Pa per level).

The paper rounds the loss factors to one decimal (28.9, 27.4) before eq. 2; ``paper_rounding``
does the same to reproduce 1505.9 / 1588.3; the exact factors give 1504.6 / 1588.1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from softphantom.errors import UserError
from softphantom.sensing.board import frame_rate_Hz
from softphantom.sensing.chain import MPXV7002, Transducer
from softphantom.sensing.measurement import P0_STANDARD_PA
from softphantom.sensing.pneumatics import loss_factor, tube_time_constant_s, tube_volume_m3


def effective_bits(adc_bits: int, osr: int) -> float:
    """Eq. (1): w + log4(OSR).

    >>> round(effective_bits(10, 100), 2)
    13.32
    """
    if osr < 1:
        raise UserError(f"osr must be ≥ 1, got {osr}")
    return adc_bits + math.log(osr, 4)


def digital_span_counts(eff_bits: float, active_span_Pa: float, loss: float,
                        measure_span_Pa: float) -> float:
    """Eq. (2): 2^eff_bits · P_active / (LF · P_measure) effective levels.

    >>> round(digital_span_counts(effective_bits(10, 100), 17_000, 28.9, 4_000), 1)
    1505.9
    """
    return 2.0**eff_bits * active_span_Pa / (loss * measure_span_Pa)


@dataclass(frozen=True)
class BudgetParams:
    """Inputs of the budget (SI). ``cavity_volumes_m3`` one per arm group (front 514, back 486 mm³)."""

    cavity_volumes_m3: tuple[float, ...] = (514e-9, 486e-9)
    group_names: tuple[str, ...] = ("front (vertical)", "back (horizontal)")
    tube_length_m: float = 12.0
    tube_id_m: float = 1.2e-3
    osr: int = 100
    adc_bits: int = 10
    active_min_Pa: float = -7000.0
    active_max_Pa: float = 10000.0
    transducer: Transducer = MPXV7002
    p0_Pa: float = P0_STANDARD_PA
    paper_rounding: bool = False

    def validate(self) -> "BudgetParams":
        for name in ("tube_length_m", "tube_id_m", "p0_Pa"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise UserError(f"{name}: must be a positive number, got {v!r}")
        if not 1 <= int(self.osr) <= 65535:
            raise UserError(f"osr: must be 1..65535, got {self.osr}")
        if not self.active_max_Pa > self.active_min_Pa:
            raise UserError("active span: max must exceed min")
        if len(self.cavity_volumes_m3) != len(self.group_names) or any(
                not (math.isfinite(v) and v > 0) for v in self.cavity_volumes_m3):
            raise UserError("cavity volumes: one positive value per group")
        return self


@dataclass(frozen=True)
class BudgetRow:
    """The budget of one arm group; "paper" figures use P_measure = the transducer's rated span
    (4 kPa), "datasheet" ones the ADC's full range through the transfer function (5 kPa)."""

    group: str
    v_cavity_mm3: float
    v_tube_mm3: float
    v_total_mm3: float
    loss_factor: float
    effective_bits: float
    span_counts_paper: float
    resolution_Pa_paper: float
    span_counts_datasheet: float
    resolution_Pa_datasheet: float
    resolution_mm3_datasheet: float
    transducer_peak_Pa: float
    transducer_use: float
    tube_tau_s: float
    frame_rate_Hz: float

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def budget(params: BudgetParams = BudgetParams()) -> tuple[BudgetRow, ...]:
    """Compute the budget for each arm group.

    >>> rows = budget(BudgetParams(paper_rounding=True))
    >>> [(round(r.v_total_mm3), r.loss_factor, round(r.span_counts_paper, 1)) for r in rows]
    [(14086, 27.4, 1588.3), (14058, 28.9, 1505.9)]
    """
    p = params.validate()
    v_tube = tube_volume_m3(p.tube_length_m, p.tube_id_m)
    eff = effective_bits(p.adc_bits, int(p.osr))
    active = p.active_max_Pa - p.active_min_Pa
    rows = []
    for name, vc in zip(p.group_names, p.cavity_volumes_m3):
        lf = loss_factor(vc, v_tube)
        if p.paper_rounding:
            lf = round(lf, 1)
        span_paper = digital_span_counts(eff, active, lf, p.transducer.rated_span_Pa)
        span_ds = digital_span_counts(eff, active, lf, p.transducer.adc_span_Pa)
        res_ds = active / span_ds
        v_total = vc + v_tube
        peak = max(abs(p.active_min_Pa), abs(p.active_max_Pa)) / lf
        rated = min(abs(p.transducer.p_min_Pa), abs(p.transducer.p_max_Pa))
        rows.append(BudgetRow(
            group=name, v_cavity_mm3=vc * 1e9, v_tube_mm3=v_tube * 1e9, v_total_mm3=v_total * 1e9,
            loss_factor=lf, effective_bits=eff,
            span_counts_paper=span_paper, resolution_Pa_paper=active / span_paper,
            span_counts_datasheet=span_ds, resolution_Pa_datasheet=res_ds,
            # a cavity-equivalent pressure δp is a volume change δV = V_cavity·δp/P0
            resolution_mm3_datasheet=vc * res_ds / p.p0_Pa * 1e9,
            transducer_peak_Pa=peak, transducer_use=peak / rated,
            tube_tau_s=tube_time_constant_s(p.tube_length_m, p.tube_id_m, vc, p.p0_Pa),
            frame_rate_Hz=frame_rate_Hz(int(p.osr)),
        ))
    return tuple(rows)


SWEEPS = {
    "tube_length_m": np.geomspace(0.5, 20.0, 60),
    "tube_id_m": np.linspace(0.5e-3, 3.0e-3, 60),
    "osr": np.unique(np.geomspace(1, 500, 60).astype(int)),
}


def sweep(params: BudgetParams, name: str, values) -> list[tuple[BudgetRow, ...]]:
    """The budget for each value of one parameter (others from ``params``)."""
    if name not in SWEEPS:
        raise UserError(f"sweep: unknown parameter {name!r} (one of {', '.join(SWEEPS)})")
    cast = int if name == "osr" else float
    return [budget(replace(params, **{name: cast(v)})) for v in values]


def plot_budget(params: BudgetParams, path) -> None:
    """PNG, one column per swept parameter (tube length, tube ID, OSR): top, the worst-case
    cavity-equivalent resolution (grey where the transducer saturates); bottom, the peak pressure
    at the transducer as a share of its rated ±2 kPa and the tube lag τ (or, for OSR, the frame
    rate)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), constrained_layout=True, sharex="col")
    labels = {"tube_length_m": ("tube length (m)", 1.0, params.tube_length_m),
              "tube_id_m": ("tube inner diameter (mm)", 1e3, params.tube_id_m * 1e3),
              "osr": ("oversampling ratio N", 1.0, params.osr)}
    for col, (name, values) in enumerate(SWEEPS.items()):
        rows = sweep(params, name, values)
        xlabel, scale, current = labels[name]
        x = np.asarray(values, float) * scale
        top, bottom = axes[0, col], axes[1, col]
        worst = np.array([max(r.resolution_Pa_datasheet for r in rs) for rs in rows])
        worst_paper = np.array([max(r.resolution_Pa_paper for r in rs) for rs in rows])
        use = np.array([max(r.transducer_use for r in rs) for rs in rows])
        top.plot(x, worst, "C0-", label="datasheet transfer (ADC range = 5 kPa)")
        top.plot(x, worst_paper, "C0--", label="paper eq. 2 (ADC range = 4 kPa)")
        sat = use > 1.0
        if sat.any():
            top.fill_between(x, 0, 1, where=sat, color="0.85", transform=top.get_xaxis_transform(),
                             label="transducer saturates")
        top.set_ylabel("worst resolution (Pa, cavity-equivalent)")
        top.set_yscale("log")
        top.set_title(f"vs {xlabel}")
        for ax in (top, bottom):
            ax.axvline(current, color="k", lw=0.8, ls=":")
            ax.grid(True, which="both", alpha=0.3)
        top.legend(fontsize=8)
        if name == "osr":
            rate = np.array([rs[0].frame_rate_Hz for rs in rows])
            bottom.plot(x, rate, "C3-", label="ADC-bound frame rate (Hz)")
            bottom.set_ylabel("board frame rate (Hz)")
            bottom.set_yscale("log")
            bottom.set_xscale("log")
        else:
            bottom.plot(x, use * 100, "C2-", label="peak at transducer / 2 kPa (%)")
            bottom.axhline(100, color="C2", ls="--", lw=0.8)
            bottom.set_ylabel("transducer use at peak (%)")
            bottom.set_yscale("log")
            ax2 = bottom.twinx()
            tau = np.array([max(r.tube_tau_s for r in rs) for rs in rows])
            ax2.plot(x, tau, "C1-", label="tube lag τ (s)")
            ax2.set_ylabel("tube lag τ (s)", color="C1")
            h1, l1 = bottom.get_legend_handles_labels()
            h2, l2 = ax2.get_legend_handles_labels()
            bottom.legend(h1 + h2, l1 + l2, fontsize=8)
            if name == "tube_length_m":
                bottom.set_xscale("log")
        if name == "osr":
            bottom.legend(fontsize=8)
        bottom.set_xlabel(xlabel)
    fig.suptitle(f"Sensing budget ({params.transducer.name}, cavity-equivalent active span "
                 f"{params.active_min_Pa / 1e3:g}…{params.active_max_Pa / 1e3:+g} kPa); dotted: "
                 f"L = {params.tube_length_m:g} m, d = {params.tube_id_m * 1e3:g} mm, N = {params.osr}")
    fig.savefig(path, dpi=100)
    plt.close(fig)
