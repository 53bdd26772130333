"""``softphantom estimate``: the real-time inverse estimator over a sensor source → estimate CSV."""

from __future__ import annotations

import time

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import (At, AtlasFYSplitN, AtlasGrid, AtlasXAxis, DurationS, Envelope, Estimator,
                                     LagCompensation, MaxForceN, ModelDir, OnNewBoard, Out, Overwrite, P0KPa, Scheduler,
                                     Source, TareS, TubeIdMm, TubeLengthM, check_choice, check_output, check_positive,
                                     staged_output, stopped)
from softphantom.errors import UserError

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


def source_contact(at: str | None, meta: dict, names: list[str], source: str) -> tuple[str, str]:
    """The contact point to estimate at and where it comes from: ``--at``; else a replay's
    recording (``recording_contact``) or a virtual scenario's (``scenario_contact``); else, for a
    serial board, on-centre. A recording or scenario that names none (or several) on a model of
    several contact points is refused in one line asking for ``--at``: estimating at the wrong
    point mirrors the pose.

    >>> source_contact(None, {"recording_contact": "port"}, ["on-centre", "port"], "replay:r.csv")
    ('port', 'recording')
    >>> source_contact(None, {"recording_contact": None}, ["on-centre", "off-centre"], "replay:r.csv")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --source replay:r.csv: the recording names no contact point and this model has several (on-centre, off-centre); give --at
    """
    from softphantom.design.params import check_contact

    if at is not None:
        return check_contact(at, names, "--at"), "--at"
    for key, what in (("recording_contact", "recording"), ("scenario_contact", "scenario")):
        if key not in meta:
            continue
        if meta[key]:  # made at a point this model may not have
            return check_contact(meta[key], names, f"{source}: {key}", hint="--at gives another"), what
        several = meta.get(key + "s")
        if several:
            raise UserError(f"--source {source}: the {what} pushes at several contact points "
                            f"({', '.join(several)}); give --at (one of them)")
        if len(names) > 1:
            raise UserError(f"--source {source}: the {what} names no contact point and this model has several "
                            f"({', '.join(names)}); give --at")
        return names[0], what
    return "on-centre", "default"


def rest_check(est) -> dict:
    """The estimator's answer at rest checked (an atlas's: :meth:`AtlasEstimator.rest_check`), for the
    estimate file's metadata: ``rest_check``, and ``warnings`` (read by ``evaluate``, shown in its
    report) with the one line printed when it is off the rest state. Empty for an estimator that
    has no check (the refresh estimator is linearized at rest: exact there)."""
    check = getattr(est, "rest_check", None)
    if not callable(check):
        return {}
    rc = check()
    if rc["ok"]:
        return {"rest_check": rc}
    lim = rc["limits"]
    msg = (f"the atlas at rest is off the rest state: at zero volumes it estimates |F| {rc['force_N']:.3f} N, "
           f"{rc['pos_mm']:.3f} mm, {rc['ang_deg']:.3f}°{'' if rc['in_envelope'] else ', outside its envelope'} "
           f"(its goals: {lim['force_N']:g} N, {lim['pos_mm']:g} mm, {lim['ang_deg']:g}°): every estimate of the "
           "phantom at rest carries it; a finer --atlas-grid (or the default) brings it down")
    console.print(f"warning: {msg}", style="yellow", highlight=False, soft_wrap=True)
    return {"rest_check": rc, "warnings": [msg]}


