"""Mesh convergence of the phantom model: marker-body pose, arm ΔV and urethra ΔV against element
order (P1 / P2) and mesh size, for ν = 0.45 and 0.49 (docs/model.md).

    .venv/bin/python benchmarks/bench_convergence.py [--p1 6 4.5] [--p2 12 9] [--nu 0.45]
        [--cases on-centre urethra] [--solver felupe|softphantom] [--contact-size-mm H]
        [--junction-size-mm H] [--arm-size-mm H] [--fillet-mm R] [--workers 2] [--scheduler ADDRESS] [--json out.json]

The solves are compressible neo-Hookean (E = 142 kPa) on the default design under DESIGN.md §5's
loads (on-centre (0.15, 2.5, −0.2) N on a 4 mm patch; urethra 30 kPa), by the independent
reference of tests/reference/felupe_bip.py (FElupe), which tests/test_fem_reference.py shows equal
to softphantom's own neo-Hookean tets on the same mesh. P1 meshes are exactly the design's linear
meshes (``softphantom design --mesh-size-mm H``); P2 the same construction at order 2 with curved
mid-edge nodes. One Dask task per (order, size, ν), through softphantom.parallel.
Prints one row per setting and, per ν and order, the change between the two finest sizes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "reference"))

from _results import add_results_option, grouped, write_table  # noqa: E402
from bench_reference import ARMS, SOLVERS, run_case  # noqa: E402

from softphantom.fem import ECOFLEX_00_50  # noqa: E402
from softphantom.parallel import dask_client, map_tasks  # noqa: E402


def solve_setting(order: int, size_mm: float, nu: float, cases: tuple[str, ...], E: float,
                  solver: str = "felupe", local: tuple = (), fillet_mm: float | None = None) -> dict:
    """One row: the design meshed at ``size_mm`` (all sizes scaled), then the ``local`` MeshParams
    overrides ((name, mm) pairs: contact_size_mm, junction_size_mm, arm_size_mm) as given, and
    every arm's ``junction_fillet_mm`` set to ``fillet_mm`` (None: the design's)."""
    import sys as _s

    _s.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "reference"))
    _s.path.insert(0, str(Path(__file__).resolve().parent))
    from felupe_bip import bip_tet10

    from softphantom.design import BIPDesign

    import dataclasses

    import resource

    t0, c0 = time.perf_counter(), time.process_time()
    d = BIPDesign()
    d = dataclasses.replace(d, mesh=dataclasses.replace(d.mesh.scaled_to(size_mm), **dict(local)))
    if fillet_mm is not None:
        d = dataclasses.replace(d, arms=tuple(dataclasses.replace(a, junction_fillet_mm=fillet_mm) for a in d.arms))
    mesh = bip_tet10(d, None, order=order)
    out = {"order": order, "mesh_size_mm": size_mm, "nu": nu, "nodes": len(mesh.nodes), "dof": 3 * len(mesh.nodes),
           "solver": solver, "local": dict(local), "fillet_mm": d.arms[0].junction_fillet_mm}
    for c in cases:
        out[c] = run_case(mesh, c, E, nu, solver=solver)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    out["cpu_s"] = round(time.process_time() - c0, 1)
    out["max_rss_GB"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)  # the worker's peak
    return out


def _row(r: dict) -> str:
    loc = "".join(f" {k.replace('_size_mm', '')} {v:g}" for k, v in r.get("local", {}).items())
    loc += f" fillet {r['fillet_mm']:g}" if r.get("fillet_mm") else ""
    parts = [f"P{r['order']} {r['mesh_size_mm']:>4g} mm{loc} ν {r['nu']:.2f} {r['nodes']:>6d} nodes"]
    if "on-centre" in r:
        c = r["on-centre"]
        parts.append(f"y {c['y_mm']:6.3f} mm yaw {c['yaw_deg']:6.3f}° dV " +
                     " ".join(f"{c['dV_mm3'][k]:+7.2f}" for k in ARMS))
    if "urethra" in r:
        u = r["urethra"]
        parts.append(f"urethra dV {u['dV_mm3']['urethra']:7.1f} mm³ near_urethra {u['near_urethra_mm']:.3f} mm")
    parts.append(f"{r['wall_s']} s wall, {r.get('cpu_s', '?')} CPU-s, max RSS {r.get('max_rss_GB', '?')} GB")
    return " | ".join(parts)


def _doc_row(r: dict) -> tuple[str, ...]:
    loc = "".join(f" + `{k}` {v:g}" for k, v in r.get("local", {}).items())
    c, u = r.get("on-centre"), r.get("urethra")
    return (f"{r['nu']:.2f}", f"P{r['order']}", f"{r['mesh_size_mm']:g}{loc}", grouped(r["nodes"]),
            f"{c['y_mm']:.3f}" if c else "", f"{c['yaw_deg']:.3f}" if c else "",
            ", ".join(f"{c['dV_mm3'][k]:+.2f}" for k in ARMS).replace("-", "−") if c else "",
            f"{u['dV_mm3']['urethra']:.1f}" if u else "", f"{u['near_urethra_mm']:.3f}" if u else "",
            f"{r['cpu_s']:.0f}", f"{r['max_rss_GB']:.1f} GB")


def quantities(r: dict) -> dict[str, float]:
    q = {}
    if "on-centre" in r:
        c = r["on-centre"]
        q.update({"y_mm": c["y_mm"], "yaw_deg": c["yaw_deg"], **{f"dV_{k}": c["dV_mm3"][k] for k in ARMS}})
    if "urethra" in r:
        q.update({"urethra_dV": r["urethra"]["dV_mm3"]["urethra"], "near_urethra_mm": r["urethra"]["near_urethra_mm"]})
    return q


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    # defaults: a quick subset for `make bench`; docs/model.md gives the full table's command
    ap.add_argument("--p1", type=float, nargs="*", default=[6.0, 4.5])
    ap.add_argument("--p2", type=float, nargs="*", default=[12.0, 9.0])
    ap.add_argument("--nu", type=float, nargs="+", default=[0.45])
    ap.add_argument("--cases", nargs="+", default=["on-centre", "urethra"], choices=["on-centre", "off-centre", "urethra"])
    ap.add_argument("--solver", default="felupe", choices=SOLVERS,
                    help="felupe: the independent reference; softphantom: its own neo-Hookean FEM on the same "
                         "mesh and loads (equal to 1e-9, several times faster)")
    ap.add_argument("--contact-size-mm", type=float, default=0.0,
                    help="local size near the interaction points (MeshParams.contact_size_mm; 0 off)")
    ap.add_argument("--junction-size-mm", type=float, default=0.0,
                    help="local size along the arm-bulb edges (MeshParams.junction_size_mm; 0 off)")
    ap.add_argument("--arm-size-mm", type=float, default=None, help="arm element size instead of the scaled one")
    ap.add_argument("--fillet-mm", type=float, default=None,
                    help="every arm's junction_fillet_mm (ArmParams; default: the design's)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scheduler", default=None)
    ap.add_argument("--json", type=Path)
    add_results_option(ap, "convergence")
    a = ap.parse_args(argv)
    E = ECOFLEX_00_50.E_Pa
    local = tuple((k, v) for k, v in (("contact_size_mm", a.contact_size_mm), ("junction_size_mm", a.junction_size_mm),
                                      ("arm_size_mm", a.arm_size_mm)) if v)
    args = [(o, h, nu, tuple(a.cases), E, a.solver, local, a.fillet_mm) for nu in a.nu for o, hs in ((1, a.p1), (2, a.p2)) for h in hs]
    # the biggest first, so the pool stays busy to the end
    args.sort(key=lambda t: -(t[0] ** 3) / t[1] ** 3)
    t0 = time.perf_counter()
    with dask_client(a.scheduler, n_workers=a.workers) as client:
        res = map_tasks(client, solve_setting, args, label=None,
                        on_result=lambda r: print(_row(r.value) if r.ok else f"failed: {r.error}", flush=True))
    rows = sorted((r.value for r in res if r.ok), key=lambda r: (r["nu"], r["order"], -r["mesh_size_mm"]))
    print(f"\n{len(rows)} settings in {time.perf_counter() - t0:.0f} s\n")
    for r in rows:
        print(_row(r))
    print("\nchange between the two finest sizes (per ν and order), % of the finer value:")
    for nu in a.nu:
        for o in (1, 2):
            sel = [r for r in rows if r["nu"] == nu and r["order"] == o]
            if len(sel) < 2:
                continue
            q1, q2 = quantities(sel[-2]), quantities(sel[-1])
            d = {k: round(100 * (q1[k] - q2[k]) / abs(q2[k]), 2) for k in q2 if abs(q2[k]) > 1e-9}
            print(f"  P{o} ν {nu}: {sel[-2]['mesh_size_mm']:g} → {sel[-1]['mesh_size_mm']:g} mm: {d}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    fillet = {r["fillet_mm"] for r in rows}
    write_table(a.results_name, ("ν", "element", "mesh", "nodes", "y mm", "yaw °", "ΔV fz+, fz−, bx+, bx− mm³",
                                 "urethra ΔV mm³", "`near_urethra` mm", "CPU s", "peak RSS"), [_doc_row(r) for r in rows],
                caption=f"Solver {a.solver}; junction fillet {', '.join(f'{f:g}' for f in sorted(fillet))} mm:")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
