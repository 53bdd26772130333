"""``softphantom sweep``: a design study (grid, random or Latin hypercube) or an optimization on Dask."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from softphantom.cli.app import app, console


@app.command("sweep")
def sweep_command(
    config: Path = typer.Option(..., "--config", help="Sweep file (TOML; docs/sweep.md)."),
    out: Path = typer.Option(..., "--out", help="Output directory: results.parquet, report.html, variants/ cache."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler (tcp://HOST:PORT); default: a local cluster."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Local cluster: worker processes (default: all cores)."),
    optimize: bool = typer.Option(False, "--optimize", help="Differential evolution over the continuous parameters instead of the sample."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Mesh and linearize every variant of a design study; write results.parquet and report.html (resumes from OUT/variants/)."""
    from softphantom.parallel import dask_client
    from softphantom.study import load_sweep_config, require_pyarrow, run_optimize, run_sweep

    cfg = load_sweep_config(config)
    require_pyarrow()
    n = len(cfg.variants()) if not optimize else None
    with dask_client(scheduler, workers) as client:
        where = scheduler or f"a local cluster of {len(client.scheduler_info()['workers'])} workers"
        if optimize:
            console.print(f"optimizing '{cfg.name}' on {where}", highlight=False)
            res = run_optimize(cfg, client, out, progress=progress)
            console.print(f"best {cfg.optimize.objective} = {res.value:.4g} after {res.evaluations} candidates: "
                          + ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}" for k, v in res.params.items()),
                          highlight=False)
            console.print(f"wrote {out}/optimize.parquet, optimize.json, optimize.html", highlight=False)
            return
        console.print(f"sweep '{cfg.name}': {n} variants on {where}", highlight=False)
        run = run_sweep(cfg, client, out, progress=progress)
    ok = sum(r.get("status") == "ok" for r in run.rows)
    console.print(f"{ok} ok, {len(run.rows) - ok} invalid or failed ({run.cached} from the cache, "
                  f"{run.computed} computed); wrote {out}/results.parquet and report.html", highlight=False)
