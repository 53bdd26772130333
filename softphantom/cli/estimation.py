"""``softphantom estimate``: the real-time inverse estimator over a sensor source → estimate CSV."""

from __future__ import annotations

import time

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import (At, AtlasFYSplitN, AtlasGrid, AtlasXAxis, DraftAtlas, DurationS, Envelope,
                                     Estimator, LagCompensation, MaxForceN, ModelDir, OnNewBoard, Out, Overwrite,
                                     P0KPa, Scheduler, Source, TareS, TubeIdMm, TubeLengthM, check_choice,
                                     check_output, check_positive, staged_output, stopped)
from softphantom.errors import UserError
from softphantom.estimation.session import source_contact  # noqa: F401  (cli/live.py imports it from here)

_SOURCES = "serial:PORT, replay:FILE or virtual:SCENARIO"


def check_source_options(source: str, *, max_force_N: float, on_new_board: str, tube_length_m: float | None,
                         tube_id_mm: float | None, tare_s: float | None = None, qp_solver: str | None = None) -> None:
    """Refuse a bad ``--source`` kind or estimator/bench option of ``estimate`` and ``live`` before
    any model is read (each is otherwise used only by some sources, or late)."""
    from softphantom.estimation.qp import QP_SOLVERS
    from softphantom.sensing.bench import NEW_BOARD_POLICIES
    from softphantom.sources import SOURCES, usage

    scheme = source.partition(":")[0]
    if scheme not in SOURCES:
        raise UserError(f"unknown --source {source!r} (unknown kind {scheme!r}); use {usage()}")
    check_positive(max_force_N, "--max-force-N", "N")
    check_choice(on_new_board, NEW_BOARD_POLICIES, "--on-new-board")
    check_positive(tube_length_m, "--tube-length-m", "m")
    check_positive(tube_id_mm, "--tube-id-mm", "mm")
    check_positive(tare_s, "--tare-s", "s")
    if qp_solver is not None:
        check_choice(qp_solver, QP_SOLVERS, "--qp-solver")


def check_lag_option(mode: str | None) -> None:
    """Refuse a bad ``--lag-compensation`` before anything is opened."""
    from softphantom.estimation.lag import MODES

    if mode is not None:
        check_choice(mode, MODES, "--lag-compensation")


def open_sensor_source(spec: str, model, *, tare_s: float = 1.0, on_new_board: str = "stop", **options):
    """The opened ``--source`` (:class:`softphantom.sensing.bench.OpenedSource`, sensor samples) for
    ``estimate`` and ``live`` (its notes printed); ``options``: ``tube_length_m``, ``tube_id_mm``,
    ``p0_kPa`` (None = default)."""
    import contextlib

    from softphantom.progress import status
    from softphantom.sources import open_source

    virtual = spec.partition(":")[0] == "virtual"
    with status(f"virtual phantom: solving scenario {spec.partition(':')[2]!r}", console) if virtual \
            else contextlib.nullcontext():
        opened = open_source(spec, model, options=options, tare_s=tare_s, on_new_board=on_new_board,
                             want="measurements")
    for note in opened.notes:
        console.print(f"note: {note}", highlight=False, soft_wrap=True)
    return opened


def lag_for(mode: str | None, opened, source: str):
    """The lag compensator of an opened source (None: off) and the estimate file's metadata about
    it; a warning line printed when a recording lacks the tube settings."""
    from softphantom.estimation.lag import lag_compensation

    comp, meta, warning = lag_compensation(mode, opened.bench, tube_missing=opened.meta.get("tube_missing"),
                                           source=source)
    if warning:
        console.print(warning, style="yellow", highlight=False, soft_wrap=True)
    return comp, meta


def warn_outside(summary: dict, envelope: str | None) -> None:
    """One warning line when estimates were clamped at the atlas envelope's faces (in_envelope 0)."""
    n, k = summary["estimates"], summary["outside"]
    console.print(f"warning: {k} of {n} estimates ({k / max(n, 1):.0%}) at or beyond the atlas envelope's faces, "
                  f"clamped (in_envelope 0): widen --envelope (now {envelope or 'the default'}); most of a run "
                  "clamped at rest: was the tare (serial) taken under load?",
                  style="yellow", highlight=False, soft_wrap=True)


def _progress_line():
    """``on_estimate`` printing one line a second: the sample count, time, force, position, step time."""
    last = [0.0]

    def show(e, n):
        now = time.monotonic()
        if now - last[0] >= 1.0:
            last[0] = now
            f = e.force
            p = e.pose.to_mm_deg()
            console.print(f"{n:7d}  t {e.t:8.2f} s  F ({f[0]:+.2f}, {f[1]:+.2f}, {f[2]:+.2f}) N  "
                          f"xyz ({p[0]:+.2f}, {p[1]:+.2f}, {p[2]:+.2f}) mm  step {e.step_time * 1e3:.2f} ms  "
                          f"{e.qp_status}", highlight=False)
    return show


def print_event(marker) -> None:
    """One console line for a link event's marker estimate."""
    console.print(f"{marker.t:10.2f} s  {marker.status}", highlight=False, markup=False)


