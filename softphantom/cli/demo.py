"""``softphantom demo`` (what ``make demo`` runs): design → mesh → the four scenarios on the virtual
phantom → estimate → evaluate → one report per scenario, an index page and a one-screen summary."""

from __future__ import annotations

import html
import json
import os
import time
from pathlib import Path

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import check_output, overwrite_option, staged_output
from softphantom.errors import UserError
from softphantom.progress import status


def _contact(scenario) -> str:
    points = {e.point for e in scenario.events if e.kind == "push"}
    return points.pop() if len(points) == 1 else "on-centre"


# The demo's atlas per scenario: the box of the scenario's peak loads (its pushes; the pressure its
# inflation reached) and zero, each face widened by MARGIN_N + MARGIN_REL × the peak on that side
# of that axis (the estimator's model differs from the truth's, so its forces do too: in the
# demo the estimates passed the truth's peaks by ≤ 0.62 N along the push, ≤ 0.2 N sideways),
# the pressure by MARGIN_KPA only: it is measured, not estimated (a 20 % margin put the
# inflation atlas's top planes at 51 kPa, beyond what the estimator's model reaches: 27 failing
# solves for points no estimate used). Margins are per axis: one margin for all axes from the
# largest force would make the sideways range 3.1 N for ±0.6 N of load.
# Grids: pushes vary the force (the pressure stays near 0: 2 points), an inflation the pressure.
# Push grids by contact, measured against exact (settled) inverses of the same model at the demo
# pushes' worst samples (docs/performance.md): on-centre, the arm pair's step at
# f_x = 0 (docs/estimation.md) wants the f_x points clustered about 0 (7, asinh width 0.1 N:
# 0.006 N / 0.008 mm / 0.04°; 5 affine: 0.03 N / 0.04 mm / 0.30°); off-centre has no such step
# there (the same clustering: 0.31°; 5 affine points: 0.02 N / 0.025 mm / 0.19°, 7: 0.20°) but a
# yaw that is steep along a line moving with f_y, which more f_y points follow (5 × 9 × 4:
# 0.023 N / 0.013 mm / 0.080°, 180 solves; 5 × 7 × 5: 0.098°; 5 × 5 × 5: 0.19°).
MARGIN_N = 0.5
MARGIN_REL = 0.2
MARGIN_KPA = 2.0
PUSH_GRID = (5, 5, 5, 2)
PUSH_GRIDS = {"on-centre": ((7, 5, 5, 2), (0.1, 0.0, 0.0)),  # contact: (grid, force_cluster_N)
              "off-centre": ((5, 9, 4, 2), None)}
INFLATE_GRID = (3, 3, 3, 5)


def _box(forces, p_kPa: float, grid, cluster_N=None):
    import numpy as np

    from softphantom.estimation import AtlasConfig

    F = np.array([np.zeros(3)] + [np.asarray(f, float) for f in forces])
    lo, hi = F.min(0), F.max(0)
    n = grid or (PUSH_GRID if p_kPa == 0.0 else INFLATE_GRID)
    # a push's pressure stays near 0 (the middle of its range): the pressure axis is the tangent
    # line there, one plane of solves instead of two (AtlasConfig.linear_pressure)
    return AtlasConfig(force_min_N=tuple(lo - MARGIN_N + MARGIN_REL * lo),
                       force_max_N=tuple(hi + MARGIN_N + MARGIN_REL * hi), p_min_kPa=-MARGIN_KPA,
                       p_max_kPa=p_kPa + MARGIN_KPA, n_force=n[:3], n_pressure=n[3],
                       linear_pressure=p_kPa == 0.0 and n[3] == 2, force_cluster_N=cluster_N,
                       x_control="force")  # the grids above were chosen (and measured) on a force axis


def scenario_atlas(truth, grid: tuple[int, int, int, int] | None = None):
    """The :class:`~softphantom.estimation.atlas.AtlasConfig` the demo builds for one scenario from
    its solved ``truth`` (see ``MARGIN_N`` above); ``grid`` overrides the points per axis.

    >>> from types import SimpleNamespace as E
    >>> push = E(events=[E(force=(0.4, 3.0, 0.3), p_urethra=0.0), E(force=(-0.5, 2.8, -0.4), p_urethra=0.0)])
    >>> a = scenario_atlas(push)
    >>> [round(v, 2) for v in a.force_min_N], [round(v, 2) for v in a.force_max_N], a.shape
    ([-1.1, -0.5, -0.98], [0.98, 4.1, 0.86], (5, 5, 5, 2))
    >>> a = scenario_atlas(E(events=[E(force=(0.0, 0.0, 0.0), p_urethra=30e3)]))
    >>> a.force_max_N, a.p_min_kPa, a.p_max_kPa, a.shape
    ((0.5, 0.5, 0.5), -2.0, 32.0, (3, 3, 3, 5))
    """
    return _box([e.force for e in truth.events], max([0.0] + [e.p_urethra * 1e-3 for e in truth.events]), grid)


