"""Benchmark of the real-time estimator: rate, step latency, accuracy during a ramp.

    .venv/bin/python benchmarks/bench_estimate.py                 # default mesh (~6 k nodes)
    .venv/bin/python benchmarks/bench_estimate.py --mesh-size-mm 12 --ramp-levels 4   # quick

1. Truth: converged ``solve_static`` (Newton, warm-started level to level) at force levels
   0 … ``--force-N`` along ``--direction`` at the on-centre p_ext (the paper's robot push:
   5 N in ~2 s at 77 Hz); the input cavity volumes between levels are interpolated (cubic).
2. Ramp at 77 Hz paced in real time, ``async`` mode (background equilibrium thread): force and
   pose error (max and RMS) at the truth levels, then after holding the last level for
   ``--hold-s``; refresh count and seconds per refresh (median, max).
3. The same ramp in ``sync`` mode as fast as possible (deterministic; refreshes in the step).
4. Sustained rate: ``async`` mode, samples fed back to back (``--samples``), the background
   thread busy refreshing: Hz, p50/p99/max step latency, ratio to the board's 19.2 and 77 Hz.
5. Naive scheme: one tangent assembly + factorization + 4 solves per sample (the paper's
   per-sample linearization), median of 3.
6. Atlas estimator: offline build on ``--workers`` Dask processes (time, size), then
   the same real-time ramp, the same ramp while a load process keeps both cores busy (also the
   async refresh estimator under that load, for comparison), the sustained rate (quiet and with
   2 busy processes), the same ramp and rate of the step as it was before its compiled kernels
   (``AtlasEstimator.step_reference``, the ratio printed), and its error against converged forward
   solves at ``--held-out`` seeded random loads inside the envelope.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import threading
import time
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import add_results_option, grouped, write_table  # noqa: E402

from softphantom.design import BIPDesign, build_model, load_model  # noqa: E402
from softphantom.estimation.config import DEFAULT_CONTACT_RADIUS_M  # noqa: E402
from softphantom.estimation import AtlasEstimator, Estimator, EstimatorConfig  # noqa: E402
from softphantom.estimation.atlas import X_CONTROLS, build_atlas, default_atlas_config, load_or_build  # noqa: E402
from softphantom.estimation.forward import ForwardModel  # noqa: E402
from softphantom.estimation.atlas.store import AXIS_NAMES  # noqa: E402
from softphantom.estimation.select import atlas_config_from_options  # noqa: E402
from softphantom.fem import (  # noqa: E402
    SparseSolver, free_tangent, probe_matrix, solve_static,
)
from softphantom.pose import pose_of_markers  # noqa: E402
from softphantom.sensing import Measurement  # noqa: E402

BOARD_RATES_HZ = (19.2, 77.0)
CORE_N = 0.1  # the held-out check's core loads: |f_x| below this (N), where the arm pair's step is


def meas(t, dV, p=0.0):
    return Measurement(t, 0, t, np.full(5, 51150), 100, np.zeros(4), np.asarray(dV, float), p)


def truth_levels(model, est, forces):
    fem = est.fem
    H = est._eq.H_f  # the estimator's own force actuator (same patch)
    pm = probe_matrix(fem, [model.markers[k] for k in est.marker_names])
    X = fem.nodes
    # the estimators' own arm volumes (the FEM's cavities, 6-node on P2): ``model.cavities`` are the
    # corner facets, whose volume change on a P2 mesh is ≈ 10 % short (docs/performance/estimation.md)
    arm_volumes = est._eq.arm_volumes
    lin = SparseSolver("auto")
    x = None
    out = []
    for F in forces:
        t = time.perf_counter()
        sol = solve_static(fem, H @ F, x0=x, solver=lin)
        if not sol.converged:
            raise SystemExit(f"truth solve failed at {F}: {sol.status}")
        x = sol.x
        dV = arm_volumes(x)
        out.append(dict(F=F, dV=dV, pose=pose_of_markers(pm @ X, pm @ x).to_mm_deg(),
                        seconds=time.perf_counter() - t, iterations=sol.iterations))
    return out


def errors(e, tr):
    d = e.pose.to_mm_deg() - tr["pose"]
    return (float(np.linalg.norm(e.force - tr["F"])), float(np.max(np.abs(d[:3]))), float(np.max(np.abs(d[3:]))))


def run_ramp(est, levels, rate_Hz, per_level, realtime, hold_s):
    """Feed the ramp; returns (errors at levels, errors after hold, step times, refreshes)."""
    F = np.array([lv["F"] for lv in levels])
    V = np.array([lv["dV"] for lv in levels])
    s_lv = np.arange(len(levels)) * per_level
    n = s_lv[-1] + 1
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(s_lv, V, axis=0) if len(levels) > 2 else None
    dt = 1.0 / rate_Hz
    steps, errs = [], []
    t0 = time.perf_counter()
    r0 = getattr(est, "refreshes", 0)
    t_r0 = len(getattr(est, "refresh_times", []))
    k_total = n + int(round(hold_s * rate_Hz))
    for k in range(k_total):
        if realtime:
            wait = t0 + k * dt - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        kk = min(k, n - 1)
        if kk in s_lv:
            dV = V[list(s_lv).index(kk)]
        else:
            dV = spline(kk) if spline is not None else np.interp(kk, s_lv, V)
        e = est.step(meas(k * dt, dV))
        steps.append(e.step_time)
        if k < n and k in s_lv:
            errs.append(errors(e, levels[list(s_lv).index(k)]))
    last = errors(e, levels[-1])
    return (np.array(errs), last, np.array(steps), getattr(est, "refreshes", 0) - r0,
            np.array(getattr(est, "refresh_times", [])[t_r0:]))


def sustained(est, levels, n_samples):
    """Back-to-back samples on a triangle wave through the truth volumes (worker always busy): (Hz, step
    times, samples per CPU second of this thread)."""
    V = np.array([lv["dV"] for lv in levels])
    m = len(V)
    seq = np.concatenate([np.linspace(0, m - 1, 200), np.linspace(m - 1, 0, 200)])
    steps = []
    t0, c0 = time.perf_counter(), time.thread_time()
    for k in range(n_samples):
        s = seq[k % len(seq)]
        i = min(int(s), m - 2)
        dV = V[i] + (s - i) * (V[i + 1] - V[i])
        e = est.step(meas(k / 1000.0, dV))
        steps.append(e.step_time)
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    # and samples per CPU second of this thread: the rate with a core of its own
    return n_samples / wall, np.array(steps), n_samples / cpu


def naive_cost(est, x, reps=3):
    eq = est._eq
    B = np.zeros((est.fem.n_dof, 4))
    B[:, :3] = eq.H_f.toarray()
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        K = free_tangent(est.fem, x)
        s = SparseSolver("auto").factorize(K)
        s.solve(B[est.fem.free_dofs])
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


BUSY = "import os\nwhile True:\n    pass\n"


def start_load(n: int = 2):
    """``n`` busy processes (one per core): the machine as loaded as the issue's measurement."""
    import subprocess

    return [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(n)]


