"""Molds of a multi-material design: the whole two-step cast (1.5 mm Sorta-Clear 12 shell, two
lesions) built and checked, with the cast pieces' volumes against the closed forms, and its cost
against the one-material design's molds measured in the same run (the peer ratio).

Run: ``.venv/bin/python benchmarks/bench_multimaterial.py [--no-busy]``

1. ``build_parts`` of the one-material default design and of the layered one (every part checked
   closed, manifold, not self-intersecting by ``write_molds``): wall and CPU seconds, the ratio.
2. The layered design's cast pieces: the shell against 4/3 π (abc − (a−t)(b−t)(c−t)) less its rod
   channel and sockets (within 2 %), each lesion against its ellipsoid (1 %), the infill against the
   inner ellipsoid less urethra and lesions (2 %). A miss exits 1: these are the checks
   tests/test_multimaterial.py leaves here because the cast shell takes the longest to build.
3. The layered build again with one busy-looping process per core started by this benchmark (the
   figure with both cores busy); ``--no-busy`` skips it.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

from _results import write_table

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from softphantom.design import BIPDesign, design_from_dict, design_to_dict  # noqa: E402
from softphantom.molds import build_parts, write_molds  # noqa: E402

SHELL_MM = 1.5
LESIONS = {"L1": ((14.0, 0.0, -10.0), (6.0, 6.0, 6.0)), "L2": ((-14.0, 0.0, -10.0), (7.0, 5.0, 5.0))}


def layered_design():
    data = design_to_dict(BIPDesign())
    data["layers"] = {"shell_mm": SHELL_MM, "lesions": {k: {"center_mm": list(c), "semi_axes_mm": list(s)}
                                                        for k, (c, s) in LESIONS.items()}}
    data["region_materials"] = {"bulb": "ecoflex_gel", "shell": "sorta_clear_12", "lesions": "ecoflex_00_50",
                                "arms": "ecoflex_00_50"}
    return design_from_dict(data)


def _timed_build(design, out: Path):
    w, c = time.perf_counter(), time.process_time()
    parts = build_parts(design)
    write_molds(parts, out)  # checks every part before writing it
    return parts, time.perf_counter() - w, time.process_time() - c


def _burn() -> None:  # pragma: no cover - a load process
    while True:
        pass


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-busy", action="store_true", help="skip the run with both cores busy")
    args = ap.parse_args()
    print(f"# bench_multimaterial: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start")
    layered = layered_design()
    failures = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        one, w1, c1 = _timed_build(BIPDesign(), tmp / "one")
        parts, w2, c2 = _timed_build(layered, tmp / "layered")
        print(f"one material: {len(one)} parts in {w1:.1f} s wall, {c1:.1f} CPU-s; layered (shell {SHELL_MM:g} mm, "
              f"{len(LESIONS)} lesions): {len(parts)} parts in {w2:.1f} s wall, {c2:.1f} CPU-s; ratio {c2 / c1:.2f}x CPU "
              f"(load average now {os.getloadavg()[0]:.1f})")
        write_table("multimaterial", ("design", "parts", "CPU-s"),
                    [("one material (default)", len(one), f"{c1:.1f}"),
                     (f"shell {SHELL_MM:g} mm + {len(LESIONS)} lesions", len(parts), f"{c2:.1f}")], right=(1, 2))
        casts = {p.name: p for p in parts if p.kind == "cast"}
        a, b, c = layered.bulb.semi_axes_mm
        t = SHELL_MM
        inner = 4.0 / 3.0 * math.pi * (a - t) * (b - t) * (c - t)
        shell = 4.0 / 3.0 * math.pi * a * b * c - inner
        u = layered.urethra
        checks = [("cast_shell", casts["cast_shell"].volume_mm3, shell, 0.02),
                  ("cast_infill", casts["cast_infill"].volume_mm3,
                   inner - u.volume_mm3 - sum(x.volume_mm3 for x in layered.layers.lesions), 0.02)]
        checks += [(f"cast_{x.region}", casts[f"cast_{x.region}"].volume_mm3, x.volume_mm3, 0.01)
                   for x in layered.layers.lesions]
        rows = []
        for name, got, want, tol in checks:
            err = got / want - 1.0
            ok = abs(err) <= tol
            print(f"{name}: {got:.0f} mm³ vs closed form {want:.0f} mm³ ({100 * err:+.2f} %, tolerance "
                  f"{100 * tol:g} %) {'ok' if ok else 'MISS'}; {casts[name].material}")
            rows.append((name, casts[name].material, f"{got:.0f}", f"{want:.0f}", f"{100 * err:+.2f}", f"{100 * tol:g}"))
            if not ok:
                failures.append(name)
        write_table("multimaterial_volumes", ("cast piece", "material", "volume mm³", "closed form mm³", "error %",
                                              "tolerance %"), rows, right=(2, 3, 4, 5))
        if not args.no_busy:
            ctx = mp.get_context("spawn")
            burners = [ctx.Process(target=_burn, daemon=True) for _ in range(os.cpu_count() or 1)]
            for p in burners:
                p.start()
            try:
                _, w3, c3 = _timed_build(layered, tmp / "busy")
            finally:
                for p in burners:
                    p.kill()
                    p.join()
            print(f"layered, with {len(burners)} busy processes started here: {w3:.1f} s wall, {c3:.1f} CPU-s "
                  f"(load average now {os.getloadavg()[0]:.1f})")
    if failures:
        print(f"FAILED: {', '.join(failures)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
