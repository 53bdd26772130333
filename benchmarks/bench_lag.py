"""The tubes' pneumatic lag and its compensation (docs/estimation.md, "The tubes' lag").

    .venv/bin/python benchmarks/bench_lag.py                        # the default model (shipped, its atlas)
    .venv/bin/python benchmarks/bench_lag.py --coarse --results-name lag_coarse   # 12 mm P1, refresh: fast

On the virtual phantom (its tube the distributed line: a ladder of RC segments), the paper's 12 m ×
1.2 mm tubes, OSR 100 (19.2 Hz frames), three runs of each scenario from the same truth and noise
(for each of ``--seeds`` noise seeds; the figures are their means):

* **exact**: the board reads the cavities' pressures without the tube (``tube_lag`` off);
* **chain**: through the tube, ``--lag-compensation off``;
* **compensated**: through the tube, ``--lag-compensation model``.

Scenarios: the needle insertion (on-centre push of 2.5 N: rise 4 s, hold 2 s, fall 3 s), the pushes
on-centre, and a load step (2.5 N in 10 ms after 16 s at rest; compensated again with the step a
quarter, half and three quarters of a frame later). Printed per run: y, yaw and |F| RMSE (the
estimate at its own time, the lag not removed; |F| in % of the peak), the lag measured by
cross-correlation (as ``softphantom evaluate``), and for the step: the noise at rest (std over the
rest before the step, y µm, yaw m°, |F| mN), the 50 % point of the step (y and |F|) after the true
one, the overshoot of y. Then the goals' ratios (compensated / exact RMSE ≤ 1.5; noise compensated /
chain ≤ 1.5; 50 % point ≤ 30 ms), the compensation's cost per sample (alone, and in the runs) and
the estimator's step time with and without it.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from _results import add_results_option, write_table  # noqa: E402

STEP = {"name": "load-step", "description": "2.5 N on-centre in 10 ms after 16 s at rest", "duration_s": 20.0,
        "rest_s": 1.5, "patch_radius_mm": 4.0,
        "push": [{"point": "on-centre", "start_s": 16.0, "rise_s": 0.01, "hold_s": 2.5, "fall_s": 0.01,
                  "force_N": [0.15, 2.5, -0.2]}]}
PHASES_S = (0.013, 0.026, 0.039)
"""The step again this much later (a quarter, half, three quarters of a 19.2 Hz frame): its 50 %
point depends on where the step falls between two frames."""


def step_at(start_s: float) -> dict:
    d = {**STEP, "push": [{**STEP["push"][0], "start_s": start_s}]}
    return d


def compensation_cost(n: int = 20000, repeats: int = 5) -> tuple[float, float]:
    """(p50, p99) µs of ``LagCompensator.apply`` alone on the paper's bench (four arms), at rest with
    noise and through a push (so every level is used), the set-up on the first sample excluded."""
    from softphantom.estimation.lag import LagCompensator
    from softphantom.sensing import Measurement
    from softphantom.sensing.bench import BenchConfig

    comp = LagCompensator.for_bench(BenchConfig())
    dt = 1 / 19.2
    comp.prepare(dt)
    rng = np.random.default_rng(0)
    t = np.arange(n) * dt
    level = 100.0 * np.clip(np.sin(np.pi * t / 4.0), 0, None) ** 2  # pushes of 2 s every 8 s
    dp = (level[:, None] + rng.normal(0, 0.3, (n, 4))) * 1e-3  # kPa
    raw = np.zeros(5, int)
    ms = [Measurement(t[k], k, t[k], raw, 100, dp[k], np.zeros(4), 0.0) for k in range(n)]
    times = []
    for _ in range(repeats):
        comp.reset()
        for m in ms:
            t0 = time.perf_counter()
            comp.apply(m)
            times.append(time.perf_counter() - t0)
    us = np.array(times) * 1e6
    return float(np.percentile(us, 50)), float(np.percentile(us, 99))


def crossing(t: np.ndarray, v: np.ndarray, level: float, after: float) -> float:
    """First time after ``after`` that ``v`` reaches ``level`` (linear between samples)."""
    i0 = int(np.searchsorted(t, after))
    up = v[i0:] >= level if level >= v[i0] else v[i0:] <= level
    if not up.any():
        return float("nan")
    i = i0 + int(np.argmax(up))
    if i == 0:
        return float(t[0])
    return float(t[i - 1] + (level - v[i - 1]) / (v[i] - v[i - 1]) * (t[i] - t[i - 1]))


def run_one(sc, model, truth, board_cfg, estimator_kind, model_dir, mode, out: Path, atlas):
    """Estimate one scenario; returns (estimate path, summary, compensator or None)."""
    from softphantom.estimation import EstimatorConfig, estimate_stream, open_estimator
    from softphantom.estimation.lag import compensated, lag_compensation
    from softphantom.sensing.bench import BenchConfig
    from softphantom.virtual import VirtualConfig, simulate

    cfg = dataclasses.replace(VirtualConfig.seeded(seed=0, osr=100), board=board_cfg)
    run = simulate(sc, model, cfg, truth=truth)
    bench = BenchConfig.from_model(model, tube_length_m=board_cfg.tube_length_m, tube_id_m=board_cfg.tube_id_m)
    comp, meta, _ = lag_compensation(mode, bench)
    ecfg = EstimatorConfig(contact="on-centre", mode="sync")
    path = out / f"{sc.name}-{'exact' if not board_cfg.tube_lag else mode}.csv"
    with open_estimator(estimator_kind, model, ecfg, cache_dir=model_dir, atlas=atlas) as est:
        s = estimate_stream(run.source(), compensated(est, comp), path, live=False, metadata=meta)
    return path, s, comp, run


def figures(truth_path: Path, est_path: Path, step_at: float | None):
    from softphantom.evaluation import evaluate, read_estimate, read_truth

    tru, est = read_truth(truth_path), read_estimate(est_path)
    at0 = evaluate(tru, est, lag_ms=0.0)
    lagged = evaluate(tru, est)
    dof = {s.name: s for s in at0.dof}
    fmag = next(s for s in at0.force if s.name == "|force|")
    out = {"y_mm": dof["y"].rmse, "yaw_deg": dof["yaw"].rmse, "F_pct": 100 * fmag.rmse / fmag.peak_truth,
           "lag_ms": lagged.lag_ms}
    if step_at is not None:
        t = est.t
        v = est.mm_deg()
        f = np.linalg.norm(est.force, axis=1)
        rest = (t > 2.0) & (t < step_at - 0.3)
        out["noise_y_um"] = float(np.std(v[rest, 1]) * 1e3)
        out["noise_yaw_mdeg"] = float(np.std(v[rest, 3]) * 1e3)
        out["noise_F_mN"] = float(np.std(f[rest]) * 1e3)
        tt, vt = tru.t, tru.mm_deg()
        ft = np.linalg.norm(tru.force, axis=1)
        hold = (tt > step_at + 1.0) & (tt < step_at + 2.0)
        for key, tv, ev in (("y", vt[:, 1], v[:, 1]), ("F", ft, f)):
            lo, hi = float(np.median(tv[(tt > 2.0) & (tt < step_at - 0.3)])), float(np.median(tv[hold]))
            half = 0.5 * (lo + hi)
            t_true = crossing(tt, tv, half, step_at - 0.5)
            out[f"step50_{key}_ms"] = (crossing(t, ev, half, step_at - 0.5) - t_true) * 1e3
            if key == "y":
                after = (t > step_at) & (t < step_at + 1.0)
                peak = ev[after].max() if hi > lo else ev[after].min()
                out["over_y_pct"] = 100.0 * (peak - hi) / (hi - lo)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size-mm", type=float, default=None, help="the model's mesh (default: the default model)")
    ap.add_argument("--element-order", type=int, default=None, help="1 or 2 (default: the design's)")
    ap.add_argument("--coarse", action="store_true", help="the 12 mm linear model, refresh estimator, linear truth "
                    "(for fast iteration)")
    ap.add_argument("--estimator", default=None, help="atlas | refresh (default: atlas; refresh with --coarse)")
    ap.add_argument("--truth-order", type=int, default=None, help="the truth's elements (default TruthConfig's; "
                    "1 on a coarse model, whose quadratic truth mesh would be too coarse)")
    ap.add_argument("--model-dir", type=Path, default=None, help="a saved model to use (and cache its atlas in)")
    ap.add_argument("--scenarios", nargs="*", default=["needle-insertion", "push-on-centre", "load-step"])
    ap.add_argument("--tube-length-m", type=float, default=12.0)
    ap.add_argument("--seeds", type=int, default=3, help="noise seeds of the board; the figures are their means")
    add_results_option(ap, "lag")
    a = ap.parse_args()
    if a.coarse:
        a.mesh_size_mm = a.mesh_size_mm or 12.0
        a.element_order = a.element_order or 1
        a.truth_order = a.truth_order or 1
    a.estimator = a.estimator or ("refresh" if a.coarse else "atlas")

    import softphantom.estimation.lag  # noqa: F401  (the code measured is the code at the start)
    from softphantom.design import BIPDesign, MeshParams, build_model, load_model, save_model
    from softphantom.design.model import default_design
    from softphantom.virtual import BoardConfig, TruthConfig, load_scenario, scenario_from_dict, solve_truth
    from softphantom.virtual.run import write_run

    t_start = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="bench_lag_"))
    if a.model_dir is not None and (a.model_dir / "model.npz").is_file():
        model, model_dir = load_model(a.model_dir), a.model_dir
    else:
        d = BIPDesign() if a.coarse or a.element_order == 1 else default_design()
        if a.element_order is not None:
            d = dataclasses.replace(d, mesh=dataclasses.replace(d.mesh, element_order=a.element_order))
        model = build_model(d, a.mesh_size_mm)
        model_dir = a.model_dir or work / "model"
        save_model(model, model_dir)
    print(f"model {len(model.nodes)} nodes ({model.design.mesh.size_mm:g} mm, P{model.element_order}), estimator "
          f"{a.estimator}, tube {a.tube_length_m:g} m × 1.2 mm, OSR 100", flush=True)
    atlas = None
    if a.estimator == "atlas":
        from softphantom.estimation.atlas.config import model_atlas_config

        atlas = model_atlas_config(model.element_order, model_dir)
    tcfg = TruthConfig() if a.truth_order is None else TruthConfig(order=a.truth_order)
    chain_cfg = BoardConfig(osr=100, seed=0, tube_length_m=a.tube_length_m)
    exact_cfg = dataclasses.replace(chain_cfg, tube_lag=False)
    rows, goals, costs, steps = [], [], [], {}
    c50, c99 = compensation_cost()
    print(f"compensation alone (four arms): p50 {c50:.1f} µs, p99 {c99:.1f} µs per sample", flush=True)
    for name in a.scenarios:
        sc = scenario_from_dict(STEP, "load-step") if name == "load-step" else load_scenario(name)
        t0 = time.perf_counter()
        truth = solve_truth(sc, model, tcfg, cache=True)  # keyed by the model: kept across runs
        print(f"{name}: truth {time.perf_counter() - t0:.0f} s", flush=True)
        t_step = STEP["push"][0]["start_s"] if name == "load-step" else None
        res, per_seed = {}, {}
        for seed in range(a.seeds):
            for label, bcfg, mode in (("exact", exact_cfg, "off"), ("chain", chain_cfg, "off"),
                                      ("compensated", chain_cfg, "model")):
                t1 = time.perf_counter()
                bcfg = dataclasses.replace(bcfg, seed=seed)
                path, s, comp, run = run_one(sc, model, truth, bcfg, a.estimator, model_dir, mode, work, atlas)
                files = write_run(run, work / f"{name}-{label}")
                f = figures(files["truth"], path, t_step)
                per_seed.setdefault(label, []).append(f)
                if comp is not None:
                    costs.append(comp.cost_s / max(comp.samples, 1))
                steps.setdefault(label, []).append((s["step_ms_p50"], s["step_ms_p99"]))
                print(f"  seed {seed} {label:12s} y {f['y_mm']:.3f} mm  yaw {f['yaw_deg']:.3f}°  |F| {f['F_pct']:.2f} %"
                      f"  lag {f['lag_ms']:+.0f} ms" + ("" if t_step is None else
                      f"  rest noise y {f['noise_y_um']:.2f} µm yaw {f['noise_yaw_mdeg']:.2f} m° |F| "
                      f"{f['noise_F_mN']:.2f} mN  50 % point y {f['step50_y_ms']:+.0f} ms |F| {f['step50_F_ms']:+.0f} ms")
                      + f"  ({s['estimates']} estimates, {time.perf_counter() - t1:.0f} s)", flush=True)
        for label, fs in per_seed.items():  # the mean over the seeds
            res[label] = f = {k: float(np.mean([x[k] for x in fs])) for k in fs[0]}
            rows.append([name, label, f"{f['y_mm']:.3f}", f"{f['yaw_deg']:.3f}", f"{f['F_pct']:.2f}",
                         f"{f['lag_ms']:+.0f}",
                         "" if t_step is None else f"{f['noise_y_um']:.2f} / {f['noise_yaw_mdeg']:.2f} / "
                                                    f"{f['noise_F_mN']:.2f}",
                         "" if t_step is None else f"{f['step50_y_ms']:+.0f} / {f['step50_F_ms']:+.0f}",
                         "" if t_step is None else f"{f['over_y_pct']:.0f}"])
        ex, ch, co = res["exact"], res["chain"], res["compensated"]
        ratio = {k: co[k] / ex[k] for k in ("y_mm", "yaw_deg", "F_pct")}
        span = {k: (min(c[k] / e[k] for c, e in zip(per_seed["compensated"], per_seed["exact"])),
                    max(c[k] / e[k] for c, e in zip(per_seed["compensated"], per_seed["exact"]))) for k in ratio}
        line = (f"  goal (mean of {a.seeds} seeds; each seed's range): compensated / exact RMSE y {ratio['y_mm']:.2f} "
                f"({span['y_mm'][0]:.2f}–{span['y_mm'][1]:.2f}), yaw {ratio['yaw_deg']:.2f} ({span['yaw_deg'][0]:.2f}–"
                f"{span['yaw_deg'][1]:.2f}), |F| {ratio['F_pct']:.2f} ({span['F_pct'][0]:.2f}–{span['F_pct'][1]:.2f}) (≤ 1.5)")
        goals.append([name, "RMSE compensated / exact (y, yaw, |F|; ≤ 1.5)",
                      f"{ratio['y_mm']:.2f}, {ratio['yaw_deg']:.2f}, {ratio['F_pct']:.2f} (seeds {span['y_mm'][0]:.2f}–"
                      f"{span['y_mm'][1]:.2f}, {span['yaw_deg'][0]:.2f}–{span['yaw_deg'][1]:.2f}, "
                      f"{span['F_pct'][0]:.2f}–{span['F_pct'][1]:.2f})"])
        if t_step is not None:
            t50 = [(per_seed["compensated"][0]["step50_y_ms"], per_seed["compensated"][0]["step50_F_ms"])]
            for dt_phase in PHASES_S:  # the same step later within a frame: compensated only
                sp = scenario_from_dict(step_at(t_step + dt_phase), "load-step")
                truth_p = solve_truth(sp, model, tcfg, cache=True)
                path, s, comp, run = run_one(sp, model, truth_p, chain_cfg, a.estimator, model_dir, "model", work, atlas)
                # (seed 0, as the first row of the step's 50 % points)
                files = write_run(run, work / f"{name}-phase")
                fp = figures(files["truth"], path, t_step + dt_phase)
                t50.append((fp["step50_y_ms"], fp["step50_F_ms"]))
                rows.append([name, f"compensated, step {dt_phase * 1e3:+.0f} ms", f"{fp['y_mm']:.3f}",
                             f"{fp['yaw_deg']:.3f}", f"{fp['F_pct']:.2f}", f"{fp['lag_ms']:+.0f}", "",
                             f"{fp['step50_y_ms']:+.0f} / {fp['step50_F_ms']:+.0f}", f"{fp['over_y_pct']:.0f}"])
            t50 = np.array(t50)
            nr = {k: co[k] / ch[k] for k in ("noise_y_um", "noise_yaw_mdeg", "noise_F_mN")}
            line += (f"; noise at rest compensated / chain y {nr['noise_y_um']:.2f}, yaw {nr['noise_yaw_mdeg']:.2f}, "
                     f"|F| {nr['noise_F_mN']:.2f} (≤ 1.5); 50 % point y {co['step50_y_ms']:+.0f} ms, "
                     f"|F| {co['step50_F_ms']:+.0f} ms (≤ 30); over {len(t50)} phases of the frame mean "
                     f"{t50.mean():+.0f} ms, max {t50.max():+.0f} ms")
            goals.append([name, "noise at rest compensated / chain (y, yaw, |F|; ≤ 1.5)",
                          f"{nr['noise_y_um']:.2f}, {nr['noise_yaw_mdeg']:.2f}, {nr['noise_F_mN']:.2f}"])
            goals.append([name, "50 % point of the step after the true one (y, |F|; ≤ 30 ms)",
                          f"{co['step50_y_ms']:+.0f} ms, {co['step50_F_ms']:+.0f} ms; over {len(t50)} phases of the "
                          f"frame mean {t50.mean():+.0f} ms, max {t50.max():+.0f} ms"])
        print(line, flush=True)
    cost_us = 1e6 * float(np.median(costs)) if costs else float("nan")
    p50 = {k: float(np.median([v[0] for v in vs])) for k, vs in steps.items()}
    p99 = {k: float(np.median([v[1] for v in vs])) for k, vs in steps.items()}
    step_line = (f"estimator step p50 / p99: {p50.get('chain', np.nan):.3f} / {p99.get('chain', np.nan):.3f} ms "
                 f"uncompensated, {p50.get('compensated', np.nan):.3f} / {p99.get('compensated', np.nan):.3f} ms "
                 f"compensated")
    print(f"compensation: {cost_us:.1f} µs per sample in the runs (all arms, median over runs), {c50:.1f} µs "
          f"(p99 {c99:.1f} µs) alone; {step_line}; total {time.perf_counter() - t_start:.0f} s")
    write_table(a.results_name, ["scenario", "run", "y RMSE mm", "yaw RMSE °", "‖F‖ RMSE %", "lag ms",
                                 "rest noise y µm / yaw m° / ‖F‖ mN", "50 % point y / ‖F‖ ms",
                                 "step overshoot y %"], rows,
                caption=f"{len(model.nodes)} nodes ({model.design.mesh.size_mm:g} mm, P{model.element_order}), "
                        f"estimator {a.estimator}, tube {a.tube_length_m:g} m × 1.2 mm, OSR 100 (19.2 Hz); the runs' figures "
                        f"are means over {a.seeds} noise seeds (the step at other phases: seed 0); "
                        f"compensation {c50:.1f} µs per sample alone (p99 {c99:.1f} µs), {cost_us:.1f} µs in the runs "
                        f"({step_line}). Goals: "
                        + "; ".join(f"{g[0]} {g[1]}: {g[2]}" for g in goals))


if __name__ == "__main__":
    main()