def warn_outside(summary: dict, envelope: str | None) -> None:
    """One warning line when estimates were clamped at the atlas envelope's faces (in_envelope 0)."""
    n, k = summary["estimates"], summary["outside"]
    console.print(f"warning: {k} of {n} estimates ({k / max(n, 1):.0%}) at or beyond the atlas envelope's faces, "
                  f"clamped (in_envelope 0): widen --envelope (now {envelope or 'the default'}); most of a run "
                  "clamped at rest: was the tare (serial) taken under load?",
                  style="yellow", highlight=False, soft_wrap=True)


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
    require_full: bool = typer.Option(False, "--require-full", help="Atlas: refuse a draft atlas (atlas build "
                                      "--draft), which is used where the model has no full one."),
    overwrite: Overwrite = False,
) -> None:
    """Estimate force, urethra pressure, 6-DoF pose and target shifts from the cavity volumes, into the
    estimate CSV --out (a metadata line, then one row per sample). A missing atlas is built (on
    --scheduler, with the --atlas-* options)."""
    import contextlib
    import threading

    from softphantom.design import load_model
    from softphantom.design.params import check_contact
    from softphantom.estimation import EstimatorConfig, estimate_stream, open_estimator
    from softphantom.estimation.atlas.build import MAX_BUILD_ON_THE_FLY_S
    from softphantom.estimation.atlas.config import model_atlas_config
    from softphantom.estimation.lag import compensated
    from softphantom.estimation.select import atlas_config_from_options, check_estimator_kind

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
    src, live = opened.source, opened.live
    try:
        at, contact_from = source_contact(at, opened.meta, list(model.p_ext), source)
        lag, lag_meta = lag_for(lag_compensation, opened, source)
    except BaseException:
        src.close()
        raise
    cfg = EstimatorConfig.box(max_force_N, contact=at, qp_solver=qp_solver,
                              mode=("async" if live else "sync") if mode == "auto" else mode)
    t0 = time.monotonic()
    try:  # the contact point may come from the recording: the source is open first
        est = open_estimator(estimator, model, cfg, cache_dir=model_dir, scheduler=scheduler, atlas=acfg,
                             max_build_s=MAX_BUILD_ON_THE_FLY_S, require_full=require_full)
    except BaseException:
        src.close()
        raise
    est = compensated(est, lag)
    stop = threading.Event()
    if duration_s is not None:
        timer = threading.Timer(duration_s, stop.set)
        timer.daemon = True
        timer.start()
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

    # a live source's estimates cannot be made again: written in place and kept on Ctrl-C (closed
    # cleanly); from a file, the CSV appears only when complete
    if live:
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            est.close()
            src.close()
            raise UserError(f"--out {out}: cannot create {out.parent} ({exc.strerror})") from None
    target = contextlib.nullcontext(out) if live else staged_output(out, overwrite=overwrite, directory=False)
    with target as path, est:
        how = f"mode {cfg.mode}" if estimator == "refresh" else "no background work"
        console.print(f"estimator {estimator} ready in {time.monotonic() - t0:.1f} s ({len(model.nodes)} nodes, "
                      f"{how}, contact {at}, |F_i| <= {max_force_N:g} N, QP {qp_solver})", highlight=False)
        draft = getattr(getattr(est, "atlas", None), "draft", False)
        if draft:
            from softphantom.estimation.atlas.check import draft_error_text

            first = getattr(est.atlas, "all_pieces", None) or getattr(est.atlas, "patches", None) or (est.atlas,)
            held = (first[0].provenance or {}).get("held_out")
            console.print(f"draft atlas: {draft_error_text(held) if held else 'its error not measured'}; the full one: "
                          f"softphantom atlas build --model {model_dir}", highlight=False, soft_wrap=True)
        rest = rest_check(est)
        meta = {"model": str(model_dir), "source": source, "contact": at, "contact_from": contact_from,
                **rest, "max_force_N": max_force_N,
                "qp_solver": qp_solver, "estimator": estimator, "mode": cfg.mode, "nodes": int(len(model.nodes)),
                "contact_radius_mm": cfg.contact_radius_m * 1e3, **({"atlas": "draft"} if draft else {}),
                **opened.meta, **lag_meta}
        try:
            s = estimate_stream(src, est, path, show, live=live, metadata=meta, stop=stop,
                                on_event=print_event)
        except KeyboardInterrupt:
            if not live:
                raise
            stopped(f"stopped (Ctrl-C); the estimates so far are in {out}")
    ev = ", ".join(f"{k} {v}" for k, v in s["events"].items()) or "none"
    if s["outside"]:
        warn_outside(s, envelope)
    console.print(f"wrote {s['estimates']} estimates to {out} ({s['rejected']} rejected, {s['skipped']} skipped "
                  f"(estimator behind); link events: {ev}; "
                  f"{s['rate_Hz']:.0f} Hz, step p50 {s['step_ms_p50']:.2f} ms, p99 {s['step_ms_p99']:.2f} ms)",
                  highlight=False)
