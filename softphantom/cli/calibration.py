"""``softphantom calibrate``: fit the model and the sensors to a bench session → a calibrated model
directory, ``report.html``, ``parameters.csv``."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from softphantom.cli.app import app, console
from softphantom.cli.options import (ModelDir, Out, Overwrite, Scheduler, Workers, check_output, check_workers,
                                     finite_number, staged_output)
from softphantom.errors import UserError


def _contact_names(model_dir: Path) -> tuple[str, ...] | None:
    """The model's contact points (its p_ext) from its design file, before the model is read; None
    when it has none (calibrate then refuses the directory)."""
    from softphantom.design import load_design

    toml = model_dir / "design.toml"
    if not toml.is_file():
        return None
    design = load_design(toml)
    return design.contact_names


def _contact(text: str, option: str = "--contact", names: tuple[str, ...] | None = None):
    if "," not in text:
        from softphantom.design.params import check_contact

        return text if names is None else check_contact(text, names, option, hint="or X,Y,Z_mm")
    try:
        v = [finite_number(x, option) * 1e-3 for x in text.split(",")]
    except UserError:
        raise UserError(f"{option}: expected a contact name or X,Y,Z_mm, got {text!r}") from None
    if len(v) != 3:
        raise UserError(f"{option}: expected 3 numbers (mm), got {len(v)}")
    return tuple(v)


def _measured(texts: list[str]) -> tuple[tuple[str, float, float | None], ...]:
    """``NAME=VALUE`` (held at VALUE) or ``NAME=VALUE:SD`` (VALUE ± SD as its prior), displayed units."""
    out = []
    for text in texts:
        name, eq, rest = text.partition("=")
        if not eq or not name.strip():
            raise UserError(f"--measured: expected NAME=VALUE or NAME=VALUE:SD, got {text!r}")
        value, colon, sd = rest.partition(":")
        out.append((name.strip(), finite_number(value, f"--measured {name.strip()}"),
                    finite_number(sd, f"--measured {name.strip()} (SD)") if colon else None))
    return tuple(out)


def _pairs(recordings: list[Path], truths: list[Path], contacts: list[str], known: list[Path], what: str,
           option: str = "--contact", names: tuple[str, ...] | None = None):
    from softphantom.calibration import SessionSpec

    if len(recordings) != len(truths):
        raise UserError(f"{what}: {len(recordings)} recording(s) but {len(truths)} truth take(s); give them in pairs")
    if contacts and len(contacts) not in (1, len(recordings)):
        raise UserError(f"{what}: give one --contact for all sessions or one per session, got {len(contacts)}")
    if known and len(known) != len(recordings):
        raise UserError(f"--known-loads: one file per --recording (in order), got {len(known)} for {len(recordings)}")
    cs = [_contact(c, option, names) for c in contacts] if contacts else ["on-centre"]
    cs = cs * len(recordings) if len(cs) == 1 else cs
    return [SessionSpec(r, t, c, known[i] if known else None) for i, (r, t, c) in enumerate(zip(recordings, truths, cs))]


def _check_files(specs, prefix: str = "--") -> None:
    """Every session's files exist, before any is read (a session is read recording first): one
    line naming the option and the file. A take may be a ROS 2 bag's directory."""
    for sp in specs:
        for opt, p in ((f"{prefix}recording", sp.recording), (f"{prefix}truth", sp.truth),
                       ("--known-loads", sp.known_loads)):
            if p is None:
                continue
            if not Path(p).exists():
                raise UserError(f"{opt} {p}: no such file")
            if Path(p).is_dir() and opt != f"{prefix}truth":
                raise UserError(f"{opt} {p}: is a directory (expected a file)")