def stop_load(procs) -> None:
    for p in procs:
        p.kill()
        p.wait()


class _BusyThread(threading.Thread):
    """A Python thread in this process busy ``busy_ms`` of every ``period_ms`` (as a Dask client's
    event loop, a progress display or a Foxglove server beside the stream): it contends for the GIL.
    Stopped as a load process is (``kill``, ``wait``)."""

    def __init__(self, busy_ms: float, period_ms: float) -> None:
        super().__init__(daemon=True)
        self.busy_s, self.period_s = busy_ms * 1e-3, period_ms * 1e-3
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            t = time.perf_counter()
            while time.perf_counter() - t < self.busy_s:
                sum(range(100))
            time.sleep(self.period_s)

    def kill(self) -> None:
        self._stop_event.set()

    def wait(self) -> None:
        self.join()


def start_thread_load(busy_ms: float = 2.0, period_ms: float = 10.0):
    """One :class:`_BusyThread`, started."""
    th = _BusyThread(busy_ms, period_ms)
    th.start()
    return [th]


def held_out(est: AtlasEstimator, fwd: ForwardModel, n: int, seed: int = 3, core_N: float = 0.0, loads_in=None):
    """Max (and 90th-percentile) errors of the atlas against converged forward solves at ``n`` seeded
    random loads inside the envelope's solved cells: volumes (mm³), points (mm), field (mm), and the
    inverse (N, mm, deg) started 0.3 N away (a stream's previous estimate is much closer; 77 Hz at
    5 N/2 s: 0.03 N); and the load of the largest force error. ``core_N`` > 0: f_x drawn within
    ±core_N instead (the arm pair's step about f_x = 0, where the map is steepest). ``fwd`` solves
    the truths (the estimator's model and contact; the equilibria only are used). ``loads_in`` (n, 4):
    these loads instead of random ones (those outside the solved cells skipped)."""
    rng = np.random.default_rng(seed)
    given = list(loads_in) if loads_in is not None else None
    at = est.atlas
    lo, hi = at.config.lower, at.config.upper
    rows, loads = [], []
    while (given if given is not None else len(rows) < n):
        lam = given.pop(0) if given is not None else lo + (hi - lo) * rng.uniform(0.02, 0.98, 4)
        if core_N > 0 and given is None:
            lam[0] = rng.uniform(max(lo[0], -core_N), min(hi[0], core_N))
        c = at.coords(lam[:3], lam[3])  # the atlas's coordinates of the load (its first axis may be ū_x)
        if not at.solved_at(c):
            continue  # where the build could not solve: outside the envelope
        lin = fwd.solve(lam)
        V, _ = at.volumes(c)
        start = at.coords(lam[:3] + rng.normal(0, 0.3 / np.sqrt(3), 3), lam[3])
        nm = fwd.n_markers
        tp = pose_of_markers(est.rest_markers, lin.sub_x[:nm]).to_mm_deg()
        row = [np.abs(V - lin.V).max() * 1e9, np.abs(at.points(c) - lin.sub_x).max() * 1e3,
               np.abs(at.nodes(c) - lin.x.reshape(-1, 3)).max() * 1e3]
        for invert in (est.invert, est.invert_reference):  # the kernel step and the pre-kernel one
            lam_e = invert(lin.V, lam[3], start=start)[0]
            d = pose_of_markers(est.rest_markers, at.points(lam_e)[:nm]).to_mm_deg() - tp
            row += [np.linalg.norm(at.forces(lam_e) - lam[:3]), np.abs(d[:3]).max(), np.abs(d[3:]).max()]
        rows.append(row)
        loads.append(lam)
    rows = np.array(rows)
    names = ["dV_mm3", "points_mm", "field_mm", "force_N", "pos_mm", "ang_deg", "reference_force_N",
             "reference_pos_mm", "reference_ang_deg"]
    out = dict(zip(names, map(float, rows.max(axis=0))))
    out.update({k + "_p90": float(v) for k, v in zip(names[:6], np.percentile(rows[:, :6], 90, axis=0))})
    worst = int(np.argmax(rows[:, 3]))
    out["worst_force_load"] = [round(float(v), 3) for v in loads[worst][:3]] + [round(float(loads[worst][3]) * 1e-3, 2)]
    return out


