"""``softphantom evaluate``: an estimate against the ground truth → report.html + PNGs."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from softphantom.cli.app import app, console
from softphantom.cli.options import (Body, NatnetVersion, Out, Overwrite, check_choice, check_output, check_positive,
                                     finite_number, staged_output)
from softphantom.errors import UserError


def _parse_lag(text: str) -> float | None:
    if text.strip().lower() == "auto":
        return None
    try:
        return finite_number(text, "--lag-ms")
    except UserError:
        raise UserError(f"--lag-ms must be 'auto' or a finite number of milliseconds, got {text!r}") from None


def _parse_window(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        a, b = (finite_number(x, "--rest-window-s") for x in text.split(","))
    except (UserError, ValueError):
        raise UserError(f"--rest-window-s must be 'START,END' in seconds, got {text!r}") from None
    if not b > a:
        raise UserError(f"--rest-window-s: END must be after START, got {text!r}")
    return a, b


def _check_reader_options(length_unit: str | None, rotation_order: str | None, clock: str | None,
                          natnet_version: str | None) -> None:
    """Refuse a bad tracker-reader option up front, whatever the truth file (a truth CSV uses none)."""
    from softphantom.errors import FileFormatError
    from softphantom.tracking.capture import SUPPORTED, parse_version
    from softphantom.tracking.motive import EULER_ORDERS, unit_scale
    from softphantom.tracking.rosbag import CLOCKS

    if length_unit is not None:
        try:
            unit_scale(length_unit)
        except FileFormatError:
            raise UserError(f"--length-unit: expected m, cm or mm, got {length_unit!r}") from None
    if rotation_order is not None:
        check_choice(rotation_order.strip().upper(), (*EULER_ORDERS, "QUATERNION"), "--rotation-order")
    if clock is not None:
        check_choice(clock, CLOCKS, "--clock")
    if natnet_version is not None:
        try:
            parse_version(natnet_version)
        except FileFormatError:
            check_choice(natnet_version, tuple("%d.%d" % v for v in SUPPORTED), "--natnet-version")


def _virtual_tracker_offset_ms(truth: Path) -> float | None:
    """The clock offset of a virtual run's tracker file (``tracker_motive.csv`` beside the run's
    ``virtual.json``, which records it), else None."""
    import json

    meta = truth.with_name("virtual.json")
    if truth.name != "tracker_motive.csv" or not meta.is_file():
        return None
    try:
        return float(json.loads(meta.read_text(encoding="utf-8"))["tracker"]["clock_offset_s"]) * 1e3
    except (OSError, ValueError, KeyError, TypeError):
        return None


@app.command("evaluate")
def evaluate_cmd(
    estimate: Path = typer.Option(..., "--estimate", help="Estimate CSV (softphantom estimate --out)."),
    truth: Path = typer.Option(..., "--truth", help="Truth CSV, or a tracker file: Motive CSV, ROS 1/2 bag, mcap, "
                               "NatNet capture (.pcap/.pcapng), a session recording's /tracker (.mcap)."),
    out: Out = ...,
    lag_ms: str = typer.Option("auto", "--lag-ms", help="Lag of the estimate behind the truth (ms), or 'auto' to measure it."),
    snapshot: Path = typer.Option(None, "--snapshot", help="VTU of the deformed phantom at peak load, for the 3-D view."),
    body: Body = None,
    rest_window_s: str = typer.Option(None, "--rest-window-s", help="START,END (s, tracker clock) of the rest pose; default the first 0.5 s."),
    clock: str = typer.Option(None, "--clock", help="Bag clock: header_stamp (default) or receive_time."),
    max_lag_ms: float = typer.Option(1000.0, "--max-lag-ms", help="Largest |lag| searched by 'auto' (ms)."),
    length_unit: str = typer.Option(None, "--length-unit", help="Motive CSV without 'Length Units': m, cm or mm."),
    rotation_order: str = typer.Option(None, "--rotation-order", help="Motive CSV Euler angles without 'Rotation Type': e.g. XYZ."),
    overwrite: Overwrite = False,
    natnet_version: NatnetVersion = None,
    clock_offset_ms: float = typer.Option(None, "--clock-offset-ms", help="The truth's clock minus the estimate's at "
                                          "the same instant (ms), if known (a virtual run: 1000 × tracker.clock_offset_s "
                                          "of virtual.json): splits the lag into that offset and the estimator's latency."),
) -> None:
    """Compare an estimate with the ground truth: metrics per DoF, Table I, report.html and its PNGs in
    the directory --out. --body: of a tracker truth file."""
    from softphantom.evaluation import evaluate, read_estimate, read_truth, write_report
    from softphantom.evaluation.metrics import signed

    check_output(out, overwrite=overwrite, directory=True)
    lag = _parse_lag(lag_ms)
    window = _parse_window(rest_window_s)
    check_positive(max_lag_ms, "--max-lag-ms", "ms")
    _check_reader_options(length_unit, rotation_order, clock, natnet_version)
    est = read_estimate(estimate)
    tru = read_truth(truth, body=body, rest_window_s=window, clock=clock,
                     length_unit=length_unit, rotation_order=rotation_order, natnet_version=natnet_version)
    offset_from = "given"
    if clock_offset_ms is None and (known := _virtual_tracker_offset_ms(truth)) is not None:
        clock_offset_ms, offset_from = known, "from virtual.json beside the tracker file"
    ev = evaluate(tru, est, lag_ms=lag, max_lag_s=max_lag_ms * 1e-3, clock_offset_ms=clock_offset_ms,
                  offset_source=offset_from)
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        report, rows = write_report(work, tru, est, ev, snapshot=snapshot, title=f"{estimate.name} vs {truth.name}")
    report = out / report.relative_to(work)

    t = Table(title=f"Estimate vs truth — lag {signed(ev.lag_ms)} ms ({ev.lag_source})")
    for h in ("DoF", "RMSE", "bias", "max |err|", "r", "lag ms", "max |truth|"):
        t.add_column(h, justify="right")
    f = lambda v, d=2: "–" if v != v else f"{v:.{d}f}"  # noqa: E731  (NaN → dash)
    for s in ev.dof + ev.force:
        t.add_row(f"{s.name} ({s.unit})", f(s.rmse), f(s.bias), f(s.max_abs), f(s.corr, 3), f(s.lag_ms, 1), f(s.peak_truth))
    console.print(t)
    for s in ev.targets:
        console.print(f"target {s.name}: RMS 3-D error {s.rmse:.2f} mm, max {s.max_abs:.2f} mm")
    flags = ", ".join(f"{r.ref.dof} {r.observed:.1f} {r.ref.unit} {r.flag} {r.ref.study}" for r in rows)
    console.print(f"Table I (max |Δ| of the truth): {flags}", highlight=False)
    console.print(ev.lag_parts.explain(), highlight=False, soft_wrap=True)
    for n in ev.notes:
        console.print(f"note: {n}", highlight=False)
    console.print(f"report: {report}", highlight=False)
