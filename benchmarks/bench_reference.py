"""The independent reference of DESIGN.md §5, recomputed: FElupe (quadratic tets, compressible
neo-Hookean, E = 142 kPa, ν = 0.45) on the default design under the three load cases, beside the
table DESIGN.md gives.

    .venv/bin/python benchmarks/bench_reference.py [--mesh-size-mm 9 4.5] [--json out.json]

The default 9 mm takes minutes; 4.5 mm (73 k nodes) about an hour on a busy 2-core machine.

Needs the ``test`` extra (felupe). Prints per mesh size: marker-body y / yaw, the four arms' ΔV,
urethra ΔV and the ``near_urethra`` shift, wall time and Newton iterations.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "reference"))

from _results import add_results_option, grouped, write_table  # noqa: E402
from felupe_bip import RefSolution, bip_tet10, cavity_volumes, patch_load, probe, solve_felupe  # noqa: E402

from softphantom.design import BIPDesign  # noqa: E402
from softphantom.fem import ECOFLEX_00_50  # noqa: E402
from softphantom.pose import pose_of_markers  # noqa: E402

ARMS = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
# DESIGN.md §5, "converged NH P2" column
DESIGN = {
    "on-centre": {"y_mm": 5.78, "yaw_deg": 5.57, "dV_mm3": [11.2, 9.1, -12.2, -8.0]},
    "off-centre": {"y_mm": 7.38, "yaw_deg": 17.8, "dV_mm3": [14.0, 15.6, None, None]},
    "urethra": {"urethra_dV_mm3": 2079.0, "near_urethra_mm": 1.18},
}
CASES = {
    "on-centre": dict(force=(0.15, 2.5, -0.2), at="on-centre"),
    "off-centre": dict(force=(0.4, 3.0, 0.3), at="off-centre"),
    "urethra": dict(pressures={"urethra": 30e3}),
}


SOLVERS = ("felupe", "softphantom")


def solve_softphantom(mesh, E: float, nu: float, *, force=None, at=None, patch_radius: float = 4e-3,
                      pressures=None) -> RefSolution:
    """The same problem as :func:`felupe_bip.solve_felupe` (same mesh, law, the reference's own patch
    load and cavities) solved by softphantom's neo-Hookean P1/P2 FEM (tests/test_fem_reference.py:
    equal to FElupe's to 1e-9), Newton to ‖r‖ ≤ 1e-10 of the load."""
    from softphantom.fem import NeoHookean, build_fem, solve_static

    fem = build_fem(mesh.nodes, mesh.tets, NeoHookean(E, nu), mesh.fixed_nodes, cavities=mesh.cavities)
    f = None
    if force is not None and np.any(force):
        f = patch_load(mesh.nodes, mesh.outer, len(mesh.nodes), at, force, patch_radius)
    sol = solve_static(fem, f, pressures=pressures, tol=1e-10, max_iter=40)
    if not sol.converged:
        raise RuntimeError(f"softphantom solve: {sol.status}")
    return RefSolution(sol.x, sol.iterations, sol.residual_norm)