def _steps(r: dict) -> str:
    return f"{r['step_ms_p50']:.2f} / {r['step_ms_p99']:.2f} / {r['step_ms_max']:.1f} ms"


def _errs(r: dict, rms: bool = False) -> str:
    out = f"{r['force_err_N_max']:.3f} N, {r['pos_err_mm_max']:.3f} mm, {r['ang_err_deg_max']:.3f}°"
    return out + (f" (RMS {r['force_err_N_rms']:.3f} N, {r['pos_err_mm_rms']:.3f} mm, {r['ang_err_deg_rms']:.3f}°)"
                  if rms else "")


def _held(h: dict) -> str:
    return (f"{h['force_N']:.3f} N, {h['pos_mm']:.3f} mm, {h['ang_deg']:.3f}° ({h['force_N_p90']:.3f} N, "
            f"{h['pos_mm_p90']:.3f} mm, {h['ang_deg_p90']:.3f}°); volumes {h['dV_mm3']:.3f} mm³")


def atlas_rows(res: dict) -> list[tuple[str, str, str]]:
    """The atlas estimator's docs table from the figures of one run."""
    rt, ref = res["atlas_77Hz_realtime"], res["atlas_reference_77Hz_realtime"]
    rows = [("5 N ramp at 77 Hz, max error (RMS)", _errs(rt, True), _errs(ref)),
            ("the same, 2 busy processes started by the benchmark", _errs(res["atlas_77Hz_realtime_loaded"]), "—")]
    for key, what in (("atlas_held_out_max", "held-out random loads: max (90th percentile)"),
                      ("atlas_held_out_core_max", f"held-out loads with \\|f_x\\| < {CORE_N} N: max (90th percentile)")):
        if key in res:
            rows.append((what, _held(res[key]), "—"))
    new, old = res["sustained_atlas"], res["sustained_atlas_reference"]
    rows += [("real-time step p50 / p99 / max", _steps(rt), _steps(ref)),
             ("the same, 2 busy processes", _steps(res["atlas_77Hz_realtime_loaded"]), "—"),
             ("sustained, back to back", f"{grouped(new['Hz'])} Hz, p99 {new['step_ms_p99']:.3f} ms",
              f"{grouped(old['Hz'])} Hz"),
             ("the same, 2 busy processes", f"{grouped(res['sustained_atlas_loaded']['Hz'])} Hz, "
              f"p99 {res['sustained_atlas_loaded']['step_ms_p99']:.3f} ms", "—"),
             ("the same, a Python thread of the process busy 2 ms in 10 ms (GIL)",
              f"{grouped(res['sustained_atlas_thread']['Hz'])} Hz, p99 {res['sustained_atlas_thread']['step_ms_p99']:.3f} ms",
              "—"),
             ("samples per CPU-second", grouped(new["Hz_per_cpu_s"]),
              f"{grouped(old['Hz_per_cpu_s'])} ({new['Hz_per_cpu_s'] / old['Hz_per_cpu_s']:.1f}× fewer)")]
    if "naive_per_sample_s" in res:
        naive = res["naive_per_sample_s"]
        rows.append(("naive per-sample assembly + factorization + 4 solves",
                     f"{naive:.2f} s: the atlas p50 {grouped(naive / (rt['step_ms_p50'] * 1e-3))}× faster", "—"))
    return rows