def _push_only(sc) -> str | None:
    """The contact point of a scenario that only pushes, at one point; else None."""
    points = {e.point for e in sc.events if e.kind == "push"}
    return points.pop() if len(points) == 1 and all(e.kind == "push" for e in sc.events) else None


def shared_atlases(scs, grid: tuple[int, int, int, int] | None = None) -> dict:
    """One atlas per contact point for the scenarios that only push there (their peak forces are
    the scenario's own, known before any solve): the box of all of them, so the needle insertion
    and the on-centre pushes share one build; the grid by contact (``PUSH_GRIDS``, else
    ``PUSH_GRID``) unless ``grid`` is given. {contact: AtlasConfig}.

    >>> from types import SimpleNamespace as E
    >>> needle = E(events=[E(kind="push", point="on-centre", force_N=(0.15, 2.5, -0.2))])
    >>> pushes = E(events=[E(kind="push", point="on-centre", force_N=(-0.6, 2.6, -0.5))])
    >>> inflate = E(events=[E(kind="inflate", point="on-centre", force_N=(0.0, 0.0, 0.0))])
    >>> a = shared_atlases([needle, pushes, inflate])
    >>> c = a["on-centre"]  # each face: 0.5 N + 0.2 × the peak on that side (f_y: 2.6 + 0.5 + 0.52)
    >>> list(a), [round(v, 2) for v in c.force_min_N], [round(v, 2) for v in c.force_max_N], c.shape
    (['on-centre'], [-1.22, -0.5, -1.1], [0.68, 3.62, 0.5], (7, 5, 5, 2))
    >>> c.linear_pressure, c.cluster_N  # one plane of solves at 0 kPa; f_x points clustered
    (True, (0.1, 0.0, 0.0))
    >>> shared_atlases([needle], grid=(4, 5, 4, 2))["on-centre"].cluster_N  # a given grid: affine
    (0.0, 0.0, 0.0)
    """
    by: dict[str, list] = {}
    for sc in scs:
        if (c := _push_only(sc)) is not None:
            by.setdefault(c, []).extend(e.force_N for e in sc.events)
    return {c: _box(f, 0.0, *((grid, None) if grid else PUSH_GRIDS.get(c, (PUSH_GRID, None))))
            for c, f in by.items()}


def _in_envelope(path: Path) -> float:
    """Fraction of the estimates inside the atlas's envelope (the CSV's in_envelope column)."""
    from softphantom.evaluation.files import read_table

    col = read_table(path).columns["in_envelope"]
    return float(col.mean()) if len(col) else float("nan")


