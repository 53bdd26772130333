"""Design studies end to end at the coarse mesh: per-variant figures against closed forms and an
independent solve, the cache and resume, a failed variant, the CLI on a local cluster and on a
separately started dask scheduler + worker, the optimizer.

The tests that need a cluster but not its processes share one in-process cluster (threads: its
worker reuses this process's meshes and linearizations); worker processes are started by the
CLI's ``--workers`` (the resume) and by hand (``dask scheduler`` + ``dask worker``)."""

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.parallel import dask_client
from softphantom.study import TIMING_COLUMNS, evaluate_variants, load_sweep_config, read_parquet
from softphantom.study.config import EvalSettings
from softphantom.study.run import rows_equal

COARSE = 12.0
SWEEP = """
[sweep]
name = "t"
method = "grid"
[fixed]
mesh_size_mm = 12.0
[evaluate]
directions = ["zneg", "yneg"]
[parameters]
"sensing.tube_length_m" = { values = [12.0, 1.0] }
"arms.*.wall_mm" = { values = [2.5, 7.0] }
"""


@pytest.fixture(scope="module")
def sweep_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("sweep") / "sweep.toml"
    p.write_text(SWEEP)
    return p


@pytest.fixture(scope="module")
def client():
    """A Dask cluster in this process (one worker thread)."""
    with dask_client(processes=False, n_workers=1) as c:
        yield c


@pytest.fixture(scope="module")
def inproc(sweep_file, client, tmp_path_factory):
    """The study evaluated in this process."""
    cfg = load_sweep_config(sweep_file)
    out = tmp_path_factory.mktemp("inproc")
    run = evaluate_variants(client, cfg.variants(), out)
    return cfg, run.rows


def test_invalid_variant_recorded_and_others_go_on(inproc):
    _, rows = inproc
    assert [r["status"] for r in rows] == ["ok", "invalid", "ok", "invalid"]
    assert rows[1]["error"].startswith("DesignError: arms.front_zpos.wall_mm = 7 leaves no cavity")
    # the same reason without meshing anything: the design's own check
    from softphantom.study import design_problem

    cfg, _ = inproc
    assert [design_problem(v) for v in cfg.variants()] == ["", rows[1]["error"], "", rows[3]["error"]]


def test_count_volume_is_the_budget_closed_form(inproc):
    _, rows = inproc
    for r, L in ((rows[0], 12.0), (rows[2], 1.0)):
        for arm, vc in (("front_zpos", 514.0), ("back_xneg", 486.0)):
            v_total = vc + math.pi / 4 * 1.2**2 * L * 1e3  # mm³
            # one effective count: 5 kPa ADC range / (1024·√100) levels, Boyle δV = V_T δp / P0
            want = v_total * (5000.0 / 10240.0) / 101_325.0
            assert r[f"count_{arm}_mm3"] == pytest.approx(want, rel=1e-9)


def test_force_resolution_scales_with_the_count_and_matches_the_estimator(inproc, coarse_model):
    from softphantom.estimation import Estimator

    _, rows = inproc
    a, b = rows[0], rows[2]  # same geometry, 12 m vs 1 m tube: same W, counts differ
    arms = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
    ratios = [a[f"count_{k}_mm3"] / b[f"count_{k}_mm3"] for k in arms]
    assert 8.0 < min(ratios) < max(ratios) < 9.5
    for ax in "xyz":  # σ_f = ‖W_f⁺ diag(q)‖ per row: between the smallest and largest count ratio
        assert min(ratios) <= a[f"res_force_{ax}_N"] / b[f"res_force_{ax}_N"] <= max(ratios)
    est = Estimator(coarse_model)  # the same default design at the same coarse mesh
    for r in (a, b):
        q = np.array([r[f"count_{k}_mm3"] for k in arms]) * 1e-9
        nb = est.noise_bound(q)
        assert [r[f"res_force_{ax}_N"] for ax in "xyz"] == pytest.approx(nb.force_N.tolist(), rel=1e-9)
        assert r["res_yaw_deg"] == pytest.approx(math.degrees(nb.pose[3]), rel=1e-6)
    assert a["cond_W"] == pytest.approx(est.last.cond_W, rel=1e-9)
    assert a["W_sv1_mm3_per_N"] >= a["W_sv2_mm3_per_N"] >= a["W_sv3_mm3_per_N"] > 0
    assert a["res_force_worst_N"] == max(a[f"res_force_{ax}_N"] for ax in "xyz")
    from softphantom.estimation.observability import observability, observed_state

    obs = observability(coarse_model, est.forward, loaded=False)  # the design report's figure
    assert a["obs_sv_min_mm3"] == b["obs_sv_min_mm3"] == pytest.approx(obs.rest.sv_force_mm3[-1], rel=1e-9)
    probes = [observed_state(est.forward.solve(lam), obs.ranges).sv_force_mm3[-1]
              for lam in ([0.0, 0.0, -3.0, 0.0], [0.0, -3.0, 0.0, 0.0])]  # the sweep's zneg, yneg at 3 N
    assert a["obs_sv_min_loaded_mm3"] == pytest.approx(min(probes), rel=1e-6)