def run_case(mesh, name: str, E: float, nu: float, patch_radius_m: float = 4e-3, solver: str = "felupe") -> dict:
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    case = dict(CASES[name])
    if "at" in case:
        case["at"] = mesh.points[case["at"]]
    t0 = time.perf_counter()
    if solver == "softphantom":
        sol = solve_softphantom(mesh, E, nu, patch_radius=patch_radius_m, **case)
    else:
        sol = solve_felupe(mesh, mu, lam, patch_radius=patch_radius_m, **case)
    wall = time.perf_counter() - t0
    markers = [k for k in mesh.points if k.startswith("m") and k[1:].isdigit()]
    P = probe(mesh, np.array([mesh.points[k] for k in markers]))
    pose = pose_of_markers(P @ mesh.nodes, (P @ sol.x)[None]).to_mm_deg()[0]
    V0, V1 = cavity_volumes(mesh, mesh.nodes), cavity_volumes(mesh, sol.x)
    Pt = probe(mesh, mesh.points["near_urethra"][None])
    shift = float(np.linalg.norm(Pt @ (sol.x - mesh.nodes)) * 1e3)
    return {
        "case": name,
        "pose_mm_deg": [round(float(v), 4) for v in pose],
        "y_mm": round(float(pose[1]), 4),
        "yaw_deg": round(float(pose[3]), 4),
        "dV_mm3": {k: round((V1[k] - V0[k]) * 1e9, 3) for k in (*ARMS, "urethra")},
        "near_urethra_mm": round(shift, 4),
        "newton_iterations": sol.iterations,
        "residual": sol.residual,
        "solve_s": round(wall, 1),
        "solver": solver,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size-mm", type=float, nargs="+", default=[9.0])
    ap.add_argument("--nu", type=float, default=ECOFLEX_00_50.nu)
    ap.add_argument("--E-kPa", type=float, default=ECOFLEX_00_50.E_Pa / 1e3)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--json", type=Path)
    add_results_option(ap, "reference")
    a = ap.parse_args(argv)
    out = []
    for h in a.mesh_size_mm:
        t0 = time.perf_counter()
        mesh = bip_tet10(BIPDesign(), h)
        print(f"mesh {h:g} mm: {len(mesh.nodes)} nodes, {len(mesh.tets)} tet10 ({time.perf_counter() - t0:.1f} s)",
              flush=True)
        for name in a.cases:
            r = run_case(mesh, name, a.E_kPa * 1e3, a.nu)
            r["mesh_size_mm"] = h
            r["nodes"] = len(mesh.nodes)
            out.append(r)
            d = DESIGN[name]
            if name == "urethra":
                print(f"  {name}: urethra dV {r['dV_mm3']['urethra']:.1f} mm³ (DESIGN.md {d['urethra_dV_mm3']}), "
                      f"near_urethra {r['near_urethra_mm']:.3f} mm (DESIGN.md {d['near_urethra_mm']}); "
                      f"{r['newton_iterations']} it, {r['solve_s']} s", flush=True)
            else:
                dv = ", ".join(f"{r['dV_mm3'][k]:+.2f}" for k in ARMS)
                print(f"  {name}: y {r['y_mm']:.3f} mm / yaw {r['yaw_deg']:.3f}° (DESIGN.md {d['y_mm']} / "
                      f"{d['yaw_deg']}), arm dV {dv} mm³ (DESIGN.md {d['dV_mm3']}); pose {r['pose_mm_deg']}; "
                      f"{r['newton_iterations']} it, {r['solve_s']} s", flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    write_table(a.results_name, *reference_table(out))
    return 0


def reference_table(out: list[dict]) -> tuple[tuple[str, ...], list[tuple[str, ...]]]:
    """DESIGN.md's table against this run's solves, one column per mesh size."""
    sizes = list(dict.fromkeys(r["mesh_size_mm"] for r in out))
    by = {(r["case"], r["mesh_size_mm"]): r for r in out}
    nodes = {r["mesh_size_mm"]: r["nodes"] for r in out}
    header = ("quantity", "DESIGN.md (converged NH P2)",
              *(f"FElupe NH P2, {h:g} mm ({grouped(nodes[h])} nodes)" for h in sizes))

    def dv(v, arms):
        return ", ".join(f"{x:+.1f}" for x in v[: len(arms)]).replace("-", "−")

    rows = []
    for case, arms in (("on-centre", ARMS), ("off-centre", ARMS[:2])):
        d = DESIGN[case]
        rows.append((f"{case} y / yaw", f"{d['y_mm']} mm / {d['yaw_deg']}°",
                     *(f"{by[case, h]['y_mm']:.2f} mm / {by[case, h]['yaw_deg']:.2f}°" if (case, h) in by else ""
                       for h in sizes)))
        rows.append((f"{case} arm ΔV ({', '.join(arms)}) mm³", dv(d["dV_mm3"], arms),
                     *(dv([by[case, h]["dV_mm3"][k] for k in arms], arms) if (case, h) in by else "" for h in sizes)))
    d = DESIGN["urethra"]
    rows.append(("urethra 30 kPa: ΔV / `near_urethra`", f"{d['urethra_dV_mm3']:.0f} mm³ / {d['near_urethra_mm']} mm",
                 *(f"{by['urethra', h]['dV_mm3']['urethra']:.0f} mm³ / {by['urethra', h]['near_urethra_mm']:.2f} mm"
                   if ("urethra", h) in by else "" for h in sizes)))
    return header, rows


if __name__ == "__main__":
    raise SystemExit(main())
