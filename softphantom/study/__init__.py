"""Design studies: sweep and optimize design parameters, each variant meshed and linearized on Dask.

:func:`load_sweep_config` reads a sweep file; :func:`run_sweep` evaluates its variants (cached,
resumable) and writes ``results.parquet`` and ``report.html``; :func:`~softphantom.study.optimize.optimize`
searches the continuous parameters. docs/sweep.md says what each output means.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from softphantom.study.config import SweepConfig, Variant, load_sweep_config, sweep_config_from_dict
from softphantom.study.run import RESULTS, SweepRun, evaluate_variants, read_parquet, require_pyarrow, write_parquet
from softphantom.study.variant import TIMING_COLUMNS, design_problem, evaluate_variant


def _meta(cfg: SweepConfig, kind: str) -> dict:
    from softphantom import __version__

    return {"softphantom": __version__, "kind": kind, "name": cfg.name, "method": cfg.method,
            "samples": cfg.samples, "seed": cfg.seed, "parameters": [p.path for p in cfg.params],
            "evaluate": cfg.settings.as_dict(), "fixed": cfg.fixed}


def run_sweep(cfg: SweepConfig, client: Any, out: Path, report: bool = True) -> SweepRun:
    """Evaluate every variant of ``cfg`` on ``client``; write ``out/results.parquet`` (and ``report.html``).
    When no variant is ok nothing is written (the run's ``path`` is None; its rows say why)."""
    require_pyarrow()
    out = Path(out)
    run = evaluate_variants(client, cfg.variants(), out)
    if not any(r.get("status") == "ok" for r in run.rows):
        return run
    path = write_parquet(run.rows, out / RESULTS, _meta(cfg, "sweep"))
    if report:
        from softphantom.study.report import write_report

        write_report(run.rows, out / "report.html", f"Design study '{cfg.name}'",
                     note=f"{cfg.method}, seed {cfg.seed}; {run.cached} from the cache, {run.computed} computed.")
    return SweepRun(run.rows, run.cached, run.computed, path)


def run_optimize(cfg: SweepConfig, client: Any, out: Path):
    """Differential evolution for ``cfg`` (see :mod:`softphantom.study.optimize`); writes
    ``out/optimize.parquet``, ``out/optimize.json`` (the best candidate) and ``out/optimize.html``."""
    from softphantom.study.optimize import optimize
    from softphantom.study.report import write_report

    require_pyarrow()
    out = Path(out)
    res = optimize(cfg, client, out)
    write_parquet(res.rows, out / "optimize.parquet", _meta(cfg, "optimize"))
    (out / "optimize.json").write_text(json.dumps(
        {"best_params": res.params, "value": res.value, "objective": cfg.optimize.objective,
         "evaluations": res.evaluations, "message": res.message,
         "best_row": {k: v for k, v in res.row.items()}}, indent=2, default=str) + "\n", encoding="utf-8")
    write_report(res.rows, out / "optimize.html", f"Optimization '{cfg.name}'",
                 note=f"differential evolution, {res.evaluations} candidates; best {cfg.optimize.objective} = {res.value:.4g}.")
    return res


__all__ = [
    "RESULTS",
    "SweepConfig",
    "SweepRun",
    "TIMING_COLUMNS",
    "design_problem",
    "Variant",
    "evaluate_variant",
    "evaluate_variants",
    "load_sweep_config",
    "read_parquet",
    "require_pyarrow",
    "run_optimize",
    "run_sweep",
    "sweep_config_from_dict",
]
