"""``softphantom demo`` (what ``make demo`` runs): its options, the models, and the one-screen summary;
the pipeline itself is :mod:`softphantom.virtual.demo`."""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import (AtlasGrid, DraftAtlas, Estimator, Force, MeshSizeMm, ModelDir, Out, Overwrite,
                                     Scheduler, TruthOptions, VirtualOptions, Workers, check_output, check_workers,
                                     staged_output, with_option_groups)
from softphantom.errors import UserError
from softphantom.progress import status


def _table_i_line(rows: list[dict]) -> str:
    by: dict[tuple[str, float, str], list[str]] = {}
    for x in rows:
        by.setdefault((x["dof"], x["observed"], x["unit"]), []).append(f"{x['flag']} {x['study']}")
    return "; ".join(f"{d} {v:.1f} {'°' if u == 'deg' else u}: {', '.join(f)}" for (d, v, u), f in by.items())


def print_summary(rows: list[dict], con=console) -> None:
    from rich.table import Table
    from rich.text import Text

    title = "demo: estimate vs virtual truth — RMSE (peak |truth|)"
    heads = ("x mm", "y mm", "z mm", "yaw °", "pitch °", "roll °", "|F| N", "lag ms")
    t = Table(title=title)
    t.add_column("scenario", no_wrap=True)
    for h in heads:
        t.add_column(h, justify="right")
    lines = []
    for r in rows:
        cells = [f"{r['rmse'][k]:.2f} ({r['peak_truth'][k]:.1f})" for k in r["rmse"]]
        f = r["force_rmse_N"]
        fr = "–" if "|force|" not in f else f"{f['|force|']:.2f}"
        t.add_row(r["scenario"], *cells, fr, f"{r['lag_ms']:.0f}")
        lines.append(f"{r['scenario']}: " + ", ".join(f"{h} {c}" for h, c in zip(heads, [*cells, fr, f"{r['lag_ms']:.0f}"])))
    if con.measure(t, options=con.options.update_width(10_000)).maximum <= con.width:
        con.print(t)
    else:  # too narrow (80 columns, a pipe): a line per scenario, its name and figures whole
        con.print(title, highlight=False, soft_wrap=True)
        for line in lines:
            con.print(f"  {line}", highlight=False, soft_wrap=True)
    for r in rows:
        c = r["tracker_clock_offset_ms"]
        extra = ""
        for e in r["truth"]["events"]:
            if e["kind"] == "inflate" and "p_urethra_kPa" in e:
                extra = (f"; urethra {e['p_urethra_kPa']:.1f} kPa: near_urethra moved "
                         f"{e.get('near_urethra_shift_mm', float('nan')):.2f} mm, bulb growth {e['bulb_growth_percent']:.2f} %")
            elif e["kind"] == "inflate":
                moved = max(((k[:-len("_shift_mm")], v) for k, v in e.items()
                             if k.endswith("_shift_mm") and k != "peak_marker_shift_mm"), key=lambda kv: kv[1], default=None)
                extra = (f"; {e['cavity']} {e['p_kPa']:.1f} kPa" + (f": {moved[0]} moved {moved[1]:.2f} mm" if moved
                         else "") + f", body growth {e['bulb_growth_percent']:.2f} %")
        if r["table_i"]:  # the prostate-motion studies: the BIP's demo only
            con.print(Text.assemble((r["scenario"], "bold"), f": Table I (truth) {_table_i_line(r['table_i'])}"),
                      highlight=False)
        else:
            con.print(Text.assemble((r["scenario"], "bold"), ":"), highlight=False)
        con.print(f"  tracker clock offset injected {c['injected']:.1f} ms, recovered {c['recovered']:.1f} ms; "
                  f"{r['estimator']} estimator {_rate(r['estimate'])} (step p50 {r['estimate']['step_ms_p50']:.2f} ms, "
                  f"p99 {r['estimate']['step_ms_p99']:.1f} ms){_atlas_note(r)}{extra}", highlight=False, soft_wrap=True)


def _rate(e: dict) -> str:
    """The estimate's rate: in wall time, and in its own CPU time when the cores were shared.

    >>> _rate({"rate_Hz": 350.0, "rate_cpu_Hz": 4100.0}), _rate({"rate_Hz": 4000.0, "rate_cpu_Hz": 4100.0})
    ('350 Hz (4100 Hz in its own CPU time: it waited for the cores)', '4000 Hz')
    """
    cpu = e.get("rate_cpu_Hz")
    if cpu is None or not cpu == cpu or cpu < 1.5 * e["rate_Hz"]:
        return f"{e['rate_Hz']:.0f} Hz"
    return f"{e['rate_Hz']:.0f} Hz ({cpu:.0f} Hz in its own CPU time: it waited for the cores)"


def _atlas_note(r: dict) -> str:
    a = r.get("atlas")
    if not a:
        return ""
    pieces = f", {a['pieces']} pieces" if a.get("pieces", 1) > 1 else ""
    draft = ", a draft atlas" if a.get("draft") else ""
    return (f", {a['in_envelope_fraction'] * 100:.0f} % of estimates inside its atlas "
            f"({'×'.join(map(str, a['grid']))}{pieces}{draft})")