def run_scenario(sc, model, out: Path, cfg, truth, bar, estimator: str = "atlas", grid=None, atlas=None) -> dict:
    """One scenario end to end from its solved ``truth``; returns its summary row (JSON-able).
    ``estimator``: atlas (``atlas``, an AtlasConfig, default the scenario's envelope
    (:func:`scenario_atlas`); loaded from or built into out/model/atlas) or refresh (sync);
    ``grid`` the atlas's points per axis (default: by kind)."""
    from softphantom.estimation import EstimatorConfig, open_estimator
    from softphantom.estimation.stream import estimate_stream
    from softphantom.evaluation import evaluate, read_estimate, read_truth, write_report
    from softphantom.tracking import estimate_lag
    from softphantom.virtual import run_summary, simulate, write_run

    d = out / sc.name
    run = simulate(sc, model, cfg, truth=truth)
    paths = write_run(run, d)
    est_path = d / "estimate.csv"
    if est_path.exists():
        est_path.unlink()
    src = run.source()
    n_frames = int(run.board().rate_Hz * sc.duration_s)
    t1 = time.perf_counter()
    task = bar.add_task(f"{sc.name}: estimate", total=n_frames, what="")
    ecfg = EstimatorConfig(contact=_contact(sc), mode="sync")
    if estimator != "atlas":
        atlas = None
    elif atlas is None:
        atlas = scenario_atlas(truth, grid)
    with open_estimator(estimator, model, ecfg, cache_dir=out / "model", progress=False, atlas=atlas,
                        log=lambda s: bar.console.print(s, highlight=False, soft_wrap=True)) as est:
        stats = estimate_stream(src, est, est_path, lambda e, n: bar.update(task, completed=n),
                                live=False, metadata={"model": "../model", "scenario": sc.name,
                                                      "source": f"virtual:{sc.name}",
                                                      "contact_radius_mm": ecfg.contact_radius_m * 1e3})
    bar.update(task, completed=n_frames)
    t_est = time.perf_counter() - t1
    t2 = time.perf_counter()
    task = bar.add_task(f"{sc.name}: evaluate", total=None, what="report")
    tru = read_truth(paths["truth"])
    estimate = read_estimate(est_path)
    ev = evaluate(tru, estimate)
    report, rows = write_report(d / "report", tru, estimate, ev, snapshot=paths["snapshot"],
                                title=f"{sc.name} — {sc.description}")
    # the tracker path: Motive CSV → reader → rest-window registration → lag against the exact truth
    trk = read_truth(paths["tracker"])
    lag = estimate_lag(tru.t, tru.mm_deg(), trk.t, trk.mm_deg(), max_lag_s=1.0)
    t_eval = time.perf_counter() - t2
    bar.update(task, total=1, completed=1)
    rs = run_summary(run)
    return {
        "scenario": sc.name, "report": str(report),
        "rmse": {s.name: s.rmse for s in ev.dof}, "units": {s.name: s.unit for s in ev.dof},
        "peak_truth": {s.name: s.peak_truth for s in ev.dof},
        "force_rmse_N": {s.name: s.rmse for s in ev.force},
        "target_rmse_mm": {s.name: s.rmse for s in ev.targets},
        "lag_ms": ev.lag_ms, "lag_source": ev.lag_source,
        "table_i": [{"dof": r.ref.dof, "observed": r.observed, "unit": r.ref.unit, "flag": r.flag,
                     "study": r.ref.study} for r in rows],
        "tracker_clock_offset_ms": {"injected": rs["tracker"]["clock_offset_s"] * 1e3, "recovered": lag.lag_ms},
        "estimate": {k: stats[k] for k in ("estimates", "rejected", "rate_Hz", "step_ms_p50", "step_ms_p99")},
        "estimator": estimator,
        "atlas": None if atlas is None else {"force_min_N": atlas.force_min_N, "force_max_N": atlas.force_max_N,
                                             "p_min_kPa": atlas.p_min_kPa, "p_max_kPa": atlas.p_max_kPa,
                                             "grid": atlas.shape,
                                             "in_envelope_fraction": _in_envelope(est_path)},
        "truth": rs["truth"], "seconds": {"truth_solve": truth.solve_s, "estimate": t_est, "evaluate": t_eval},
    }


# --- truth solves in a worker process (overlapping the estimation of the previous scenario) ------
_QUEUE = None


def _init_worker(queue, parent: int) -> None:
    import threading

    global _QUEUE
    _QUEUE = queue
    threading.Thread(target=exit_with_parent, args=(parent,), daemon=True).start()


