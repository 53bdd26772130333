"""``softphantom estimate``: the real-time inverse estimator over a sensor source → estimate CSV."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import check_output, overwrite_option, staged_output, stopped
from softphantom.errors import UserError

_SOURCES = "serial:PORT, replay:FILE or virtual:SCENARIO"


def _chain_for(model):
    from softphantom.sensing.chain import default_chain

    by_name = {a.name: a.cavity_volume_mm3 for a in model.design.arms}
    from softphantom.estimation import ARM_NAMES

    try:
        return default_chain([by_name[a] * 1e-9 for a in ARM_NAMES])
    except KeyError as exc:
        raise UserError(f"design has no arm {exc.args[0]!r}") from None


def _serial_source(port: str, model, tare_s: float, p0_Pa: float, timeout_s: float = 5.0):
    """The board on ``port``, tared on its first ``tare_s`` seconds (which are not estimated)."""
    import numpy as np

    from softphantom.sensing.chain import nominal_tare, tare_from_window
    from softphantom.sensing.sources import SerialSource

    chain = _chain_for(model)
    src = SerialSource(port, chain, nominal_tare(chain, p0_Pa))
    window: list = []
    t0 = time.monotonic()
    while not window or window[-1].t - window[0].t < tare_s or len(window) < 5:
        window += src.read(0.05) or []
        if not window and time.monotonic() - t0 > timeout_s:
            src.close()
            raise UserError(f"--source serial:{port}: no valid frame within {timeout_s:g} s "
                            f"(state {src.stats().state})")
        if time.monotonic() - t0 > timeout_s + tare_s + 5:
            src.close()
            raise UserError(f"--source serial:{port}: too few frames for a {tare_s:g} s tare window")
    src.set_tare(tare_from_window(np.array([m.raw for m in window]), np.array([m.osr for m in window]),
                                  np.array([m.t for m in window]), chain, p0_Pa))
    return src


def open_sensor_source(spec: str, model, *, tare_s: float = 1.0, p0_Pa: float = 101_325.0):
    """(source, live) for ``--source``: ``serial:PORT``, ``replay:FILE`` or ``virtual:SCENARIO``."""
    kind, _, arg = spec.partition(":")
    if not arg:
        raise UserError(f"--source {spec!r}: use {_SOURCES}")
    if kind == "replay":
        from softphantom.sensing.sources import ReplaySource

        if not Path(arg).is_file():
            raise UserError(f"--source replay:{arg}: no such file")
        return ReplaySource(arg), False
    if kind == "serial":
        return _serial_source(arg, model, tare_s, p0_Pa), True
    if kind == "virtual":
        try:
            from softphantom.virtual import open_source
        except ImportError:
            raise UserError("--source virtual:…: the virtual phantom (softphantom.virtual) is not available "
                            "in this installation") from None
        console.print(f"virtual phantom: solving scenario {arg!r} (may take a while)…", highlight=False)
        return open_source(arg, model), False
    raise UserError(f"--source {spec!r}: unknown kind {kind!r}; use {_SOURCES}")


@app.command("estimate")
def estimate_cmd(
    model_dir: Path = typer.Option(..., "--model", help="Model directory (softphantom design --out)."),
    source: str = typer.Option(..., "--source", help="serial:PORT | replay:FILE (sensing recording) | virtual:SCENARIO"),
    out: Path = typer.Option(..., "--out", help="Estimate CSV to write (metadata line, then one row per sample)."),
    at: str = typer.Option("on-centre", "--at", help="Contact point: on-centre | off-centre (the model's p_ext)."),
    max_force_N: float = typer.Option(10.0, "--max-force-N", help="Bound on each force component (N)."),
    qp_solver: str = typer.Option("daqp", "--qp-solver", help="QP solver: daqp | quadprog."),
    mode: str = typer.Option("auto", "--mode", help="sync (deterministic) | async (background equilibrium) | "
                             "auto (async for serial, sync otherwise)."),
    tare_s: float = typer.Option(1.0, "--tare-s", help="Serial: rest window for the tare at start (s)."),
    p0_kPa: float = typer.Option(101.325, "--p0-kPa", help="Serial: absolute ambient pressure at tare (kPa)."),
    duration_s: float = typer.Option(None, "--duration-s", help="Stop after this many seconds (serial)."),
    overwrite: bool = overwrite_option(),
) -> None:
    """Estimate force, urethra pressure, 6-DoF pose and target shifts from the cavity volumes."""
    import contextlib
    import threading

    from softphantom.design import load_model
    from softphantom.estimation import Estimator, EstimatorConfig, estimate_stream

    if mode not in ("auto", "sync", "async"):
        raise UserError(f"--mode must be auto, sync or async, got {mode!r}")
    if at not in ("on-centre", "off-centre"):
        raise UserError(f"--at must be on-centre or off-centre, got {at!r}")
    if duration_s is not None and not duration_s > 0:
        raise UserError(f"--duration-s must be > 0, got {duration_s}")
    if not p0_kPa > 0:
        raise UserError(f"--p0-kPa must be > 0, got {p0_kPa}")
    check_output(out, overwrite=overwrite, directory=False)
    if not (model_dir / "model.npz").is_file():
        raise UserError(f"--model {model_dir}: not a model directory (no model.npz; run softphantom design)")
    model = load_model(model_dir)
    src, live = open_sensor_source(source, model, tare_s=tare_s, p0_Pa=p0_kPa * 1e3)
    cfg = EstimatorConfig.box(max_force_N, contact=at, qp_solver=qp_solver,
                              mode=("async" if live else "sync") if mode == "auto" else mode)
    stop = threading.Event()
    if duration_s is not None:
        timer = threading.Timer(duration_s, stop.set)
        timer.daemon = True
        timer.start()
    last = [0.0]

    def progress(e, n):
        now = time.monotonic()
        if now - last[0] >= 1.0:
            last[0] = now
            f = e.force
            p = e.pose.to_mm_deg()
            console.print(f"{n:7d}  t {e.t:8.2f} s  F ({f[0]:+.2f}, {f[1]:+.2f}, {f[2]:+.2f}) N  "
                          f"xyz ({p[0]:+.2f}, {p[1]:+.2f}, {p[2]:+.2f}) mm  step {e.step_time * 1e3:.2f} ms  "
                          f"{e.qp_status}", highlight=False)

    t0 = time.monotonic()
    # a live source's estimates cannot be made again: written in place and kept on Ctrl-C (closed
    # cleanly); from a file, the CSV appears only when complete
    target = contextlib.nullcontext(out) if live else staged_output(out, overwrite=overwrite, directory=False)
    with target as path, Estimator(model, cfg) as est:
        console.print(f"estimator ready in {time.monotonic() - t0:.1f} s ({len(model.nodes)} nodes, "
                      f"mode {cfg.mode}, contact {at}, |F_i| <= {max_force_N:g} N, QP {qp_solver})", highlight=False)
        meta = {"model": str(model_dir), "source": source, "contact": at, "max_force_N": max_force_N,
                "qp_solver": qp_solver, "mode": cfg.mode, "nodes": int(len(model.nodes))}
        try:
            s = estimate_stream(src, est, path, progress, live=live, metadata=meta, stop=stop)
        except KeyboardInterrupt:
            if not live:
                raise
            stopped(f"stopped (Ctrl-C); the estimates so far are in {out}")
    console.print(f"wrote {s['estimates']} estimates to {out} ({s['rejected']} rejected, {s['skipped']} skipped; "
                  f"{s['rate_Hz']:.0f} Hz, step p50 {s['step_ms_p50']:.2f} ms, p99 {s['step_ms_p99']:.2f} ms)",
                  highlight=False)
