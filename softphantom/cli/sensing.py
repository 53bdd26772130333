"""``softphantom sensing budget`` and ``softphantom acquire``."""

from __future__ import annotations

import csv
from pathlib import Path

import typer
from rich.table import Table

from softphantom.cli.app import app, console
from softphantom.errors import UserError

sensing_app = typer.Typer(help="Sensing chain: resolution budget.", no_args_is_help=True)
app.add_typer(sensing_app, name="sensing")


@sensing_app.command("budget")
def budget_cmd(
    tube_length_m: float = typer.Option(12.0, "--tube-length-m", help="Tube length per arm (m)."),
    tube_id_mm: float = typer.Option(1.2, "--tube-id-mm", help="Tube inner diameter (mm)."),
    osr: int = typer.Option(100, "--osr", help="Readings summed per channel per frame (N)."),
    front_cavity_mm3: float = typer.Option(514.0, "--front-cavity-mm3", help="Front (vertical) arm cavity (mm³)."),
    back_cavity_mm3: float = typer.Option(486.0, "--back-cavity-mm3", help="Back (horizontal) arm cavity (mm³)."),
    active_min_kPa: float = typer.Option(-7.0, "--active-min-kPa", help="Cavity-equivalent active span, low end (kPa)."),
    active_max_kPa: float = typer.Option(10.0, "--active-max-kPa", help="Cavity-equivalent active span, high end (kPa)."),
    p0_kPa: float = typer.Option(101.325, "--p0-kPa", help="Absolute ambient pressure (kPa)."),
    paper_rounding: bool = typer.Option(False, "--paper-rounding", help="Round loss factors to 0.1 as the paper does."),
    out: Path = typer.Option(None, "--out", help="Directory for budget.csv and budget.png."),
) -> None:
    """Resolution budget of the arm sensing chain (paper eq. 1–2) and how it moves."""
    from softphantom.sensing.budget import BudgetParams, budget, plot_budget

    params = BudgetParams(
        cavity_volumes_m3=(front_cavity_mm3 * 1e-9, back_cavity_mm3 * 1e-9),
        tube_length_m=tube_length_m, tube_id_m=tube_id_mm * 1e-3, osr=osr,
        active_min_Pa=active_min_kPa * 1e3, active_max_Pa=active_max_kPa * 1e3,
        p0_Pa=p0_kPa * 1e3, paper_rounding=paper_rounding)
    rows = budget(params)
    cols = [("group", "arm group", "{}"), ("v_cavity_mm3", "V_cavity mm³", "{:.1f}"),
            ("v_tube_mm3", "V_tube mm³", "{:.1f}"), ("v_total_mm3", "V_total mm³", "{:.1f}"),
            ("loss_factor", "loss factor", "{:.2f}"), ("effective_bits", "eff. bits", "{:.2f}"),
            ("span_counts_paper", "span levels (paper, 4 kPa)", "{:.1f}"),
            ("resolution_Pa_paper", "resol. Pa (paper)", "{:.2f}"),
            ("span_counts_datasheet", "span levels (datasheet, 5 kPa)", "{:.1f}"),
            ("resolution_Pa_datasheet", "resol. Pa (datasheet)", "{:.2f}"),
            ("resolution_mm3_datasheet", "resol. mm³", "{:.4f}"),
            ("transducer_peak_Pa", "peak at transducer Pa", "{:.0f}"),
            ("transducer_use", "use of ±2 kPa", "{:.1%}"), ("tube_tau_s", "tube τ s", "{:.3f}"),
            ("frame_rate_Hz", "frame rate Hz", "{:.1f}")]
    table = Table(title=f"Sensing budget: tube {tube_length_m:g} m × {tube_id_mm:g} mm, N = {osr}")
    table.add_column("quantity")
    for r in rows:
        table.add_column(r.group, justify="right")
    for key, label, fmt in cols[1:]:
        table.add_row(label, *[fmt.format(getattr(r, key)) for r in rows])
    console.print(table)
    worst = max(rows, key=lambda r: r.resolution_Pa_datasheet)
    console.print(f"worst case: {worst.resolution_Pa_datasheet:.2f} Pa (datasheet), "
                  f"{max(r.resolution_Pa_paper for r in rows):.2f} Pa (paper eq. 2) — {worst.group}")
    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--out {out}: cannot create ({exc.strerror})") from None
        with open(out / "budget.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow([k for k, _, _ in cols])
            for r in rows:
                w.writerow([r.group] + [f"{getattr(r, k):.6g}" for k, _, _ in cols[1:]])
        plot_budget(params, out / "budget.png")
        console.print(f"wrote {out / 'budget.csv'} and {out / 'budget.png'}")