@app.command("calibrate")
def calibrate_cmd(
    model: ModelDir = ...,
    recording: list[Path] = typer.Option(..., "--recording", help="Bench recording (acquire / virtual run); repeat for several sessions."),
    truth: list[Path] = typer.Option(..., "--truth", help="Tracker take of the same session (Motive CSV, bag, mcap, truth CSV); one per --recording."),
    out: Out = ...,
    contact: list[str] = typer.Option(None, "--contact", help="Contact point per session: on-centre, off-centre, one of the design's [contacts] or X,Y,Z_mm (default on-centre)."),
    known_loads: list[Path] = typer.Option(None, "--known-loads", help="CSV t_s, force_x_N, force_y_N, force_z_N per session (a force sensor or hung weights)."),
    holdout_recording: list[Path] = typer.Option(None, "--holdout-recording", help="Recording kept out of the fit, to check the calibration on."),
    holdout_truth: list[Path] = typer.Option(None, "--holdout-truth", help="Take of each --holdout-recording."),
    holdout_contact: list[str] = typer.Option(None, "--holdout-contact", help="Contact point of the held-out sessions."),
    fix: list[str] = typer.Option(None, "--fix", help="Hold a parameter at its nominal value (repeat), e.g. tube_volume_factor, lag (every session's), drift (every session's pressure drift at 0)."),
    measured: list[str] = typer.Option(None, "--measured", help="A parameter measured on the bench apart from the session, NAME=VALUE (held there) or NAME=VALUE:SD (its prior), displayed units; repeat. E.g. gain_back_xpos=1.04:0.01 from a reference gauge."),
    law: str = typer.Option(None, "--law", help="Fit under this law instead of the design's (neo-hookean, yeoh, corotational): every material at its small-strain E and ν (Yeoh: C10 = μ/2, C20 = C30 = 0, its shape then fitted); the calibrated model is written under it, the nominal checks keep the design's."),
    max_keyframes: int = typer.Option(16, "--max-keyframes", help="Distinct loads used per session."),
    contact_radius_mm: float = typer.Option(4.0, "--contact-radius-mm", help="Radius of the contact patch the force is spread on (mm)."),
    scheduler: Scheduler = None,
    workers: Workers = None,
    overwrite: Overwrite = False,
) -> None:
    """Fit material stiffness, sensor gains/offsets/drift, tube volume, registration and lag to a bench
    session by least squares over forward FEM solves; print the parameters with 95 % intervals and
    write the calibrated model, report.html and parameters.csv into the new directory --out."""
    from softphantom.calibration import FitOptions, calibrate, parameter_set, write_calibration
    from softphantom.calibration.fit import Parameter, ratio_names
    from softphantom.calibration.forward import FIT_LAWS

    check_workers(workers)
    if not (contact_radius_mm > 0 and contact_radius_mm < 50):
        raise UserError(f"--contact-radius-mm must be in (0, 50), got {contact_radius_mm}")
    if law is not None and law not in FIT_LAWS:
        raise UserError(f"--law {law!r}: not a law the calibration can fit (have {', '.join(FIT_LAWS)})")
    if not 3 <= max_keyframes <= 200:
        raise UserError(f"--max-keyframes must be in 3..200, got {max_keyframes}")
    check_output(out, overwrite=overwrite, directory=True)
    names = _contact_names(model)
    specs = _pairs(recording, truth, contact or [], known_loads or [], "--recording/--truth", names=names)
    hold = _pairs(holdout_recording or [], holdout_truth or [], holdout_contact or [], [],
                  "--holdout-recording/--holdout-truth", "--holdout-contact", names)
    opts = FitOptions(fix=tuple(fix or ()), measured=_measured(measured or []), radius_m=contact_radius_mm * 1e-3, law=law)
    # refuse a bad name or value before any work (a law's ratio, e.g. yeoh_C20_C10_bulb, is
    # checked against the model's laws once the model is read)
    ratios = ratio_names()
    known = [p.name for p in parameter_set()]
    bad = [f for f in opts.fix if f not in known and f not in ratios and not f.startswith(("lag", "drift"))]
    if bad:
        raise UserError(f"--fix: unknown parameter(s) {', '.join(bad)}; have {', '.join(known)}, lag, drift "
                        "or a law's ratio")
    parameter_set(measured=tuple(m for m in opts.measured if m[0] not in ratios))
    for name, value, sd in (m for m in opts.measured if m[0] in ratios):
        Parameter(name, 0.0, 1.0).measured(value, sd)
    _check_files(specs)
    _check_files(hold, "--holdout-")
    cal = calibrate(model, specs, hold, options=opts, scheduler=scheduler, n_workers=workers,
                    max_keyframes=max_keyframes)
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        written = write_calibration(cal, work, shown=out)
    paths = {"model": out, "report": out / "report.html"}
    f = cal.fit
    t = Table(title=f"Calibration: objective {f.history[0]:.4g} → {f.history[-1]:.4g}, {f.solves} forward solves, {f.seconds:.0f} s")
    for c in ("parameter", "nominal", "calibrated", "95 % interval", "identifiable"):
        t.add_column(c, justify="right" if c != "parameter" else "left", overflow="fold")
    for i, n in enumerate(f.names):
        ci = f"[{f.ci95[i, 0]:.4g}, {f.ci95[i, 1]:.4g}]" if f.free[i] else "fixed"
        t.add_row(n, f"{f.nominal[i]:.4g}", f"{f.value[i]:.4g}", ci,
                  ("yes" if f.identifiable[i] else "NO") if f.free[i] else "–")
    console.print(t)
    for w in f.warnings:
        console.print(f"warning: {w}", markup=False, highlight=False, style="yellow")
    if cal.held_out is not None:
        from softphantom.calibration import rmse_ratio, rmse_ratio_interval

        lo, hi = rmse_ratio_interval(cal.held_out)
        console.print(f"held-out pose RMSE, nominal / calibrated: {rmse_ratio(cal.held_out):.2f} "
                      f"({lo:.2f}–{hi:.2f} over its keyframes resampled, 90 %)", markup=False)
    console.print(f"atlas: {written['atlas']}", markup=False, highlight=False, soft_wrap=True)
    console.print(f"wrote {paths['model']} (report: {paths['report']})", markup=False, highlight=False)