def write_atlas_table(name: str | None, res: dict) -> None:
    if name is None:
        return
    write_table(name, ("figure", "compiled step", "numpy step (`step_reference`), same run"), atlas_rows(res),
                caption=f"{res['ramp']}; {grouped(res['nodes'])}-node model, atlas grid "
                        f"{' × '.join(map(str, res['atlas_build']['grid']))}:")


def refresh_rows(res: dict, naive: float) -> list[tuple[str, ...]]:
    """The refresh estimator's docs table."""
    def hold(r):
        h = r["after_hold"]
        return f"{h['force_err_N']:.2g} N, {h['pos_err_mm']:.2g} mm, {h['ang_err_deg']:.2g}°"

    sa, rt, sy = res["sustained_async"], res["async_77Hz_realtime"], res["sync_ramp"]
    return [("async, samples back to back", f"{grouped(sa['Hz'])} Hz", _steps(sa), "—", "—"),
            ("async, real time at 77 Hz", "77 Hz", _steps(rt), _errs(rt), hold(rt)),
            ("async, real time, 2 busy processes", "77 Hz", _steps(res["async_77Hz_realtime_loaded"]),
             _errs(res["async_77Hz_realtime_loaded"]), hold(res["async_77Hz_realtime_loaded"])),
            ("sync, as fast as possible", "not real time", _steps(sy), _errs(sy), hold(sy)),
            ("naive: assemble + factor + 4 solves per sample", f"{1 / naive:.1f} Hz", f"{naive * 1e3:.0f} ms", "—", "—")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", help="model directory (default: build the default design)")
    ap.add_argument("--mesh-size-mm", type=float, default=None)
    ap.add_argument("--force-N", type=float, default=5.0)
    ap.add_argument("--contact-radius-mm", type=float, default=DEFAULT_CONTACT_RADIUS_M * 1e3,
                    help="force spread over the surface nodes within this radius of p_ext (default: the "
                         "estimator's, so the default atlas in a model's cache is reused; 0: one element, "
                         "a 5 N point load on one element does not converge on the default mesh)")
    ap.add_argument("--direction", default="0,1,0", help="force direction x,y,z")
    ap.add_argument("--ramp-s", type=float, default=2.0)
    ap.add_argument("--ramp-levels", type=int, default=10, help="truth levels after rest")
    ap.add_argument("--hold-s", type=float, default=1.0)
    ap.add_argument("--samples", type=int, default=3000, help="samples for the sustained-rate run")
    ap.add_argument("--json", help="write the figures to this JSON file")
    add_results_option(ap, "estimate_atlas")
    ap.add_argument("--workers", type=int, default=2, help="Dask worker processes of the atlas build")
    ap.add_argument("--atlas-cache", help="model directory to keep the atlas in (default: build it in this run)")
    ap.add_argument("--held-out", type=int, default=10, help="random loads for the atlas accuracy check")
    ap.add_argument("--held-out-core", type=int, default=10,
                    help=f"more random loads with |f_x| < {CORE_N} N, the arm pair's step (0: none)")
    ap.add_argument("--skip-refresh", action="store_true", help="only the atlas rows (and the naive ratio)")
    ap.add_argument("--rt-repeats", type=int, default=1,
                    help="real-time ramps (and holds) per atlas row, for the step latency's p99")
    ap.add_argument("--atlas-grid", help="atlas points per axis NX,NY,NZ,NP (default: the model's, "
                    "default_atlas_config of its element order)")
    ap.add_argument("--x-control", choices=X_CONTROLS, default=None,
                    help="the atlas's first axis: f_x or the patch displacement (AtlasConfig.x_control; default: "
                    "the model's, force on a linear model, displacement on a quadratic one)")
    ap.add_argument("--atlas-f-y-split-N", help="the atlas in pieces along f_y, split at these forces (N, "
                    "comma-separated; AtlasConfig.f_y_splits_N)")
    ap.add_argument("--envelope", help="atlas envelope FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX (N, kPa; "
                    "default: AtlasConfig's)")
    ap.add_argument("--atlas-hermite-axis", choices=AXIS_NAMES, default=None,
                    help="interpolate this axis by Hermite from the exact derivatives of every grid point "
                    "(AtlasConfig.hermite_axis; its NX/NY/NZ/NP points then give a polynomial of twice as many terms)")
    a = ap.parse_args()
    # another atlas layout writes the default layout's docs table only when named: a trial run
    # (a grid, an envelope, a Hermite axis) must not replace the figures the docs show
    if (any(v is not None for v in (a.atlas_grid, a.envelope, a.x_control, a.atlas_f_y_split_N, a.atlas_hermite_axis))
            and not any(arg.startswith("--results-name") for arg in sys.argv[1:])):
        print("atlas options given without --results-name: no docs table written")
        a.results_name = None

    t = time.perf_counter()
    model = load_model(a.model) if a.model else build_model(BIPDesign(), a.mesh_size_mm)
    print(f"model: {len(model.nodes)} nodes, {len(model.tets)} tets ({time.perf_counter() - t:.1f} s)")
    t = time.perf_counter()
    base = dict(contact_radius_m=a.contact_radius_mm * 1e-3)
    est = Estimator(model, EstimatorConfig(mode="sync", **base))
    print(f"estimator build (rest factorization): {time.perf_counter() - t:.2f} s")
    d = np.array([float(v) for v in a.direction.split(",")])
    d /= np.linalg.norm(d)
    forces = [a.force_N * d * i / a.ramp_levels for i in range(a.ramp_levels + 1)]
    t = time.perf_counter()
    levels = truth_levels(model, est, forces)
    print(f"truth: {len(levels)} converged solves in {time.perf_counter() - t:.1f} s; "
          f"peak pose {np.round(levels[-1]['pose'], 2).tolist()} (mm, deg)")
    rate = 77.0
    per_level = max(1, int(round(a.ramp_s * rate / a.ramp_levels)))
    res: dict = {"nodes": len(model.nodes), "tets": len(model.tets), "cpus": os.cpu_count(),
                 "contact_radius_mm": a.contact_radius_mm, "ramp": f"{a.force_N} N along {d.round(3).tolist()} in {a.ramp_levels * per_level / rate:.2f} s at 77 Hz"}

    def report(name, errs, last, steps, refreshes, rtimes):
        r = {"force_err_N_max": float(errs[:, 0].max()), "pos_err_mm_max": float(errs[:, 1].max()),
             "ang_err_deg_max": float(errs[:, 2].max()),
             "force_err_N_rms": float(np.sqrt(np.mean(errs[:, 0] ** 2))),
             "pos_err_mm_rms": float(np.sqrt(np.mean(errs[:, 1] ** 2))),
             "ang_err_deg_rms": float(np.sqrt(np.mean(errs[:, 2] ** 2))),
             "refresh_s_median": float(np.median(rtimes)) if len(rtimes) else float("nan"),
             "refresh_s_max": float(np.max(rtimes)) if len(rtimes) else float("nan"),
             "after_hold": {"force_err_N": last[0], "pos_err_mm": last[1], "ang_err_deg": last[2]},
             "step_ms_p50": float(np.percentile(steps, 50) * 1e3), "step_ms_p99": float(np.percentile(steps, 99) * 1e3),
             "step_ms_max": float(steps.max() * 1e3), "refreshes": int(refreshes)}
        print(f"{name}: during ramp max |ΔF| {r['force_err_N_max']:.3f} N, pos {r['pos_err_mm_max']:.3f} mm, "
              f"ang {r['ang_err_deg_max']:.3f} deg (RMS {r['force_err_N_rms']:.3f} N, {r['pos_err_mm_rms']:.3f} mm, "
              f"{r['ang_err_deg_rms']:.3f} deg); after {a.hold_s:g} s hold |ΔF| {last[0]:.2e} N, "
              f"pos {last[1]:.2e} mm, ang {last[2]:.2e} deg; step p50 {r['step_ms_p50']:.2f} ms, "
              f"p99 {r['step_ms_p99']:.2f} ms, max {r['step_ms_max']:.1f} ms; {refreshes} refreshes "
              f"(median {r['refresh_s_median']:.2f} s, max {r['refresh_s_max']:.2f} s)")
        r["load_avg"] = os.getloadavg()[0]
        print(f"  (load average {r['load_avg']:.1f})")
        res[name] = r

    # -- atlas: offline build, then the same ramps (quiet and loaded), sustained rate, held-out loads
    cfg = EstimatorConfig(**base)
    base_acfg = default_atlas_config(model.element_order)
    if a.atlas_hermite_axis is not None:  # first: a Hermite axis may have 2 points
        base_acfg = dataclasses.replace(base_acfg, hermite_axis=AXIS_NAMES.index(a.atlas_hermite_axis))
    acfg = atlas_config_from_options(a.atlas_grid, a.envelope, a.x_control, a.atlas_f_y_split_N, base=base_acfg)
    t = time.perf_counter()
    print(f"load average before the atlas build: {os.getloadavg()[0]:.1f}")
    if a.atlas_cache:
        atlas = load_or_build(model, cfg, acfg, cache_dir=a.atlas_cache, n_workers=a.workers)
    else:
        atlas = build_atlas(model, cfg, acfg, n_workers=a.workers)
    res["atlas_build"] = {"s": atlas.build_s, "cpu_s": atlas.build_cpu_s, "solves": atlas.solves, "unsolved": atlas.unsolved,
                          "grid": list(acfg.shape), "f_y_splits_N": list(acfg.f_y_splits_N), "envelope": [list(acfg.lower), list(acfg.upper)],
                          "load_avg_after": os.getloadavg()[0], "MB": atlas.nbytes / 1e6,
                          "field_modes": atlas.field_modes, "field_pod_rms_um": atlas.field_rms_m * 1e6,
                          "workers": a.workers, "wall_s_incl_load": time.perf_counter() - t}
    print(f"atlas build: {atlas.solves} forward solves ({atlas.unsolved} unreachable) in {atlas.build_s:.0f} s "
          f"({atlas.build_cpu_s:.0f} CPU-s in the solves: {atlas.build_cpu_s / 2:.0f} s on 2 idle cores) on "
          f"{a.workers} workers, {atlas.nbytes / 1e6:.1f} MB ({atlas.field_modes} field modes); grid "
          f"{acfg.shape}{f' in pieces split at f_y {list(acfg.f_y_splits_N)} N' if acfg.f_y_splits_N else ''}, envelope {acfg.lower.round(2).tolist()}..{acfg.upper.round(2).tolist()}; load average "
          f"{os.getloadavg()[0]:.1f}")
    at = AtlasEstimator(model, cfg, atlas)
    # the step as it was before the compiled kernels, on the same atlas: the ratio
    ref = SimpleNamespace(step=at.step_reference)
    for name, est_, loaded in (("atlas_77Hz_realtime", at, False), ("atlas_77Hz_realtime_loaded", at, True),
                               ("atlas_reference_77Hz_realtime", ref, False)):
        procs = start_load() if loaded else []
        try:
            runs = []
            for _ in range(a.rt_repeats):  # more samples for the p99 (one ramp and hold: 231)
                at.reset()
                runs.append(run_ramp(est_, levels, rate, per_level, True, a.hold_s))
        finally:
            stop_load(procs)
        errs, steps = (np.concatenate([r[i] for r in runs]) for i in (0, 2))
        report(name, errs, runs[-1][1], steps, 0, np.array([]))
        print(f"  ({len(steps)} real-time samples: {a.rt_repeats} ramp(s) and holds)")
    for name, est_, n, loaded in (("sustained_atlas", at, max(a.samples, 20000), False),
                                  ("sustained_atlas_loaded", at, max(a.samples, 20000), True),
                                  ("sustained_atlas_thread", at, max(a.samples, 20000), "thread"),
                                  ("sustained_atlas_reference", ref, a.samples, False)):
        procs = start_thread_load() if loaded == "thread" else start_load() if loaded else []
        try:
            at.reset()
            hz, steps, cpu_hz = sustained(est_, levels, n)
        finally:
            stop_load(procs)
        res[name] = r = {"Hz": hz, "Hz_per_cpu_s": cpu_hz, "step_ms_p50": float(np.percentile(steps, 50) * 1e3),
                         "step_ms_p99": float(np.percentile(steps, 99) * 1e3), "step_ms_max": float(steps.max() * 1e3),
                         "load_avg": os.getloadavg()[0]}
        beside = {True: ", 2 busy processes", "thread": ", a Python thread busy 20 % beside it"}.get(loaded, "")
        print(f"{name} (back to back, {len(steps)} samples{beside}): {hz:.0f} Hz "
              f"({cpu_hz:.0f} samples per CPU-s), step p50 {r['step_ms_p50']:.3f} ms, p99 {r['step_ms_p99']:.3f} ms, max {r['step_ms_max']:.2f} ms "
              f"(load average {r['load_avg']:.1f})")
    new, old = res["sustained_atlas"], res["sustained_atlas_reference"]
    res["atlas_step_vs_reference"] = ratio = {
        "Hz": new["Hz"] / old["Hz"], "Hz_per_cpu_s": new["Hz_per_cpu_s"] / old["Hz_per_cpu_s"],
        "p50": old["step_ms_p50"] / new["step_ms_p50"],
        "realtime_p50": res["atlas_reference_77Hz_realtime"]["step_ms_p50"] / res["atlas_77Hz_realtime"]["step_ms_p50"]}
    print(f"atlas step vs the reference (pre-kernel) step, same run: {ratio['Hz']:.1f}x the sustained rate "
          f"({ratio['Hz_per_cpu_s']:.1f}x per CPU-s), "
          f"p50 {ratio['p50']:.1f}x shorter back to back, {ratio['realtime_p50']:.1f}x in real time")
    r = res["sustained_atlas"]
    # the truths need only the equilibria: no exact sensitivities (≈ 7 s a solve on the default)
    truth_fwd = ForwardModel(model, cfg, exact_sensitivities=False)
    for key, n, core, what in (("atlas_held_out_max", a.held_out, 0.0, "held-out loads"),
                               ("atlas_held_out_core_max", a.held_out_core, CORE_N,
                                f"held-out loads with |f_x| < {CORE_N} N (the arm pair's step)")):
        if n <= 0:
            continue
        res[key] = ho = held_out(at, truth_fwd, n, core_N=core)
        print(f"atlas vs converged solves at {n} {what} (max): dV {ho['dV_mm3']:.4f} mm3, points "
              f"{ho['points_mm']:.4f} mm, field {ho['field_mm']:.4f} mm; inverse {ho['force_N']:.4f} N, "
              f"{ho['pos_mm']:.4f} mm, {ho['ang_deg']:.4f} deg (the reference step's inverse {ho['reference_force_N']:.4f} N, "
              f"{ho['reference_pos_mm']:.4f} mm, {ho['reference_ang_deg']:.4f} deg); 90th percentile dV {ho['dV_mm3_p90']:.4f} "
              f"mm3, points {ho['points_mm_p90']:.4f} mm, inverse {ho['force_N_p90']:.4f} N, {ho['pos_mm_p90']:.4f} mm, "
              f"{ho['ang_deg_p90']:.4f} deg; largest force error at {ho['worst_force_load']} (N, N, N, kPa)")
    if a.skip_refresh:
        naive = naive_cost(est, est._eq.solve(est.rest, np.r_[forces[len(forces) // 2], 0.0]).x)
        print(f"naive per sample {naive:.3f} s; atlas p50 is {naive / (r['step_ms_p50'] * 1e-3):.0f}x faster")
        res["naive_per_sample_s"] = naive
        write_atlas_table(a.results_name, res)
        if a.json:
            with open(a.json, "w") as f:
                json.dump(res, f, indent=2)
        return
    with Estimator(model, EstimatorConfig(mode="async", **base)) as ea:
        out = run_ramp(ea, levels, rate, per_level, True, a.hold_s)
        report("async_77Hz_realtime", *out)
    procs = start_load()
    try:
        with Estimator(model, EstimatorConfig(mode="async", **base)) as ea:
            out = run_ramp(ea, levels, rate, per_level, True, a.hold_s)
            report("async_77Hz_realtime_loaded", *out)
    finally:
        stop_load(procs)
    es = Estimator(model, EstimatorConfig(mode="sync", **base))
    out = run_ramp(es, levels, rate, per_level, False, a.hold_s)
    report("sync_ramp", *out)
    with Estimator(model, EstimatorConfig(mode="async", **base)) as ea:
        hz, steps, _ = sustained(ea, levels, a.samples)
        r = {"Hz": hz, "step_ms_p50": float(np.percentile(steps, 50) * 1e3),
             "step_ms_p99": float(np.percentile(steps, 99) * 1e3), "step_ms_max": float(steps.max() * 1e3),
             "refreshes": ea.refreshes, "ratio_to_board": {f"{b:g}Hz": hz / b for b in BOARD_RATES_HZ}}
        print(f"sustained (async, back to back, {a.samples} samples): {hz:.0f} Hz, step p50 {r['step_ms_p50']:.3f} ms, "
              f"p99 {r['step_ms_p99']:.3f} ms, max {r['step_ms_max']:.2f} ms; {ea.refreshes} background refreshes; "
              f"{hz / 19.2:.0f}x the 19.2 Hz mode, {hz / 77:.1f}x the 77 Hz mode")
        res["sustained_async"] = r
    naive = naive_cost(est, est._eq.solve(est.rest, np.r_[forces[len(forces) // 2], 0.0]).x)
    res["naive_per_sample_s"] = naive
    res["speedup_vs_naive"] = naive / (res["sustained_async"]["step_ms_p50"] * 1e-3)
    res["atlas_speedup_vs_naive"] = naive / (res["sustained_atlas"]["step_ms_p50"] * 1e-3)
    write_atlas_table(a.results_name, res)
    if a.results_name is not None:
        write_table("estimate_refresh", ("scheme", "rate", "step p50 / p99 / max", "ramp max error", "after the hold"),
                    refresh_rows(res, naive), caption=f"{res['ramp']}, then a {a.hold_s:g} s hold; "
                                                      f"{grouped(res['nodes'])}-node model:")
    print(f"naive (assemble + factorize + 4 solves per sample): {naive:.3f} s = {1 / naive:.1f} Hz; "
          f"async foreground p50 is {res['speedup_vs_naive']:.0f}x faster, atlas p50 "
          f"{res['atlas_speedup_vs_naive']:.0f}x")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=2)


if __name__ == "__main__":
    main()
