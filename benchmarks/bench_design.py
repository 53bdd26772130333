"""Design → mesh: wall time, sizes, volume errors and quality for coarse / default / fine meshes.

Run: ``.venv/bin/python benchmarks/bench_design.py [--repeat N] [--compliance] [--stages] [--only default]``

``cpu_s`` is the CPU time of a build, this process and its gmsh child together (what it costs on a
quiet core, whatever else the machine runs); ``sha`` a hash of the mesh (nodes, tets, regions,
faces): a change meant to speed meshing up must leave it as it is.

``--stages`` meshes the default in this process and splits gmsh's work by its own log: the CAD
(solids, fillets, booleans: everything before ``generate``), the size fields' set-up (their
distance fields sample the surfaces before the 1-D pass), the 1-D, 2-D and 3-D passes and the
optimization, in CPU seconds.

``--command`` times ``softphantom design --out DIR`` of the default design as a user runs it (a
new process: imports, the shipped mesh, the report, its observability at rest and drawing), idle
and with two busy processes, median of ``--repeat`` runs: ``design_command``.

``--compliance`` adds a sanity figure for the arm stiffness: a *linear* (small-strain) elastic
solve of a 5 N push along +y at p_ext on-centre (spread over the surface within 4 mm), Ecoflex
00-50 E = 140 kPa, ν = 0.45, arm ends clamped; it prints the mean marker displacement. Linear
elasticity over-predicts this large-deformation load (DESIGN.md §5: ~45 mm linear vs ~20 mm
neo-Hookean on a similar geometry), so it is a plausibility check, not a result.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import re
import resource
import statistics
import time

import numpy as np

from _results import IMG_DIR, grouped, write_table
from softphantom.design import BIPDesign, build_model
from softphantom.design.model import model_summary

CASES = (("coarse", 12.0), ("default", None), ("fine", 4.0))


def _linear_push(model, force_N=(0.0, 5.0, 0.0), E=140e3, nu=0.45, patch_m=4e-3):
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    x, t = model.nodes, model.tets
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[np.arange(3), np.arange(3)] += 2 * mu
    D[np.arange(3, 6), np.arange(3, 6)] = mu
    X = x[t]  # (M,4,3)
    A = np.concatenate([np.ones((len(t), 4, 1)), X], axis=2)
    grads = np.linalg.inv(A)[:, 1:, :]  # (M,3,4): d N_a / d x_i
    vol = model.tet_volumes()
    B = np.zeros((len(t), 6, 12))
    for a in range(4):
        gx, gy, gz = grads[:, 0, a], grads[:, 1, a], grads[:, 2, a]
        B[:, 0, 3 * a], B[:, 1, 3 * a + 1], B[:, 2, 3 * a + 2] = gx, gy, gz
        B[:, 3, 3 * a], B[:, 3, 3 * a + 1] = gy, gx
        B[:, 4, 3 * a + 1], B[:, 4, 3 * a + 2] = gz, gy
        B[:, 5, 3 * a], B[:, 5, 3 * a + 2] = gz, gx
    Ke = np.einsum("mji,jk,mkl,m->mil", B, D, B, vol)
    dofs = (3 * t[:, :, None] + np.arange(3)).reshape(len(t), 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    n = 3 * len(x)
    K = sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(n, n))
    f = np.zeros(n)
    tris = model.outer_faces
    c = x[tris].mean(axis=1)
    sel = np.linalg.norm(c - model.p_ext["on-centre"], axis=1) < patch_m
    area = 0.5 * np.linalg.norm(np.cross(x[tris[sel, 1]] - x[tris[sel, 0]], x[tris[sel, 2]] - x[tris[sel, 0]]), axis=1)
    w = np.zeros(len(x))
    np.add.at(w, tris[sel].ravel(), np.repeat(area / 3, 3))
    w /= w.sum()
    for i in range(3):
        f[i::3] = w * force_N[i]
    fixed = np.zeros(n, bool)
    for i in range(3):
        fixed[3 * model.fixed_nodes + i] = True
    free = ~fixed
    u = np.zeros(n)
    u[free] = spla.spsolve(K[free][:, free].tocsc(), f[free])
    u = u.reshape(-1, 3)
    out = []
    for p in model.markers.values():
        k = int(np.argmin(np.linalg.norm(x - p, axis=1)))
        out.append(u[k])
    return np.array(out)


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the gmsh child)."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def mesh_sha(m) -> str:
    """A hash of the mesh: node coordinates, connectivity, regions and the boundary faces."""
    h = hashlib.sha256()
    for a in (m.nodes, m.tets, m.tet_region, m.outer_faces, m.fixed_faces, *[m.cavities[k] for k in sorted(m.cavities)]):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:12]


def stages(design) -> dict:
    """CPU seconds of each part of one mesh of ``design`` in this process (see the module doc)."""
    import gmsh

    from softphantom.design import mesh as M

    got: dict = {}
    generate = gmsh.model.mesh.generate

    def timed_generate(dim: int = 3) -> None:
        gmsh.option.setNumber("General.Verbosity", 5)  # gmsh's own "Done meshing nD (…, CPU x s)"
        got["cad"] = time.process_time() - got["t0"]
        t = time.process_time()
        generate(dim)
        got["generate"] = time.process_time() - t
        for line in gmsh.logger.get():
            if (hit := re.search(r"Done (meshing \dD|optimizing mesh) \(Wall [\d.e-]+s, CPU ([\d.e-]+)s\)", line)):
                got[hit.group(1)] = got.get(hit.group(1), 0.0) + float(hit.group(2))

    gmsh.model.mesh.generate = timed_generate
    try:
        got["t0"] = time.process_time()
        M.mesh_design(design, isolate=False)
        got["total"] = time.process_time() - got.pop("t0")
    finally:
        gmsh.model.mesh.generate = generate
    passes = sum(got.get(k, 0.0) for k in ("meshing 1D", "meshing 2D", "meshing 3D", "optimizing mesh"))
    got["fields set-up (+ the rest of generate)"] = got["generate"] - passes
    return got


BUSY = "while True:\n    pass\n"


def command_times(repeat: int) -> list[tuple[str, float]]:
    """Median wall (s) of ``softphantom design --out TMP`` of the default design, idle and with two
    busy processes (one per core)."""
    import subprocess
    import sys
    import tempfile

    def once() -> float:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "softphantom", "-q", "design", "--out", f"{d}/model"], check=True,
                           stdout=subprocess.DEVNULL)
            return time.perf_counter() - t0

    rows = []
    for label, n_busy in (("idle", 0), ("2 busy processes", 2)):
        busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(n_busy)]
        try:
            rows.append((label, statistics.median(once() for _ in range(repeat))))
        finally:
            for b in busy:
                b.kill()
                b.wait()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--command", action="store_true", help="only time `softphantom design` of the default design")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per case (median reported)")
    ap.add_argument("--compliance", action="store_true", help="also run the linear 5 N push sanity check")
    ap.add_argument("--stages", action="store_true", help="also split the default mesh's CPU time by gmsh's passes")
    ap.add_argument("--only", choices=[c for c, _ in CASES], action="append", help="only these cases (repeat)")
    args = ap.parse_args()
    if args.command:
        rows = command_times(args.repeat)
        for label, t in rows:
            print(f"softphantom design (default), {label}: {t:.1f} s")
        write_table("design_command", ("softphantom design --out DIR (default design)", "wall s"),
                    [(label, f"{t:.1f}") for label, t in rows], right=(1,),
                    caption=f"Median of {args.repeat} runs, each a new process (goal: ≤ 10 s):")
        return
    print(f"# bench_design  python {platform.python_version()}  cpus {os.cpu_count()}  {platform.machine()}  "
          f"load {os.getloadavg()[0]:.1f}")
    print("| mesh | size_mm | nodes | tets | mesh_s (median) | build_s | cpu_s | bulb_err_% | cavity_err_% (worst) "
          "| min_dihedral_deg | sha |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    d = BIPDesign()
    models, doc = {}, []
    for label, size in CASES:
        if args.only and label not in args.only:
            continue
        walls, mesh_s, cpus = [], [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), _cpu()
            m = build_model(d, size)
            walls.append(time.perf_counter() - t0)
            cpus.append(_cpu() - c0)
            mesh_s.append(m.mesh_seconds)
        s = model_summary(m)
        bulb = 100 * (s["bulb_mesh_mm3"] / s["bulb_design_mm3"] - 1)
        cav = min((100 * (s[f"{n}_mesh_mm3"] / s[f"{n}_design_mm3"] - 1) for n in d.cavity_volumes_mm3()), key=lambda v: -abs(v))
        print(
            f"| {label} | {m.design.mesh.size_mm:g} | {len(m.nodes)} | {len(m.tets)} | {statistics.median(mesh_s):.2f} | "
            f"{statistics.median(walls):.2f} | {statistics.median(cpus):.2f} | {bulb:+.2f} | {cav:+.2f} | "
            f"{s['min_dihedral_deg']:.1f} | {mesh_sha(m)} |"
        )
        models[label] = m
        doc.append((label, f"{m.design.mesh.size_mm:g}", grouped(len(m.nodes)), grouped(len(m.tets)),
                    f"{statistics.median(cpus):.2f}"))
    if "default" in models:                              # the docs' picture of the default phantom
        from softphantom.viz.mesh_view import render_mesh_png

        print(f"wrote {render_mesh_png(models['default'], IMG_DIR / 'phantom-mesh.png')}")
    write_table("design_mesh", ("mesh", "size_mm", "nodes", "tets", "CPU s (build)"), doc, right=(2, 3, 4),
                caption=f"Median of {args.repeat} builds, this process and its gmsh child:")
    if args.stages:
        print("\n# default design, one mesh in this process: CPU s by part")
        parts = stages(d)
        for k, v in parts.items():
            print(f"{k}: {v:.2f}")
        write_table("design_stages", ("part of the default mesh", "CPU s"), [(k, f"{v:.2f}") for k, v in parts.items()],
                    right=(1,))
    if args.compliance:
        print("\n# linear 5 N push along +y at p_ext on-centre (E 140 kPa, nu 0.45): marker displacement")
        for label, m in models.items():
            t0 = time.perf_counter()
            u = _linear_push(m) * 1e3
            print(
                f"{label}: mean |u| {np.linalg.norm(u, axis=1).mean():.1f} mm, mean u_y {u[:, 1].mean():.1f} mm "
                f"(solve {time.perf_counter() - t0:.1f} s)"
            )


if __name__ == "__main__":
    main()
