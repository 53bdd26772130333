"""``softphantom sweep``: a design study (grid, random or Latin hypercube) or an optimization on Dask."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import Out, Scheduler, Workers, check_workers


@app.command("sweep")
def sweep_command(
    config: Path = typer.Option(..., "--config", help="Sweep file (TOML; docs/sweep.md)."),
    out: Out = ...,
    scheduler: Scheduler = None,
    workers: Workers = None,
    optimize: bool = typer.Option(False, "--optimize", help="Differential evolution over the continuous parameters instead of the sample."),
    objective: Optional[str] = typer.Option(None, "--objective", help="With --optimize: the column to optimize, instead of "
                                            "the file's optimize.objective (e.g. obs_sv_min_mm3, maximized; docs/sweep.md)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show the variants' progress."),
) -> None:
    """Mesh and linearize every variant of a design study; write results.parquet, report.html and the
    variants/ cache into the directory --out (resumes from OUT/variants/)."""
    from softphantom.cli.logs import hide_progress
    from softphantom.study import load_sweep_config, require_pyarrow

    check_workers(workers)
    if not progress:
        hide_progress()
    cfg = load_sweep_config(config)
    if objective is not None:
        import dataclasses

        from softphantom.errors import UserError
        from softphantom.study.optimize import check_objective

        if not optimize:
            raise UserError("--objective: only with --optimize")
        cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, objective=check_objective(objective, "--objective")))
    require_pyarrow()
    n = len(cfg.variants()) if not optimize else None
    created = not out.exists()
    try:
        run = _run(cfg, out, scheduler, workers, optimize, n)
    except BaseException:
        if created:
            _remove_empty(out)  # an interrupted or refused run leaves no empty folder (a resumable cache stays)
        raise
    if run is None:
        return
    ok = sum(r.get("status") == "ok" for r in run.rows)
    if run.path is None:  # no variant is ok: nothing written
        for line in why_not_ok(run.rows):
            console.print(line, highlight=False, soft_wrap=True)
        if created:
            import shutil

            shutil.rmtree(out, ignore_errors=True)
        invalid = sum(r.get("status") == "invalid" for r in run.rows)
        from softphantom.errors import SolverError, UserError

        what = ("its one variant is invalid" if len(run.rows) == 1 and invalid else
                f"all {len(run.rows)} variants are invalid" if invalid == len(run.rows) else
                f"no variant of {len(run.rows)} is ok ({invalid} invalid, {len(run.rows) - invalid} failed)")
        error = UserError if invalid == len(run.rows) else SolverError
        raise error(f"sweep '{cfg.name}': {what} (reasons above); nothing written to {out}")
    console.print(f"{ok} ok, {len(run.rows) - ok} invalid or failed ({run.cached} from the cache, "
                  f"{run.computed} computed); wrote {out}/results.parquet and report.html", highlight=False,
                  soft_wrap=True)
    for line in why_not_ok(run.rows):
        console.print(line, highlight=False, soft_wrap=True)


def _run(cfg, out: Path, scheduler: Optional[str], workers: Optional[int], optimize: bool, n: Optional[int]):
    """The study on its cluster: the sweep's run, or None after an optimization (reported here)."""
    from softphantom.parallel import dask_client
    from softphantom.study import run_optimize, run_sweep

    with dask_client(scheduler, workers) as client:
        where = scheduler or f"a local cluster of {len(client.scheduler_info()['workers'])} workers"
        if optimize:
            console.print(f"optimizing '{cfg.name}' on {where}", highlight=False)
            res = run_optimize(cfg, client, out)
            console.print(f"best {cfg.optimize.objective} = {res.value:.4g} after {res.evaluations} candidates: "
                          + ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}" for k, v in res.params.items()),
                          highlight=False)
            console.print(f"wrote {out}/optimize.parquet, optimize.json, optimize.html", highlight=False)
            return None
        console.print(f"sweep '{cfg.name}': {n} variants on {where}", highlight=False)
        return run_sweep(cfg, client, out)


def _remove_empty(out: Path) -> None:
    """Remove ``out`` if it holds nothing but empty folders."""
    if not out.is_dir():
        return
    for d in sorted((p for p in out.rglob("*")), key=lambda p: len(p.parts), reverse=True):
        if d.is_dir() and not any(d.iterdir()):
            d.rmdir()
    if not any(out.iterdir()):
        out.rmdir()


def why_not_ok(rows: list[dict], most: int = 10) -> list[str]:
    """One line per variant that is not ok (its status and reason), at most ``most`` of them.

    >>> why_not_ok([{"variant": 0, "status": "ok"}, {"variant": 1, "status": "invalid", "error": "DesignError: x"}])
    ['  variant 1 invalid: DesignError: x']
    """
    bad = [r for r in rows if r.get("status") != "ok"]
    lines = [f"  variant {r.get('variant')} {r.get('status')}: {r.get('error') or 'no reason recorded'}" for r in bad[:most]]
    if len(bad) > most:
        lines.append(f"  … and {len(bad) - most} more (report.html lists every one)")
    return lines