@app.command("estimate")
def estimate_cmd(
    model_dir: ModelDir = ...,
    source: Source = ...,
    out: Out = ...,
    at: At = None,
    max_force_N: MaxForceN = 10.0,
    qp_solver: str = typer.Option("daqp", "--qp-solver", help="QP solver: daqp | quadprog."),
    estimator: Estimator = "atlas",
    scheduler: Scheduler = None,
    atlas_grid: AtlasGrid = None,
    atlas_x_axis: AtlasXAxis = None,
    atlas_f_y_split: AtlasFYSplitN = None,
    envelope: Envelope = None,
    mode: str = typer.Option("auto", "--mode", help="refresh estimator: sync (deterministic) | async (background "
                             "equilibrium) | auto (async for serial, sync otherwise)."),
    tare_s: TareS = 1.0,
    p0_kPa: P0KPa = None,
    tube_length_m: TubeLengthM = None,
    tube_id_mm: TubeIdMm = None,
    on_new_board: OnNewBoard = "stop",
    lag_compensation: LagCompensation = None,
    duration_s: DurationS = None,
    draft: DraftAtlas = False,
    require_full: bool = typer.Option(False, "--require-full", help="Atlas: refuse a draft atlas (atlas build "
                                      "--draft), which is used where the model has no full one."),
    overwrite: Overwrite = False,
) -> None:
    """Estimate force, urethra pressure, 6-DoF pose and target shifts from the cavity volumes, into the
    estimate CSV --out (a metadata line, then one row per sample). A missing atlas is built (on
    --scheduler, with the --atlas-* options)."""
    import contextlib

    from softphantom.design import load_model
    from softphantom.design.params import check_contact
    from softphantom.estimation.atlas.config import model_atlas_config
    from softphantom.estimation.select import atlas_config_from_options, check_estimator_kind
    from softphantom.estimation.session import EstimateSession

    check_estimator_kind(estimator)
    atlas_config_from_options(atlas_grid, envelope, atlas_x_axis, atlas_f_y_split)  # bad options fail first
    if mode not in ("auto", "sync", "async"):
        raise UserError(f"--mode must be auto, sync or async, got {mode!r}")
    if duration_s is not None and not duration_s > 0:
        raise UserError(f"--duration-s must be > 0, got {duration_s}")
    if p0_kPa is not None and not p0_kPa > 0:
        raise UserError(f"--p0-kPa must be > 0, got {p0_kPa}")
    check_source_options(source, max_force_N=max_force_N, qp_solver=qp_solver, tare_s=tare_s,
                         tube_length_m=tube_length_m, tube_id_mm=tube_id_mm, on_new_board=on_new_board)
    check_lag_option(lag_compensation)
    check_output(out, overwrite=overwrite, directory=False)
    if not (model_dir / "model.npz").is_file():
        raise UserError(f"--model {model_dir}: not a model directory (no model.npz; run softphantom design)")
    model = load_model(model_dir)
    if at is not None:
        check_contact(at, list(model.p_ext), "--at")
    acfg = atlas_config_from_options(atlas_grid, envelope, atlas_x_axis, atlas_f_y_split,
                                     base=model_atlas_config(model.element_order, model_dir))
    opened = open_sensor_source(source, model, tare_s=tare_s, on_new_board=on_new_board,
                                tube_length_m=tube_length_m, tube_id_mm=tube_id_mm, p0_kPa=p0_kPa)
    session = EstimateSession.start(model_dir, model, opened, source, at=at, lag_mode=lag_compensation)
    if session.lag_warning:
        console.print(session.lag_warning, style="yellow", highlight=False, soft_wrap=True)
    session.open_estimator(estimator, max_force_N=max_force_N, qp_solver=qp_solver, mode=mode, scheduler=scheduler,
                           atlas=acfg, require_full=require_full, draft=draft)
    # a live source's estimates cannot be made again: written in place and kept on Ctrl-C (closed
    # cleanly); from a file, the CSV appears only when complete
    if session.live:
        session.prepare_output(out)
    target = contextlib.nullcontext(out) if session.live else staged_output(out, overwrite=overwrite, directory=False)
    with target as path, session:
        how = f"mode {session.config.mode}" if estimator == "refresh" else "no background work"
        console.print(f"estimator {estimator} ready in {session.ready_s:.1f} s ({len(model.nodes)} nodes, "
                      f"{how}, contact {session.contact}, |F_i| <= {max_force_N:g} N, QP {qp_solver})", highlight=False)
        note = session.draft_note()
        if note:
            console.print(note, highlight=False, soft_wrap=True)
        rest, warning = session.rest_check()
        if warning:
            console.print(f"warning: {warning}", style="yellow", highlight=False, soft_wrap=True)
        try:
            s = session.run(path, _progress_line(), metadata=session.metadata(rest), duration_s=duration_s,
                            on_event=print_event)
        except KeyboardInterrupt:
            if not session.live:
                raise
            stopped(f"stopped (Ctrl-C); the estimates so far are in {out}")
    ev = ", ".join(f"{k} {v}" for k, v in s["events"].items()) or "none"
    if s["outside"]:
        warn_outside(s, envelope)
    console.print(f"wrote {s['estimates']} estimates to {out} ({s['rejected']} rejected, {s['skipped']} skipped "
                  f"(estimator behind); link events: {ev}; "
                  f"{s['rate_Hz']:.0f} Hz, step p50 {s['step_ms_p50']:.2f} ms, p99 {s['step_ms_p99']:.2f} ms)",
                  highlight=False)
