"""``softphantom sensing budget`` and ``softphantom acquire``."""

from __future__ import annotations

import csv
from pathlib import Path

import typer
from rich.table import Table

from softphantom.cli.app import app, console
from softphantom.cli.options import (At, ConnectTimeoutS, DurationS, ModelDir, OnNewBoard, Osr, Out, Overwrite, P0KPa,
                                     TareS, TubeIdMm, TubeLengthM, check_output, staged_output, stopped)
from softphantom.errors import UserError
from softphantom.sensing.measurement import ARM_CAVITY_VOLUMES_M3, TUBE_ID_M, TUBE_LENGTH_M

sensing_app = typer.Typer(help="Sensing chain: resolution budget.", no_args_is_help=True)
app.add_typer(sensing_app, name="sensing")


@sensing_app.command("budget")
def budget_cmd(
    tube_length_m: TubeLengthM = TUBE_LENGTH_M,
    tube_id_mm: TubeIdMm = TUBE_ID_M * 1e3,
    osr: Osr = 100,
    front_cavity_mm3: float = typer.Option(ARM_CAVITY_VOLUMES_M3[0] * 1e9, "--front-cavity-mm3",
                                           help="Front (vertical) arm cavity (mm³)."),
    back_cavity_mm3: float = typer.Option(ARM_CAVITY_VOLUMES_M3[2] * 1e9, "--back-cavity-mm3",
                                          help="Back (horizontal) arm cavity (mm³)."),
    active_min_kPa: float = typer.Option(-7.0, "--active-min-kPa", help="Cavity-equivalent active span, low end (kPa)."),
    active_max_kPa: float = typer.Option(10.0, "--active-max-kPa", help="Cavity-equivalent active span, high end (kPa)."),
    p0_kPa: P0KPa = 101.325,
    paper_rounding: bool = typer.Option(False, "--paper-rounding", help="Round loss factors to 0.1 as the paper does."),
    out: Out = None,
    overwrite: Overwrite = False,
) -> None:
    """Resolution budget of the arm sensing chain (paper eq. 1–2) and how it moves; with --out, a
    directory for budget.csv and budget.png."""
    from softphantom.sensing.budget import BudgetParams, budget, plot_budget

    if out is not None:
        check_output(out, overwrite=overwrite, directory=True)
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
        with staged_output(out, overwrite=overwrite, directory=True) as work:
            with open(work / "budget.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow([k for k, _, _ in cols])
                for r in rows:
                    w.writerow([r.group] + [f"{getattr(r, k):.6g}" for k, _, _ in cols[1:]])
            plot_budget(params, work / "budget.png")
        console.print(f"wrote {out / 'budget.csv'} and {out / 'budget.png'}")


def _status_table(stats, elapsed_s: float, rows: int, out: Path, arm_names: tuple[str, ...]):
    d = stats.decoder
    t = Table(title=f"acquire → {out}  ({elapsed_s:.1f} s, {rows} rows)", show_header=False)
    t.add_column("what")
    t.add_column("value", justify="right")
    t.add_row("state", stats.state)
    t.add_row("rate (Hz)", f"{stats.rate_Hz:.1f}")
    t.add_row("firmware / OSR", f"{stats.firmware or '?'} / {stats.osr or '?'}")
    t.add_row("CRC errors / malformed / content", f"{d.crc_errors} / {d.malformed + d.overflows} / {d.content_errors}")
    t.add_row("seq gaps (frames lost) / duplicates", f"{d.seq_gaps} ({d.frames_lost}) / {d.duplicates}")
    t.add_row("silent events / reconnects", f"{stats.silent_events} / {stats.reconnects}")
    m = stats.last
    if m is not None:
        for i, a in enumerate(arm_names):
            t.add_row(f"dp_{a}_kPa", f"{m.dp[i] / 1e3:+.4f}")
        for c, p in m.cavity_pressures.items():
            t.add_row(f"p_{c}_kPa", f"{p / 1e3:+.2f}")
        # the values above are the last sample's: while no sample comes, say so beside its status
        t.add_row("status", m.status if stats.state == "ok" else f"{stats.state}: no sample (the last: {m.status})")
    return t


@app.command("acquire")
def acquire_cmd(
    port: str = typer.Option(..., "--port", help="Serial port or pyserial URL (/dev/ttyACM0, loop://, socket://)."),
    out: Out = ...,
    duration_s: DurationS = None,
    osr: Osr = None,
    baud: int = typer.Option(115_200, "--baud", min=1, help="Serial baud rate."),
    tare_s: TareS = 1.0,
    no_tare: bool = typer.Option(False, "--no-tare", help="Skip the tare; use the datasheet zero offsets."),
    p0_kPa: P0KPa = None,
    tube_length_m: TubeLengthM = None,
    tube_id_mm: TubeIdMm = None,
    model_dir: ModelDir = None,
    at: At = "on-centre",
    on_new_board: OnNewBoard = "stop",
    connect_timeout_s: ConnectTimeoutS = 5.0,
) -> None:
    """Record the sensing board: tare at rest, then append every frame to the recording --out (a CSV
    with a JSON metadata line; never overwritten) with live status; link events (silent, unplugged,
    replugged, a new board) become marker rows. --model: the volume channels' cavities from its
    design (default: the paper's 514/486 mm³); --at: the trial's contact point, stored, so estimate
    on the replay needs no option; --osr: asked of the board (default: the board's own)."""
    import time
    from datetime import datetime, timezone

    from rich.live import Live

    from softphantom import __version__
    from softphantom.design.params import DERIVED_CONTACTS, check_contact
    from softphantom.sensing.bench import BenchConfig, RetareSource, check_link_options, tare_at_rest
    from softphantom.sensing.chain import to_measurement
    from softphantom.sensing.recording import Recorder
    from softphantom.sensing.sources import SerialSource

    # every option's value before the port or the model is opened
    if duration_s is not None and not duration_s > 0:
        raise UserError(f"--duration-s: must be > 0, got {duration_s}")
    if model_dir is None:
        check_contact(at, DERIVED_CONTACTS, "--at", "the default design", "--model for a design's [contacts]")
    check_link_options(tare_s, connect_timeout_s, on_new_board)
    if out.exists():
        raise UserError(f"--out {out}: exists; recordings are never overwritten")
    model = None
    if model_dir is not None:
        from softphantom.design import load_model

        if not (model_dir / "model.npz").is_file():
            raise UserError(f"--model {model_dir}: not a model directory (no model.npz; run softphantom design)")
        model = load_model(model_dir)
        check_contact(at, list(model.p_ext), "--at")
    bench = BenchConfig.from_options(tube_length_m, tube_id_mm, p0_kPa, model=model)
    chain = bench.chain()
    serial_src = SerialSource(port, chain, baud=baud, osr=osr)
    src = RetareSource(serial_src, bench, on_new_board, tare_s, f"--port {port}")
    rec = None
    t_start = time.monotonic()
    need = 0.0 if no_tare else tare_s
    try:
        with Live(console=console, refresh_per_second=4, transient=False) as live:
            # 1. tare window (or just wait for the first frame)
            tare, window = tare_at_rest(
                serial_src, bench, need, label=f"--port {port}", connect_timeout_s=connect_timeout_s,
                on_read=lambda _: live.update(_status_table(serial_src.stats(), time.monotonic() - t_start, 0, out,
                                                            chain.arm_names)))
            serial_src.set_tare(tare)
            serial_src.events()             # connecting is not an outage
            st = serial_src.stats()
            meta = {"softphantom": __version__, "protocol_version": st.decoder.version,
                    "firmware": st.firmware, "osr": st.osr, "p0_Pa": bench.p0_Pa, "port": port, "baud": baud,
                    "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "tare": tare.to_dict(), "chain": chain.summary(), "bench": bench.to_meta(), "contact": at,
                    "on_new_board": on_new_board, "model": str(model_dir) if model_dir else None}
            rec = Recorder(out, meta, layout=chain.layout)
            for m in window:        # the tare window is part of the recording, re-converted
                rec.write(to_measurement(m.t, m.seq, m.t_board, m.raw, m.osr, chain, tare))
            # 2. record
            last_ui = 0.0
            while duration_s is None or time.monotonic() - t_start < duration_s + need:
                batch = []
                try:
                    batch = src.read(0.05) or []
                finally:
                    for ev in src.events():     # a marker never reorders the file: held before the batch
                        rec.write_event(ev, next_t=batch[0].t if batch else None)
                        console.print(f"{ev.t:10.2f} s  {ev.kind}: {ev.detail}", highlight=False, markup=False)
                for m in batch:
                    rec.write(m)
                rec.tick()
                now = time.monotonic()
                if now - last_ui > 0.25:
                    live.update(_status_table(src.stats(), now - t_start, rec.rows, out, chain.arm_names))
                    last_ui = now
    except KeyboardInterrupt:
        interrupted = True
    else:
        interrupted = False
    finally:  # every way out (Ctrl-C, a new board under --on-new-board stop, an error) says what was kept
        if rec is not None:
            rec.close()
        src.close()
        if rec is not None:
            d = src.stats().decoder
            console.print(f"wrote {rec.rows} rows and {rec.events} link events to {out} (CRC errors "
                          f"{d.crc_errors}, frames lost {d.frames_lost}, duplicates {d.duplicates}, reconnects "
                          f"{src.stats().reconnects})", highlight=False, soft_wrap=True)
    if interrupted:
        stopped()  # the recording is closed and complete; exit 130
