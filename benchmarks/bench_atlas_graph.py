"""The atlas build's task graph: parallel efficiency on 1, 2 and 4 workers, critical path, the ETA's
error, the cost model's prediction, and a build killed at a random point and resumed.

On the default design (``--mesh-size-mm 6``, ``--order 1``: the linear default model, so the runs
take minutes; ``--order 2`` for the quadratic one, whose default atlas adds Hermite f_z) with the
quadratic default atlas's graph (displacement axis, two pieces along f_y split at 3.3 N) on the grid
``--atlas-grid`` per piece, each run in a fresh model directory through ``atlas build`` (the CLI,
as a user runs it):

- **1, 2 and 4 workers** (``--workers``, a LocalCluster each): wall seconds, CPU seconds of the
  tasks, parallel efficiency (CPU over wall times workers) and the critical path (the longest chain
  of task wall times: the build's wall time on a cluster with a worker per task), from the atlas's
  provenance, and the wall time the cost model predicted before the build (``estimate_build``);
- **the graph on larger clusters**: the 1-worker run's task times scheduled on 2, 4, 16 and 64
  workers as the build schedules them (``tasks.schedule_s``): the wall time a cluster of idle
  workers would take, and its efficiency;
- **ETA**: at every progress line after 10 % of the tasks, the time left it printed against the
  time the build then still took; the largest relative error;
- **kill and resume** (2 workers): ``kill -9`` of the whole process group at a seeded random
  moment between 20 % and 80 % of the 2-worker build's wall time, then the same command: tasks
  kept, tasks the killed run had reported done, and whether the resumed atlas equals the
  uninterrupted one (every array, bit for bit).

Also with both cores busy (``--busy``: two spinning processes beside the 2-worker build).

    .venv/bin/python benchmarks/bench_atlas_graph.py [--mesh-size-mm 12] [--atlas-grid 5,3,2,2] [--busy]
    nice -n 10 .venv/bin/python benchmarks/bench_atlas_graph.py --model P2_12MM_DIR --atlas-grid 5,4,3,2 --workers 1 2 4
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import numpy as np  # noqa: E402

from _results import add_results_option, write_table  # noqa: E402

PROGRESS = re.compile(r"(\d+)/(\d+) \(\d+ %\)(?: ETA (\d+):(\d\d):(\d\d))?")


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def run_build(model_dir: Path, grid: str, workers: int, kill_after_s: float | None = None):
    """One ``atlas build`` (2 pieces, displacement axis, Hermite f_z): (wall s, progress lines as
    (t, done, total, eta_s or None), returncode, stdout)."""
    cmd = [sys.executable, "-m", "softphantom", "atlas", "build", "--model", str(model_dir), "--workers",
           str(workers), "--atlas-grid", grid, "--atlas-x-axis", "displacement", "--atlas-f-y-split-N", "3.3"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env={**os.environ, "COLUMNS": "200"}, bufsize=1)
    lines, out = [], []

    def read() -> None:  # each line with the time it arrived
        for chunk in proc.stdout:
            out.append(chunk)
            m = PROGRESS.search(chunk)
            if m:
                eta = None if m.group(3) is None else int(m.group(3)) * 3600 + int(m.group(4)) * 60 + int(m.group(5))
                lines.append((time.perf_counter() - t0, int(m.group(1)), int(m.group(2)), eta))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    while proc.poll() is None:
        if kill_after_s is not None and time.perf_counter() - t0 >= kill_after_s:
            os.killpg(proc.pid, signal.SIGKILL)
            kill_after_s = None
        time.sleep(0.05)
    reader.join(timeout=5)
    return time.perf_counter() - t0, lines, proc.returncode, "".join(out)


def eta_error(lines, wall: float) -> float:
    """The largest |printed time left − true time left| / true time left after 10 % of the tasks."""
    errs = [abs(eta - (wall - t)) / (wall - t) for t, done, total, eta in lines
            if eta is not None and done >= 0.1 * total and done < total and wall - t > 1.0]
    return max(errs) if errs else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh-size-mm", type=float, default=6.0)
    ap.add_argument("--order", type=int, choices=(1, 2), default=1, help="element order of the meshed model")
    ap.add_argument("--model", help="a saved quadratic model directory instead of meshing the default design")
    ap.add_argument("--atlas-grid", default="7,5,4,3", help="points per axis NX,NY,NZ,NP (per piece)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--busy", action="store_true", help="also the 2-worker build with both cores busy")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="LocalCluster sizes to run (the first: "
                    "the task times the larger clusters are scheduled with)")
    ap.add_argument("--no-kill", action="store_true", help="skip the killed-and-resumed build")
    add_results_option(ap, "atlas_graph")
    a = ap.parse_args()

    from softphantom.design import BIPDesign, MeshParams, build_model, load_model, save_model
    from softphantom.estimation.atlas.catalogue import atlases_of as model_atlases
from softphantom.estimation.atlas.store import ARRAYS, load_atlas

    work = Path(tempfile.mkdtemp(prefix="bench_atlas_graph-"))
    if a.model:
        model = load_model(a.model)
    else:
        import dataclasses

        design = BIPDesign(mesh=dataclasses.replace(MeshParams(), element_order=a.order))
        model = build_model(design, a.mesh_size_mm, isolate=False)
    nodes = len(model.nodes)

    def fresh(name: str) -> Path:
        d = work / name
        d.mkdir()
        save_model(model, d)
        return d

    from dataclasses import replace

    from softphantom.estimation.atlas.build import estimate_build, plan_tasks
    from softphantom.estimation.atlas.config import default_atlas_config
    from softphantom.estimation.atlas.tasks import critical_path_s, schedule_s

    g = [int(v) for v in a.atlas_grid.split(",")]
    acfg = replace(default_atlas_config(2), n_force=tuple(g[:3]), n_pressure=g[3], x_control="displacement",
                   f_y_splits_N=(3.3,), hermite_axis=2 if model.element_order == 2 else None)
    rows, figures = [], {}
    for workers in a.workers:
        d = fresh(f"w{workers}")
        load0 = os.getloadavg()[0]
        wall, lines, rc, out = run_build(d, a.atlas_grid, workers)
        load = f"{load0:.1f}–{os.getloadavg()[0]:.1f}"
        if rc != 0:
            raise SystemExit(f"atlas build failed ({rc}):\n{out[-2000:]}")
        b = load_atlas(model_atlases(d)[0]).provenance["build"]
        eff = b["cpu_s"] / (b["wall_s"] * workers)
        err = eta_error(lines, wall)
        figures[workers] = (d, b)
        pred = estimate_build(model.element_order, nodes, acfg, workers)
        rows.append([f"{workers} worker{'s' if workers > 1 else ''}", load, b["tasks"], f"{b['cpu_s']:.0f}",
                     f"{wall:.0f}", f"{pred.wall_s:.0f}", f"{eff:.0%}", f"{b['critical_path_s']:.0f}", f"{err:.0%}"])
        print(f"{workers} workers: {b['tasks']} tasks, {b['cpu_s']:.0f} CPU-s, wall {wall:.0f} s "
              f"(build {b['wall_s']:.0f} s; cost model {pred.wall_s:.0f} s), efficiency {eff:.0%}, critical path "
              f"{b['critical_path_s']:.0f} s, ETA max error after 10 %: {err:.0%}", flush=True)
    # the first run's task times on idle clusters of more workers, scheduled as the build does
    first = figures[a.workers[0]][1]
    times = {n: float(v[1]) for n, v in first["task_s"].items()}
    tasks = plan_tasks(model.element_order, nodes, acfg)
    total = sum(times.values())
    crit = critical_path_s(tasks, times)
    for w in (2, 4, 16, 64):
        sim = schedule_s(tasks, times, w)
        rows.append([f"{w} idle workers, scheduled from the {a.workers[0]}-worker run's task times", "", len(tasks),
                     f"{total:.0f} (wall-s of the tasks)", f"{sim:.0f}", "", f"{total / (sim * w):.0%}", f"{crit:.0f}",
                     ""])
        print(f"{w} idle workers (scheduled): wall {sim:.0f} s, efficiency {total / (sim * w):.0%}, critical path "
              f"{crit:.0f} s", flush=True)
    if a.busy:
        stop = mp.Event()
        spinners = [mp.Process(target=_spin, args=(stop,), daemon=True) for _ in range(2)]
        for p in spinners:
            p.start()
        try:
            d = fresh("busy")
            wall, lines, rc, out = run_build(d, a.atlas_grid, 2)
        finally:
            stop.set()
            for p in spinners:
                p.join()
        b = load_atlas(model_atlases(d)[0]).provenance["build"]
        rows.append(["2 workers, two spinning processes beside", f"{os.getloadavg()[0]:.1f}", b["tasks"],
                     f"{b['cpu_s']:.0f}", f"{wall:.0f}", "",
                     f"{b['cpu_s'] / (b['wall_s'] * 2):.0%}", f"{b['critical_path_s']:.0f}",
                     f"{eta_error(lines, wall):.0%}"])
        print(f"busy: wall {wall:.0f} s, {b['cpu_s']:.0f} CPU-s")

    if a.no_kill or 2 not in figures:
        _write(a, rows, model, nodes)
        shutil.rmtree(work, ignore_errors=True)
        return
    # killed at a random moment and resumed
    ref_dir, ref = figures[2]
    rng = np.random.default_rng(a.seed)
    kill_at = float(rng.uniform(0.2, 0.8)) * ref["wall_s"]
    d = fresh("killed")
    _, lines, _, _ = run_build(d, a.atlas_grid, 2, kill_after_s=kill_at)
    reported = max((done for _, done, _, _ in lines), default=0)
    kept = len(list((d / "atlas" / "partial").glob("*/*.task")))
    wall2, _, rc, out = run_build(d, a.atlas_grid, 2)
    if rc != 0:
        raise SystemExit(f"resumed atlas build failed ({rc}):\n{out[-2000:]}")
    same = all(np.array_equal(getattr(load_atlas(f), k), getattr(load_atlas(g), k))
               for f, g in zip(model_atlases(d), model_atlases(ref_dir)) for k in ARRAYS)
    total = ref["tasks"]
    print(f"killed at {kill_at:.0f} s: {kept} tasks kept, {reported} reported done before the kill; "
          f"resumed in {wall2:.0f} s; the same atlas as uninterrupted: {same}")
    rows.append([f"2 workers, killed at {kill_at:.0f} s and resumed", f"{os.getloadavg()[0]:.1f}", total,
                 f"kept {kept} of {total} ({reported} reported done)", f"{wall2:.0f} (resumed)", "", "", "",
                 "identical" if same else "DIFFERENT"])
    _write(a, rows, model, nodes)
    shutil.rmtree(work, ignore_errors=True)


def _write(a, rows, model, nodes) -> None:
    write_table(a.results_name, ["run", "load average", "tasks", "CPU-s", "wall s", "cost model's wall s",
                                 "parallel efficiency", "critical path s", "ETA max error after 10 %"], rows,
                right=(2, 3, 4, 5, 6, 7),
                caption=f"Default design, element order {model.element_order}, {nodes} nodes; grid {a.atlas_grid} per "
                        f"piece, 2 pieces along f_y (split at 3.3 N), displacement axis (`bench_atlas_graph.py`).")


if __name__ == "__main__":
    main()
