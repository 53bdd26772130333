"""``--optimize``: differential evolution over the continuous parameters, its generations on Dask.

Why differential evolution (scipy) rather than a surrogate fitted to the sweep: every objective
value comes from a new mesh, and a mesh changes by whole elements as a parameter moves, so the
outputs are piecewise smooth with small jumps — gradients and a smooth surrogate are misled by
them, a population method is not; bounds are native; a variant that fails (an invalid design, a
solver that gives up) is simply a bad value; and ``updating="deferred"`` evaluates a whole
generation (``popsize × n_params`` candidates) at once, which is what the Dask workers want. Each
candidate is an ordinary variant: cached under its key, so a repeated candidate or a resumed run
costs nothing, and every evaluation is a row of ``optimize.parquet``.

Objective: minimize ``optimize.objective`` (default the worst-axis force resolution, N per count),
or maximize it for the ones :data:`OBJECTIVES` marks (``obs_sv_min_mm3``, the smallest scaled
singular value of W at rest: its negative is minimized), subject to ``range_min_N ≥ min_range_N`` and ``silicone_mL ≤ max_silicone_mL``; an infeasible or
failed candidate scores ``PENALTY`` plus its relative violation, worse than any feasible one.
Parameters given as ``values`` lists are held at their first value.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from softphantom.errors import UserError
from softphantom.study.config import SweepConfig, Variant
from softphantom.study.run import evaluate_variants

PENALTY = 1e3
#: objective column -> +1 (minimized) or -1 (maximized)
OBJECTIVES = {"res_force_worst_N": 1, "res_target_worst_mm": 1, "cond_W": 1, "res_yaw_deg": 1, "res_pitch_deg": 1,
              "obs_sv_min_mm3": -1}


def check_objective(name: str, option: str = "optimize.objective") -> str:
    """``name`` if it is one of :data:`OBJECTIVES`, else a one-line :class:`UserError` naming ``option``.

    >>> check_objective("cond", "--objective")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --objective: 'cond' is not one of res_force_worst_N, res_target_worst_mm, cond_W, res_yaw_deg, res_pitch_deg, obs_sv_min_mm3
    """
    if name not in OBJECTIVES:
        raise UserError(f"{option}: {name!r} is not one of {', '.join(OBJECTIVES)}")
    return name


def score(row: dict, objective: str, min_range_N: float, max_silicone_mL: float) -> float:
    """The value differential evolution minimizes for one result row (a maximized objective's
    negative; feasible values of the objectives are far from ``PENALTY``).

    >>> score({"status": "ok", "res_force_worst_N": 0.02, "range_min_N": 8.0, "silicone_mL": 100.0}, "res_force_worst_N", 5.0, 120.0)
    0.02
    >>> score({"status": "ok", "res_force_worst_N": 0.02, "range_min_N": 4.0, "silicone_mL": 100.0}, "res_force_worst_N", 5.0, 120.0)
    1200.0
    >>> score({"status": "invalid"}, "res_force_worst_N", 5.0, 120.0)
    2000.0
    >>> score({"status": "ok", "obs_sv_min_mm3": 13.4, "range_min_N": 8.0, "silicone_mL": 100.0}, "obs_sv_min_mm3", 5.0, 120.0)
    -13.4
    """
    if row.get("status") != "ok":
        return 2 * PENALTY
    v = row.get(objective)
    if v is None or not math.isfinite(v):
        return 2 * PENALTY
    viol = 0.0
    if min_range_N > 0 and row["range_min_N"] < min_range_N:
        viol += (min_range_N - row["range_min_N"]) / min_range_N
    if math.isfinite(max_silicone_mL) and row["silicone_mL"] > max_silicone_mL:
        viol += (row["silicone_mL"] - max_silicone_mL) / max_silicone_mL
    return PENALTY * (1.0 + viol) if viol > 0 else OBJECTIVES[objective] * float(v)


@dataclass(frozen=True)
class OptimizeResult:
    """The best candidate (``params`` by path, its ``row``, its ``value``: the objective's, or
    the penalty score where no candidate was feasible), all evaluated rows, and scipy's message."""

    params: dict
    row: dict
    value: float
    rows: list[dict]
    evaluations: int
    message: str


def optimize(cfg: SweepConfig, client: Any, out: Path) -> OptimizeResult:
    """Run differential evolution for ``cfg`` on ``client``; candidates are cached under ``out``."""
    from scipy.optimize import differential_evolution

    o = cfg.optimize
    check_objective(o.objective)
    cont = [p for p in cfg.params if p.continuous and p.hi > p.lo]
    if not cont:
        raise UserError("--optimize: no continuous parameter (give at least one {min, max} with max > min)")
    held = {p.path: (p.values[0] if p.values else p.lo) for p in cfg.params if p not in cont}
    seen: list[dict] = []
    count = [0]

    def as_variant(x: Sequence[float]) -> Variant:
        vals = dict(held)
        vals.update({p.path: float(xi) for p, xi in zip(cont, x)})
        count[0] += 1
        return cfg.resolve(count[0] - 1, vals)

    def batch_map(_func, population) -> list[float]:
        variants = [as_variant(x) for x in population]
        run = evaluate_variants(client, variants, out, label=f"generation {len(seen) // max(len(variants), 1)}")
        seen.extend(run.rows)
        return [score(r, o.objective, o.min_range_N, o.max_silicone_mL) for r in run.rows]

    res = differential_evolution(
        lambda x: 0.0,  # never called: batch_map evaluates the population on the workers
        [(p.lo, p.hi) for p in cont], maxiter=o.maxiter, popsize=o.popsize, polish=False,
        updating="deferred", workers=batch_map, rng=np.random.default_rng(o.seed), tol=0.0,
    )
    scores = [score(r, o.objective, o.min_range_N, o.max_silicone_mL) for r in seen]
    best = int(np.argmin(scores))
    best_params = {k[2:]: v for k, v in seen[best].items() if k.startswith("p.")}
    value = scores[best] if scores[best] >= PENALTY else OBJECTIVES[o.objective] * scores[best]
    return OptimizeResult(best_params, seen[best], value, seen, len(seen), str(res.message))
