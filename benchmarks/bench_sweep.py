"""Design sweeps on Dask: 100 variants of the default design at the coarse mesh, speed-up from 1 to
2 workers, the same results in-process and on a local cluster, and a run with both cores busy.

Run: ``.venv/bin/python benchmarks/bench_sweep.py [--variants 100] [--subset 10] [--mesh-size-mm 12]``

On a machine shared with other work the wall times measure the sharing; the worker CPU time
(``cpu_s`` of each row) does not, so the benchmark also prints what the variants cost on 2 idle
cores, and with ``--variants`` other than 100 projects that to 100.

1. ``--variants`` Latin-hypercube variants of the default design (arm radius and wall, the front
   arms' y direction, tube length) on a local cluster of 2 worker processes, from an empty cache:
   wall time (goal: ≤ 10 min on 2 cores), ok/invalid counts, median seconds per variant.
2. The first ``--subset`` variants in-process (Dask threads in this process, no cluster), on 1
   worker process and on 2 (each from an empty cache, cluster start-up not counted): wall times and
   the 1 → 2 speed-up; the in-process rows against the 2-worker rows of step 1 (largest relative
   difference over every non-timing column).
3. The 2-worker subset again while this benchmark runs its own load (one busy-looping process
   per core): the figure with both cores busy.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _results import write_table

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from softphantom.parallel import dask_client  # noqa: E402
from softphantom.study import TIMING_COLUMNS, evaluate_variants, sweep_config_from_dict  # noqa: E402
from softphantom.study.run import rows_equal  # noqa: E402


def _config(n: int, mesh_size_mm: float):
    return sweep_config_from_dict({
        "sweep": {"name": "bench", "method": "lhs", "samples": n, "seed": 7},
        "fixed": {"mesh_size_mm": mesh_size_mm},
        "parameters": {
            "arms.*.radius_mm": {"min": 5.5, "max": 6.5},
            "arms.*.wall_mm": {"min": 2.0, "max": 3.0},
            "arms.front_zpos.direction[1]": {"min": -0.8, "max": -0.4},
            "arms.front_zneg.direction[1]": {"min": -0.8, "max": -0.4},
            "sensing.tube_length_m": {"min": 1.0, "max": 12.0, "log": True},
        },
    })


def _timed(variants, out: Path, **client_kw):
    with dask_client(**client_kw) as client:
        t = time.perf_counter()
        run = evaluate_variants(client, variants, out)
        return time.perf_counter() - t, run.rows


def _burn() -> None:  # pragma: no cover - a load process
    while True:
        pass


def _max_rel_diff(a, b) -> float:
    worst = 0.0
    for ra, rb in zip(a, b):
        for k, x in ra.items():
            y = rb.get(k)
            if k in TIMING_COLUMNS or not isinstance(x, float) or not isinstance(y, float):
                continue
            if math.isfinite(x) and math.isfinite(y) and max(abs(x), abs(y)) > 0:
                worst = max(worst, abs(x - y) / max(abs(x), abs(y)))
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", type=int, default=100)
    ap.add_argument("--subset", type=int, default=10)
    ap.add_argument("--mesh-size-mm", type=float, default=12.0)
    args = ap.parse_args()
    cfg = _config(args.variants, args.mesh_size_mm)
    variants = cfg.variants()
    sub = variants[: args.subset]
    print(f"# bench_sweep: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f} at start; coarse mesh {args.mesh_size_mm:g} mm")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        wall, rows = _timed(variants, tmp / "full", n_workers=2)
        ok = [r for r in rows if r["status"] == "ok"]
        per = statistics.median(r["total_s"] for r in ok) if ok else float("nan")
        cpu = sum(r.get("cpu_s", 0.0) for r in rows)
        goal = f" ({'meets' if wall <= 600 else 'misses'} the 600 s goal)" if len(variants) == 100 else ""
        doc = [(f"{len(variants)} variants, 2 workers", f"{wall:.0f} s wall{goal}; {len(ok)} ok, {len(rows) - len(ok)} "
                f"invalid; median {per:.1f} s a variant; worker CPU {cpu:.0f} s")]
        print(f"{len(variants)} variants, 2 workers: {wall:.1f} s wall{goal}; {len(ok)} ok, {len(rows) - len(ok)} invalid/failed; median {per:.2f} s a variant; "
              f"worker CPU {cpu:.0f} s in all, i.e. {cpu / 2:.0f} s on 2 otherwise idle cores "
              f"(load average now {os.getloadavg()[0]:.1f})")
        if len(variants) != 100:  # a loaded machine: the goal's figure from the CPU actually spent
            print(f"projected for 100 such variants on 2 idle cores: {cpu / len(variants) * 100 / 2:.0f} s "
                  f"(worker CPU per variant × 100 / 2; goal 600 s)")

        t_in, rows_in = _timed(sub, tmp / "inproc", processes=False, n_workers=1)
        t1, _ = _timed(sub, tmp / "w1", n_workers=1)
        t2, rows2 = _timed(sub, tmp / "w2", n_workers=2)
        print(f"{len(sub)} variants: in-process {t_in:.1f} s, 1 worker {t1:.1f} s, 2 workers {t2:.1f} s; "
              f"speed-up 1 -> 2 workers {t1 / t2:.2f}x")
        doc.append((f"{len(sub)} variants: in-process / 1 worker / 2 workers",
                    f"{t_in:.1f} / {t1:.1f} / {t2:.1f} s (1 → 2 workers {t1 / t2:.2f}×)"))
        diffs = rows_equal(rows_in, rows[: len(sub)], TIMING_COLUMNS, rtol=1e-9)
        print(f"in-process vs local cluster (2 workers), {len(sub)} variants: "
              f"{'equal' if not diffs else f'{len(diffs)} differences, e.g. {diffs[0]}'} to 1e-9 relative "
              f"(largest relative difference {_max_rel_diff(rows_in, rows[: len(sub)]):.1e})")
        doc.append(("in-process vs local cluster", f"{'equal' if not diffs else f'{len(diffs)} differences'} to 1e-9 "
                    f"relative (largest difference {_max_rel_diff(rows_in, rows[: len(sub)]):.1e})"))
        same = rows_equal(rows2, rows[: len(sub)], TIMING_COLUMNS, rtol=1e-9)
        print(f"2-worker subset vs the same variants in the full run: {'equal' if not same else same[0]}")

        ctx = mp.get_context("spawn")
        burners = [ctx.Process(target=_burn, daemon=True) for _ in range(os.cpu_count() or 1)]
        for b in burners:
            b.start()
        try:
            tb, _ = _timed(sub, tmp / "busy", n_workers=2)
        finally:
            for b in burners:
                b.terminate()
            for b in burners:
                b.join()
        print(f"{len(sub)} variants, 2 workers, both cores busy with {len(burners)} load processes: {tb:.1f} s "
              f"({tb / t2:.2f}x the quiet 2-worker time)")
    doc.append((f"{len(sub)} variants, 2 workers, both cores busy", f"{tb:.1f} s ({tb / t2:.2f}× the quiet time)"))
    write_table("sweep", ("measure", "result"), doc,
                caption=f"Coarse {args.mesh_size_mm:g} mm mesh, Latin-hypercube variants of the default design:")


if __name__ == "__main__":
    main()