def test_range_is_where_a_transducer_reaches_its_rated_pressure(inproc, coarse_model):
    """An independent Newton solve (fem.solve_static) at the reported range, along −z with the
    1 m tube: the largest transducer pressure (Boyle over cavity + tube) is the rated 2 kPa, to
    the accuracy of the extrapolation from the 3 N linearization."""
    from softphantom.fem import fem_from_phantom, force_actuator, solve_static
    from softphantom.fem.actuators import cavity_volume
    from softphantom.sensing.pneumatics import boyle_dp

    _, rows = inproc
    r = rows[2]
    assert r["range_extrapolated"] and 3.0 < r["range_zneg_N"] < 50.0
    assert r["range_min_N"] == min(r["range_zneg_N"], r["range_yneg_N"])
    fem = fem_from_phantom(coarse_model)
    H = force_actuator(fem, coarse_model.p_ext["on-centre"], EvalSettings().contact_radius_mm * 1e-3)  # the study's patch
    sol = solve_static(fem, H @ np.array([0.0, 0.0, -r["range_zneg_N"]]))
    assert sol.converged
    arms = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
    v0 = np.array([coarse_model.cavity_volume(a) for a in arms])
    dV = np.array([cavity_volume(sol.x.reshape(-1), coarse_model.cavities[a]) for a in arms]) - v0
    v_total = np.array([514.0, 514.0, 486.0, 486.0]) * 1e-9 + math.pi / 4 * 1.2e-3**2 * 1.0
    p = boyle_dp(dV, v_total, 101_325.0)
    assert np.abs(p).max() == pytest.approx(2000.0, rel=0.1)
    # the 12 m tube needs ~8× the volume change: beyond the cap, or far beyond the 1 m range
    assert rows[0]["range_min_N"] > 5 * r["range_min_N"]