@app.command("demo")
@with_option_groups
def demo_cmd(
    out: Out = Path("out/demo"),
    mesh_size_mm: MeshSizeMm = None,
    scenarios: list[str] = typer.Option(None, "--scenarios", help="Scenario names or TOML files (repeat; default: the "
                                        "paper's four bundled ones, whose atlases ship: on-centre full, off-centre a "
                                        "draft until `softphantom atlas build --at off-centre` builds the full one)."),
    truth: TruthOptions = TruthOptions(osr=100),
    force: Force = False,
    model_dir: ModelDir = None,
    design_file: Path = typer.Option(None, "--design", help="A design file (TOML/JSON) instead of the default "
                                     "design, e.g. examples/organs/kidney.toml: meshed as its [mesh] says (or at "
                                     "--mesh-size-mm); unless --scenarios, three pushes of --push-N at each of its "
                                     "contact points and an inflation of each of its cavities; the demo's own atlases "
                                     "(--atlas-grid; default 5,5,5,2 for pushes, 3,3,3,5 for inflations)."),
    push_n: float = typer.Option(2.5, "--push-N", help="With --design: the generated pushes' force (N)."),
    inflate_kpa: float = typer.Option(20.0, "--inflate-kPa", help="With --design: the generated inflations' gauge "
                                      "pressure (kPa)."),
    overwrite: Overwrite = False,
    estimator: Estimator = None,
    atlas_grid: AtlasGrid = None,
    scheduler: Scheduler = None,
    workers: Workers = None,
    draft: DraftAtlas = False,
) -> None:
    """The paper's experiments end to end without hardware: reports and a summary in the directory
    --out. --model: an estimator model (e.g. from softphantom calibrate) instead of the default
    design; the truth is meshed from its design. --estimator: by default atlas for a design with an
    actuated internal cavity, refresh (re-linearized inside each step) for one of none. --atlas-grid:
    build a small atlas for the demo over the scenarios' own loads (e.g. 5,5,5,2; for a model
    without its atlas) instead of using the model's (the default design's ships with softphantom).
    The truth solves and atlas builds run on --scheduler. --mesh-size-mm: mesh the default design at
    it instead of using its shipped quadratic model (9 mm; that mesh has no atlas yet: give
    --atlas-grid or --estimator refresh)."""
    from softphantom.cli.virtual import _config
    from softphantom.design import build_model, default_design, load_design, load_model, save_model
    from softphantom.estimation.select import atlas_config_from_options, check_estimator_kind
    from softphantom.virtual import load_scenario, truth_model
    from softphantom.virtual.demo import DEMO_SCENARIOS, design_scenarios, model_atlases, run_all, write_summary

    if estimator is not None:
        check_estimator_kind(estimator)
    check_workers(workers)
    grid = atlas_config_from_options(atlas_grid).shape if atlas_grid is not None else None
    t0 = time.perf_counter()
    check_output(out, overwrite=overwrite, directory=True)
    scs = [load_scenario(n) for n in scenarios] if scenarios else None  # all validated before the long work
    cfg = _config(VirtualOptions(**asdict(truth)))
    if mesh_size_mm is not None and not mesh_size_mm > 0:
        raise UserError(f"--mesh-size-mm: must be > 0, got {mesh_size_mm:g}")
    if model_dir is not None and mesh_size_mm is not None:
        raise UserError("--model and --mesh-size-mm: give one (a model directory has its mesh)")
    if model_dir is not None and design_file is not None:
        raise UserError("--model and --design: give one (a model directory has its design)")
    if not 0.0 < push_n <= 20.0:
        raise UserError(f"--push-N: must be in (0, 20] N, got {push_n:g}")
    if not 0.0 < inflate_kpa <= 250.0:
        raise UserError(f"--inflate-kPa: must be in (0, 250] kPa (the MPX4250D's range), got {inflate_kpa:g}")
    given = load_model(model_dir) if model_dir is not None else None
    design = given.design if given is not None else load_design(design_file) if design_file is not None else default_design()
    if scs is None:
        scs = (design_scenarios(design, push_n, inflate_kpa) if design_file is not None
               else [load_scenario(n) for n in DEMO_SCENARIOS])
    if estimator is None:
        estimator = "atlas" if design.pressure_names else "refresh"
        if estimator == "refresh":
            console.print("estimator: refresh (the atlas tabulates an internal pressure; this design has no "
                          "actuated cavity)", highlight=False)
    if design_file is not None and grid is None and estimator == "atlas":
        grid = ()  # no atlas ships for it: the demo's own, each of the grid of its kind (push, inflation)
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        with status("design → mesh (estimator model)", console):
            model = given if given is not None else build_model(design, mesh_size_mm, force=force)
            save_model(model, work / "model")
        console.print(f"model: {len(model.nodes)} nodes, {len(model.tets)} tets, P{model.element_order} (mesh "
                      f"{model.design.mesh.size_mm:g} mm) → {out / 'model'}", highlight=False, soft_wrap=True)
        atlases = None
        if estimator == "atlas" and grid is None:  # the model's own, found (or refused) before the long work
            atlases = model_atlases(scs, model, model_dir or work / "model", scheduler, draft=draft)
        with status("mesh (truth model, finer)", console):
            tm = truth_model(model, cfg.truth)
        console.print(f"truth model: {len(tm.nodes)} nodes, {len(tm.tets)} tets, P{tm.element_order} (mesh "
                      f"{tm.design.mesh.size_mm:g} mm)", highlight=False)
        rows = run_all(scs, model, work, cfg, tm, estimator, grid, scheduler=scheduler, n_workers=workers,
                       shown=out, atlas_dir=model_dir, atlases=atlases, clinical=design_file is None)
        for r in rows:  # the paths the user will see, once the directory is in place
            r["report"] = str(out / Path(r["report"]).relative_to(work))
        wall = time.perf_counter() - t0
        write_summary(out, work, rows, wall)
    index = out / "index.html"
    print_summary(rows)
    for r in rows:
        console.print(f"report: {r['report']}", highlight=False, soft_wrap=True)
    console.print(f"index: {index}  (demo took {wall:.0f} s)", highlight=False, soft_wrap=True)