def exit_with_parent(parent: int, poll_s: float = 0.5) -> None:
    """Exit this process once ``parent`` is gone: a demo killed (SIGTERM/SIGKILL: no clean-up runs)
    must not leave its truth worker solving for minutes on a 2-core machine."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    os._exit(1)


def _solve_in_worker(sc, model, truth_cfg, truth_mesh):
    from softphantom.virtual import solve_truth

    def cb(done: int, total: int, what: str) -> None:
        _QUEUE.put((sc.name, done, total, what))

    return solve_truth(sc, model, truth_cfg, cb, truth_mesh=truth_mesh)


def _listen(queue, bar, tasks) -> None:
    while (item := queue.get()) is not None:
        name, done, total, what = item
        bar.update(tasks[name], completed=done, total=max(total, done), what=what)


def _index(out: Path, work: Path, rows: list[dict], wall_s: float) -> Path:
    items = "".join(
        f"<li><a href='{html.escape(str(Path(r['report']).relative_to(out)))}'>{html.escape(r['scenario'])}</a>: "
        f"lag {r['lag_ms']:.0f} ms; RMSE " + ", ".join(f"{k} {v:.2f} {r['units'][k]}" for k, v in r["rmse"].items())
        + "</li>" for r in rows)
    p = work / "index.html"
    p.write_text("<!doctype html><html><head><meta charset='utf-8'><title>softphantom demo</title></head><body>"
                 f"<h1>softphantom demo</h1><p>virtual phantom, {len(rows)} scenarios, {wall_s:.0f} s</p>"
                 f"<ul>{items}</ul></body></html>\n")
    return p


def _table_i_line(rows: list[dict]) -> str:
    by: dict[tuple[str, float, str], list[str]] = {}
    for x in rows:
        by.setdefault((x["dof"], x["observed"], x["unit"]), []).append(f"{x['flag']} {x['study']}")
    return "; ".join(f"{d} {v:.1f} {'°' if u == 'deg' else u}: {', '.join(f)}" for (d, v, u), f in by.items())


def print_summary(rows: list[dict], con=console) -> None:
    from rich.table import Table
    from rich.text import Text

    t = Table(title="demo: estimate vs virtual truth — RMSE (peak |truth|)")
    for h in ("scenario", "x mm", "y mm", "z mm", "yaw °", "pitch °", "roll °", "|F| N", "lag ms"):
        t.add_column(h, justify="right")
    for r in rows:
        cells = [f"{r['rmse'][k]:.2f} ({r['peak_truth'][k]:.1f})" for k in r["rmse"]]
        f = r["force_rmse_N"]
        fr = "–" if "|force|" not in f else f"{f['|force|']:.2f}"
        t.add_row(r["scenario"], *cells, fr, f"{r['lag_ms']:.0f}")
    con.print(t)
    for r in rows:
        c = r["tracker_clock_offset_ms"]
        extra = ""
        for e in r["truth"]["events"]:
            if e["kind"] == "inflate":
                extra = (f"; urethra {e['p_urethra_kPa']:.1f} kPa: near_urethra moved "
                         f"{e.get('near_urethra_shift_mm', float('nan')):.2f} mm, bulb growth {e['bulb_growth_percent']:.2f} %")
        con.print(Text.assemble((r["scenario"], "bold"), f": Table I (truth) {_table_i_line(r['table_i'])}"),
                  highlight=False)
        con.print(f"  tracker clock offset injected {c['injected']:.1f} ms, recovered {c['recovered']:.1f} ms; "
                  f"{r['estimator']} estimator {r['estimate']['rate_Hz']:.0f} Hz (step p99 "
                  f"{r['estimate']['step_ms_p99']:.1f} ms){_atlas_note(r)}{extra}", highlight=False)


def _atlas_note(r: dict) -> str:
    a = r.get("atlas")
    if not a:
        return ""
    return f", {a['in_envelope_fraction'] * 100:.0f} % of estimates inside its atlas ({'×'.join(map(str, a['grid']))})"


def _prebuild(model, out: Path, shared: dict, bar) -> None:
    """Build (or find) the shared atlases in out/model while the worker solves the truths."""
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas import load_or_build

    for contact, acfg in shared.items():
        task = bar.add_task(f"atlas at {contact}", total=None, what=f"{acfg.n_solves} forward solves")
        load_or_build(model, EstimatorConfig(contact=contact, mode="sync"), acfg, cache_dir=out / "model",
                      progress=False, log=lambda s: bar.console.print(s, highlight=False, soft_wrap=True))
        bar.update(task, total=1, completed=1, what="built")


def _run_all(scs, model, out: Path, cfg, tm, estimator: str = "atlas", grid=None) -> list[dict]:
    """Truth solves in one worker process; the main process meanwhile builds the atlases shared by
    the push scenarios (:func:`shared_atlases`), then estimates and evaluates each scenario as
    soon as its truth is ready (2 cores: both stay busy). The scenarios whose atlas needs their
    truth (an inflation: its pressure) are solved first. Rows in the order of ``scs``."""
    import multiprocessing as mp
    import threading
    from concurrent.futures import ProcessPoolExecutor

    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

    from softphantom.progress import progress_bar

    shared = shared_atlases(scs, grid) if estimator == "atlas" else {}
    order = sorted(scs, key=lambda sc: _push_only(sc) in shared)  # stable: the others first
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    bar = progress_bar(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                       TextColumn("{task.fields[what]}"), console=console)
    rows: dict[str, dict] = {}
    with bar, ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker, initargs=(queue, os.getpid())) as pool:
        tasks = {sc.name: bar.add_task(f"{sc.name}: truth", total=None, what="queued") for sc in order}
        listener = threading.Thread(target=_listen, args=(queue, bar, tasks), daemon=True)
        listener.start()
        futures = []
        try:
            futures = [pool.submit(_solve_in_worker, sc, model, cfg.truth, tm) for sc in order]
            _prebuild(model, out, shared, bar)
            for sc, fut in zip(order, futures):
                truth = fut.result()
                bar.update(tasks[sc.name], what=f"solved in {truth.solve_s:.0f} s")
                rows[sc.name] = run_scenario(sc, model, out, cfg, truth, bar, estimator, grid,
                                             atlas=shared.get(_push_only(sc)))
        finally:
            for f in futures:
                f.cancel()
            queue.put(None)
            listener.join(5)
    return [rows[sc.name] for sc in scs]


@app.command("demo")
def demo_cmd(
    out: Path = typer.Option(Path("out/demo"), "--out", help="Output directory."),
    mesh_size_mm: float = typer.Option(None, "--mesh-size-mm", help="Estimator mesh size (mm; default: the design's, 6 mm)."),
    scenarios: list[str] = typer.Option(None, "--scenarios", help="Scenario names or TOML files (repeat; default: the four bundled)."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random source."),
    osr: int = typer.Option(100, "--osr", help="Board oversampling (100: 19.2 Hz, the paper's N; 25: 76.9 Hz)."),
    truth_mesh_scale: float = typer.Option(0.75, "--truth-mesh-scale", help="Truth node spacing relative to the estimator's mesh size (P2 elements are twice that)."),
    truth_order: int = typer.Option(2, "--truth-order", help="Truth element order: 2 (10-node tets, the default) or 1."),
    force: bool = typer.Option(False, "--force", help="Mesh above the element-count limit (docs/robustness.md)."),
    model_dir: Path = typer.Option(None, "--model", help="Estimator model directory (e.g. from softphantom calibrate) instead of the default design; the truth is meshed from its design."),
    overwrite: bool = overwrite_option(),
    estimator: str = typer.Option("atlas", "--estimator", help="atlas (precomputed, real time) | refresh (sync: "
                                  "re-linearized inside each step)."),
    atlas_grid: str = typer.Option(None, "--atlas-grid", help="Atlas: Chebyshev points per axis NX,NY,NZ,NP (default: "
                                   "7,5,5,2 on-centre (f_x clustered) and 5,9,4,2 off-centre for pushes, 3,3,3,5 for an inflation; the envelope is the scenario's loads)."),
) -> None:
    """The paper's experiments end to end without hardware: reports and a summary."""
    from softphantom.cli.virtual import _config
    from softphantom.design import BIPDesign, build_model, load_model, save_model
    from softphantom.estimation.select import atlas_config_from_options, check_estimator_kind
    from softphantom.virtual import BUNDLED, load_scenario, truth_model

    check_estimator_kind(estimator)
    grid = atlas_config_from_options(atlas_grid).shape if atlas_grid is not None else None
    t0 = time.perf_counter()
    check_output(out, overwrite=overwrite, directory=True)
    names = list(scenarios or BUNDLED)
    for n in names:
        load_scenario(n)  # validate all before the long work
    cfg = _config(seed, osr, truth_mesh_scale, order=truth_order)
    if mesh_size_mm is not None and not mesh_size_mm > 0:
        raise UserError(f"--mesh-size-mm: must be > 0, got {mesh_size_mm:g}")
    if model_dir is not None and mesh_size_mm is not None:
        raise UserError("--model and --mesh-size-mm: give one (a model directory has its mesh)")
    given = load_model(model_dir) if model_dir is not None else None
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        with status("design → mesh (estimator model)", console):
            model = given if given is not None else build_model(BIPDesign(), mesh_size_mm, force=force)
            save_model(model, work / "model")
        console.print(f"model: {len(model.nodes)} nodes, {len(model.tets)} tets (mesh {model.design.mesh.size_mm:g} "
                      f"mm) → {out / 'model'}", highlight=False, soft_wrap=True)
        with status("mesh (truth model, finer)", console):
            tm = truth_model(model, cfg.truth)
        console.print(f"truth model: {len(tm.nodes)} nodes, {len(tm.tets)} tets, P{tm.element_order} (mesh "
                      f"{tm.design.mesh.size_mm:g} mm)", highlight=False)
        rows = _run_all([load_scenario(n) for n in names], model, work, cfg, tm, estimator, grid)
        for r in rows:  # the paths the user will see, once the directory is in place
            r["report"] = str(out / Path(r["report"]).relative_to(work))
        wall = time.perf_counter() - t0
        (work / "summary.json").write_text(json.dumps({"wall_s": wall, "scenarios": rows}, indent=2, default=float)
                                           + "\n")
        _index(out, work, rows, wall)
    index = out / "index.html"
    print_summary(rows)
    for r in rows:
        console.print(f"report: {r['report']}", highlight=False, soft_wrap=True)
    console.print(f"index: {index}  (demo took {wall:.0f} s)", highlight=False, soft_wrap=True)