def test_cli_local_cluster_resumes_from_the_cache(sweep_file, inproc, client, tmp_path, capsys):
    out = tmp_path / "out"
    address = client.scheduler.address
    assert main(["sweep", "--config", str(sweep_file), "--out", str(out), "--scheduler", address, "--no-progress"]) == 0
    rows = read_parquet(out / "results.parquet")
    assert rows_equal(inproc[1], rows, TIMING_COLUMNS, rtol=1e-9) == []
    html = (out / "report.html").read_text()
    assert "Pareto front" in html and "data:image/png;base64" in html
    # each invalid variant's reason: in the results, the report and the command's own output
    printed = capsys.readouterr().out.splitlines()
    assert not any(ln.startswith("variants:") for ln in printed)  # --no-progress
    for r in rows:
        if r["status"] != "ok":
            assert "leaves no cavity" in r["error"] and __import__("html").escape(r["error"]) in html
            assert f"  variant {r['variant']} invalid: {r['error']}" in printed
    meta = json.loads(__import__("pyarrow.parquet").parquet.read_schema(out / "results.parquet").metadata[b"softphantom"])
    assert meta["parameters"] == ["sensing.tube_length_m", "arms.*.wall_mm"]
    capsys.readouterr()
    # an interrupted run: one variant's file is missing, only that one is computed again (on a local
    # cluster of worker processes: the invalid variant, refused before any mesh)
    cache = sorted((out / "variants").glob("*.json"))
    assert len(cache) == 4
    (out / "variants" / f"{rows[1]['key']}.json").unlink()
    assert main(["sweep", "--config", str(sweep_file), "--out", str(out), "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert "4 variants on a local cluster of 1 workers" in printed.replace("\n", " ")
    assert "3 from the cache, 1 computed" in printed.replace("\n", " ")
    # output that is not a terminal (this capture) shows the progress as lines, from the Dask client
    assert [ln.rsplit(" ", 1)[0] for ln in printed.splitlines() if ln.startswith("variants:")] == [
        "variants: 0/1 (0 %)", "variants: 1/1 (100 %)"]
    assert rows_equal(rows, read_parquet(out / "results.parquet"), TIMING_COLUMNS) == []


@pytest.mark.slow
def test_cli_on_a_separately_started_scheduler_and_worker(sweep_file, inproc, tmp_path):
    dask = Path(sys.executable).with_name("dask")
    sched_file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([str(dask), "scheduler", "--scheduler-file", str(sched_file), "--port", "0",
                               "--no-dashboard", "--host", "127.0.0.1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        # --no-nanny: the worker process itself, not a nanny starting it (one Python start-up fewer)
        procs.append(subprocess.Popen([str(dask), "worker", "--scheduler-file", str(sched_file), "--no-nanny",
                                       "--nthreads", "1", "--no-dashboard"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        time.sleep(0.5)
        address = json.loads(sched_file.read_text())["address"]
        from distributed import Client

        with Client(address, timeout=30) as c:
            c.wait_for_workers(1, timeout=60)
        out = tmp_path / "out"
        assert main(["sweep", "--config", str(sweep_file), "--out", str(out), "--scheduler", address, "--no-progress"]) == 0
        rows = read_parquet(out / "results.parquet")
        assert rows_equal(inproc[1], rows, TIMING_COLUMNS, rtol=1e-9) == []
        assert {r["host"].split(":")[1] for r in rows if r["status"] == "ok"} != {str(__import__("os").getpid())}
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


def test_cli_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    import socket

    import softphantom.parallel as par

    bad = tmp_path / "bad.toml"
    bad.write_text('[parameters]\n"arms.*.girth_mm" = { min = 1, max = 2 }\n')
    assert main(["sweep", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert 'parameters."arms.*.girth_mm": unknown parameter' in err and err.count("\n") == 0
    monkeypatch.setattr(par, "CONNECT_TIMEOUT_S", 0.2)  # nobody listens: refused at once, retried until then
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    good = tmp_path / "good.toml"
    good.write_text("[sweep]\nmethod = 'grid'\n")
    assert main(["sweep", "--config", str(good), "--out", str(tmp_path / "o"), "--scheduler", f"tcp://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip().replace("\n", " ")
    assert f"tcp://127.0.0.1:{port}: unreachable" in err


def test_optimize_finds_the_shortest_tube_that_keeps_the_range(client, tmp_path):
    """Only the tube length varies: resolution improves and range shrinks as it shortens, so the
    best feasible candidate is the shortest feasible one evaluated."""
    from softphantom.study import run_optimize, sweep_config_from_dict

    cfg = sweep_config_from_dict({
        "sweep": {"name": "opt"}, "fixed": {"mesh_size_mm": COARSE}, "evaluate": {"directions": ["zneg"]},
        "parameters": {"sensing.tube_length_m": {"min": 0.5, "max": 12.0}},
        "optimize": {"maxiter": 1, "popsize": 5, "seed": 2, "min_range_N": 6.0},
    })
    res = run_optimize(cfg, client, tmp_path)
    rows = read_parquet(tmp_path / "optimize.parquet")
    assert len(rows) == res.evaluations == 10  # 5 initial + 5 in the one generation
    feasible = [r for r in rows if r["status"] == "ok" and r["range_min_N"] >= 6.0]
    assert feasible and res.row["range_min_N"] >= 6.0
    assert res.params["sensing.tube_length_m"] == min(r["p.sensing.tube_length_m"] for r in feasible)
    assert res.value == min(r["res_force_worst_N"] for r in feasible)
    assert json.loads((tmp_path / "optimize.json").read_text())["best_params"] == res.params


def test_material_stiffness_scales_w_exactly_at_rest(inproc, monkeypatch):
    """At rest the co-rotational tangent is linear elasticity, K ∝ E at fixed ν: doubling E halves
    every singular value of W and doubles the force resolution; cond(W) is unchanged. A variant
    that differs from it only in the tube reuses its mechanics (no second solve)."""
    import softphantom.estimation as estimation
    from softphantom.study import evaluate_variant

    solvers = []
    real = estimation.EquilibriumSolver
    monkeypatch.setattr(estimation, "EquilibriumSolver", lambda *a, **k: solvers.append(real(*a, **k)) or solvers[-1])
    cfg, rows = inproc
    base = rows[0]
    E = cfg.base["materials"]["ecoflex_00_50"]["E_kPa"]
    stiff = evaluate_variant(cfg.resolve(0, {"materials.*.E_kPa": 2 * E}))
    assert stiff["status"] == "ok" and stiff["solve_s"] > 0
    short = evaluate_variant(cfg.resolve(1, {"materials.*.E_kPa": 2 * E, "sensing.tube_length_m": 1.0}))
    assert len(solvers) == 1 and short["solve_s"] == short["mesh_s"] == 0.0
    for k in ("W_sv1_mm3_per_N", "cond_W", "range_zneg_N", "count_front_zpos_mm3"):
        assert (short[k] == stiff[k]) == (k in ("W_sv1_mm3_per_N", "cond_W")), k  # the tube changes only the sensing
    for k in ("W_sv1_mm3_per_N", "W_sv2_mm3_per_N", "W_sv3_mm3_per_N"):
        assert stiff[k] == pytest.approx(base[k] / 2, rel=1e-6)
    assert stiff["cond_W"] == pytest.approx(base["cond_W"], rel=1e-6)
    assert stiff["res_force_worst_N"] == pytest.approx(2 * base["res_force_worst_N"], rel=1e-6)
    bad = evaluate_variant(cfg.resolve(0, {"materials.ecoflex_00_50.nu": 0.7}))
    assert bad["status"] == "invalid" and "nu" in bad["error"]
