"""Issue 56, second half: bad input refused in one line (empty files, every sweep variant invalid,
an empty NatNet address), a sweep that stops at once on Ctrl-C and leaves no empty folder, new
organs' first hour (markers, surface points, arms into the body, balloon segments, mesh.png's
legend), the virtual truth's progress and cache, and cosmetic output."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from softphantom.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parent))
from subproc import sigint_default  # noqa: E402


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: ") and "Traceback" not in err, err
    return err


# --- empty files ---------------------------------------------------------------------------------

@pytest.mark.parametrize("text", ["", "# nothing here\n\n"])
def test_design_refuses_an_empty_config(text, tmp_path, capsys):
    cfg = tmp_path / "empty.toml"
    cfg.write_text(text)
    assert main(["design", "--config", str(cfg), "--out", str(tmp_path / "o"), "--no-png"]) == 2
    assert "empty.toml: empty design file" in _one_line(capsys)
    assert not (tmp_path / "o").exists()


def test_sweep_refuses_an_empty_config(tmp_path, capsys):
    cfg = tmp_path / "empty.toml"
    cfg.write_text("\n")
    assert main(["sweep", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    assert "empty.toml: empty sweep file" in _one_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.toml"]


def test_track_refuses_an_empty_natnet_address_at_once(tmp_path, capsys):
    assert main(["track", "--natnet", "", "--out", str(tmp_path / "t.csv")]) == 2
    assert "--natnet: empty address" in _one_line(capsys)  # not a connect timeout naming ":1510"


# --- sweeps ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def client():
    from softphantom.parallel import dask_client

    with dask_client(processes=False, n_workers=1) as c:
        yield c


def _sweep(client, tmp_path, extra: str, walls_mm: tuple[float, float]) -> tuple[int, Path]:
    """Run a grid sweep over both walls of every arm on ``client``: its exit code and --out."""
    cfg = tmp_path / "s.toml"
    cfg.write_text(f'[sweep]\nmethod = "grid"\n[fixed]\nmesh_size_mm = 12.0\n{extra}'
                   f'[parameters]\n"arms.*.wall_mm" = {{ values = {list(walls_mm)} }}\n')
    out = tmp_path / "o"
    return main(["sweep", "--config", str(cfg), "--out", str(out), "--scheduler", client.scheduler.address,
                 "--no-progress"]), out


def test_sweep_where_every_variant_is_invalid_exits_2_and_writes_nothing(client, tmp_path, capsys):
    code, out = _sweep(client, tmp_path, "", (7.0, 8.0))
    assert code == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert err.count("\n") == 0 and "all 2 variants are invalid" in err, err
    assert "variant 0 invalid: DesignError: arms.front_zpos.wall_mm = 7 leaves no cavity" in cap.out
    assert not out.exists()


def test_sweep_with_one_valid_variant_still_exits_0(client, tmp_path, capsys):
    code, out = _sweep(client, tmp_path, '[evaluate]\ndirections = ["zneg"]\n', (2.5, 7.0))
    assert code == 0
    assert "1 ok, 1 invalid or failed" in capsys.readouterr().out.replace("\n", " ")
    assert (out / "results.parquet").is_file()


@pytest.mark.slow  # a local cluster of one worker process (~5 CPU-s)
def test_sweep_stops_at_once_on_ctrl_c_and_leaves_no_empty_folder(tmp_path):
    (tmp_path / "s.toml").write_text('[sweep]\nmethod = "grid"\n[fixed]\nmesh_size_mm = 12.0\n'
                                     '[parameters]\n"arms.*.wall_mm" = { values = [2.5, 2.6, 2.7] }\n')
    proc = subprocess.Popen([sys.executable, "-m", "softphantom", "sweep", "--config", "s.toml", "--out", "o",
                             "--workers", "1"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=sigint_default)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        while not any(ln.startswith("variants: 0/3") for ln in lines) and proc.poll() is None \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # the worker is in its first variant
        assert proc.poll() is None, "".join(lines)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    # the nanny's graceful close waited 4 s for the busy worker and then killed it, saying so
    assert "still alive" not in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


# --- new organs: markers, surface points, arms, balloons ----------------------------------------

KIDNEY = Path(__file__).resolve().parents[1] / "examples" / "organs" / "kidney.toml"


def _kidney() -> dict:
    import tomllib

    return tomllib.loads(KIDNEY.read_text())


def _refused(data: dict) -> str:
    from softphantom.design import design_from_dict
    from softphantom.errors import DesignError

    with pytest.raises(DesignError) as err:
        design_from_dict(data)
    msg = str(err.value)
    assert "\n" not in msg
    return msg


def test_a_body_without_markers_is_asked_for_its_own_not_blamed_for_the_prostates():
    data = _kidney()
    del data["markers"]
    msg = _refused(data)
    assert msg.startswith("markers: none given") and "give [markers]: at least 4 points on your body" in msg, msg
    assert "markers.m1" not in msg
    data = _kidney()
    del data["targets"]
    assert _refused(data) == ("targets: none given, and the default (the prostate's) seed_mid is inside the "
                              "collecting_system cavity: give [targets], named points inside your body, outside its "
                              "cavities (NAME = [x, y, z] mm)")
    data["targets"] = {"t": [10.0, 0.0, 0.0]}  # the collecting system's centre
    assert _refused(data).startswith("targets.t is inside the collecting_system cavity (")


def test_snap_to_surface_puts_markers_contacts_and_inlets_on_the_body(caplog):
    import logging

    import numpy as np

    from softphantom.design import design_from_dict, design_to_dict
    from softphantom.design.params import SURFACE_TOL_MM

    data = _kidney()
    off = {k: [1.05 * x for x in v] for k, v in data["markers"].items()}  # 1–1.5 mm outside the body
    data["markers"] = off
    data["contacts"]["access"] = [-12.0, -19.0, 10.0]
    data["cavities"]["collecting_system"]["inlet_mm"] = [28.0, 0.0, 0.0]  # 2 mm inside
    msg = _refused(data)  # without the option
    assert "mm off the bulb surface" in msg and "snap_to_surface = true moves it onto the surface" in msg, msg
    data["snap_to_surface"] = True
    with caplog.at_level(logging.INFO, logger="softphantom"):
        d = design_from_dict(data)
    pts = np.array([p for _, p in d.markers] + [p for _, p in d.contacts] + [d.cavities[0].inlet_mm])
    assert np.abs(d.bulb.signed_distance(pts)).max() < 1e-3 * SURFACE_TOL_MM
    # the closest surface point: the move is along the surface normal there (for the 2 mm inlet too)
    for (name, p), q in zip(d.markers, off.values()):
        move = np.asarray(q) - np.asarray(p)
        assert abs(np.dot(move / np.linalg.norm(move), d.bulb.normal(p))) > 0.99, name
    assert "snap_to_surface: cavities.collecting_system.inlet_mm moved 2 mm" in caplog.text
    # the saved design holds the moved points (and no option): it loads as it is
    saved = design_to_dict(d)
    assert "snap_to_surface" not in saved and design_from_dict(saved) == d
    data["snap_to_surface"] = "yes"
    assert _refused(data) == "snap_to_surface: expected true or false, got 'yes'"


def test_closest_point_on_an_ellipsoid_closed_forms():
    import numpy as np

    from softphantom.design import BulbParams

    b = BulbParams(semi_axes_mm=(30.0, 20.0, 25.0))
    q = b.closest_surface_point([[0.0, -21.5, 0.0], [40.0, 0.0, 0.0], [0.0, 0.0, -23.0], [3.0, -4.0, 5.0]])
    assert q[:3].round(9).tolist() == [[0.0, -20.0, 0.0], [30.0, 0.0, 0.0], [0.0, 0.0, -25.0]]
    assert np.all(np.sign(q[3]) == [1, -1, 1]) and abs(b.signed_distance([q[3]])[0]) < 1e-9


@pytest.mark.parametrize("point, direction, expect", [
    ([0, 0, 60], [0, -0.3, -1], r"arms.upper_pole.axis_point_mm = \[0, 0, 60\] is outside the body"),
    ([0, 0, 40], [0, 0, -1], r"arms.upper_pole.axis_point_mm = \[0, 0, 40\] is 8.\d+ mm under the surface behind "
                             r"it, and direction = \[0, 0, -1\] takes the arm 88.\d+ mm across the body"),
])
def test_an_arm_pointing_into_the_body_is_refused_naming_its_axis(point, direction, expect):
    import re

    data = _kidney()
    data["arms"]["upper_pole"].update(axis_point_mm=point, direction=direction)
    msg = _refused(data)
    assert re.search(expect, msg), msg
    assert "embed_mm" not in msg


def test_a_cavity_volume_off_names_cavity_segments(monkeypatch):
    import types

    import softphantom.design.model as m
    from softphantom.design import design_from_dict
    from softphantom.errors import MeshError

    design = design_from_dict(_kidney())
    summary = {"upper_pole_design_mm3": 500.0, "upper_pole_mesh_mm3": 490.0, "bulb_design_mm3": 1.0,
               "bulb_mesh_mm3": 1.0, "lower_pole_design_mm3": 500.0, "lower_pole_mesh_mm3": 500.0,
               "lateral_design_mm3": 500.0, "lateral_mesh_mm3": 500.0, "medial_design_mm3": 500.0,
               "medial_mesh_mm3": 500.0, "collecting_system_design_mm3": 2880.0,
               "collecting_system_mesh_mm3": 2880.0 * (1 - 0.104)}
    monkeypatch.setattr(m, "model_summary", lambda model, quality=False: summary)
    with pytest.raises(MeshError) as err:
        m.check_meshed_volumes(types.SimpleNamespace(design=design))
    msg = str(err.value)
    # 12 segments, −10.4 %: (2π/n)² scaling to a quarter of the 10 % tolerance asks for 25
    assert "collecting_system volume" in msg and "-10.4 % off" in msg, msg
    assert "mesh.cavity_segments = 12 elements around each cavity wall: raise it, e.g. to 25, or --force" in msg, msg


# --- cosmetic -------------------------------------------------------------------------------------

def test_demo_help_cites_the_kidney_where_it_is(capsys):
    assert main(["demo", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "examples/organs/kidney.toml" in text and "examples/kidney.toml" not in text
    assert (Path(__file__).resolve().parents[1] / "examples" / "organs" / "kidney.toml").is_file()


def _summary_row(name: str) -> dict:
    axes = ("x", "y", "z", "yaw", "pitch", "roll")
    return {"scenario": name, "rmse": dict.fromkeys(axes, 0.02), "peak_truth": dict.fromkeys(axes, 12.4),
            "force_rmse_N": {"|force|": 0.03}, "lag_ms": 99.0, "tracker_clock_offset_ms": {"injected": 1.0, "recovered": 1.0},
            "truth": {"events": []}, "table_i": [], "estimator": "atlas",
            "estimate": {"rate_Hz": 350.0, "rate_cpu_Hz": 4100.0, "step_ms_p50": 0.1, "step_ms_p99": 0.3}}


@pytest.mark.parametrize("width", [80, 200])
def test_demo_summary_keeps_scenario_names_and_figures_whole_at_any_width(width):
    import io

    from rich.console import Console

    from softphantom.cli.demo import print_summary

    names = ["push-on-centre", "inflate-collecting_system", "push-access"]
    buf = io.StringIO()
    print_summary([_summary_row(n) for n in names], Console(file=buf, width=width, markup=False))
    text = buf.getvalue()
    assert "…" not in text, text
    for n in names:
        assert n in text
    assert text.count("0.02 (12.4)") == 6 * len(names)
    # a rate in wall time far below its CPU time's: the cores were shared, not the estimator slow
    assert text.count("atlas estimator 350 Hz (4100 Hz in its own CPU time: it waited for the cores)") == len(names)


# --- the virtual truth: progress with the time left, and a cache -----------------------------------

TWO_PUSHES = {"name": "two", "duration_s": 8.0, "push": [
    {"start_s": 1.0, "rise_s": 1.0, "hold_s": 0.5, "force_N": [0.3, 2.0, -0.2]},
    {"start_s": 4.0, "rise_s": 1.0, "hold_s": 0.5, "force_N": [-0.4, 1.5, 0.3]}]}


def _scenario(**over):
    import copy

    from softphantom.virtual import scenario_from_dict

    d = copy.deepcopy(TWO_PUSHES)
    for k, v in over.items():
        if k == "force":
            d["push"][0]["force_N"] = v
        elif k == "start":
            d["push"][1]["start_s"] = v
        else:
            d[k] = v
    return scenario_from_dict(d, "two.toml")


def test_truth_progress_says_the_total_at_once_and_the_time_left(coarse_model, coarse_truth_p1, caplog):
    import logging

    from softphantom.progress import is_progress
    from softphantom.virtual import TruthConfig, solve_truth

    with caplog.at_level(logging.INFO, logger="softphantom"):
        solve_truth(_scenario(), coarse_model, TruthConfig(order=1, levels=2), truth_mesh=coarse_truth_p1)
    steps = [r.progress for r in caplog.records if is_progress(r)]
    assert (steps[0].done, steps[0].total) == (0, 4) and "solving keyframe 1" in steps[0].what  # before any solve
    assert [s.done for s in steps] == [0, 1, 2, 3, 4]
    assert all("; ETA 0:" in s.what for s in steps[1:-1]) and "ETA" not in steps[-1].what


def test_a_solved_truth_is_kept_by_key_and_read_back_at_once(coarse_model, coarse_truth_p1, tmp_path,
                                                             monkeypatch):
    import numpy as np

    import softphantom.virtual.truth as vt
    from softphantom.virtual import TruthConfig, solve_truth

    monkeypatch.setenv("SOFTPHANTOM_CACHE_DIR", str(tmp_path))
    cfg = TruthConfig(order=1, levels=2)
    sc = _scenario()
    first = solve_truth(sc, coarse_model, cfg, truth_mesh=coarse_truth_p1, cache=True)
    assert not first.cached and len(list((tmp_path / "truth").iterdir())) == 1

    def no_solve(*a, **k):
        raise AssertionError("solved again")

    monkeypatch.setattr(vt, "_solve_truth", no_solve)
    # another name and other times, the same loads and overlaps: the same keyframes
    again = solve_truth(_scenario(name="renamed", duration_s=9.0, start=4.5), coarse_model, cfg,
                        truth_mesh=coarse_truth_p1, cache=True)
    assert again.cached and again.solve_s == first.solve_s and again.scenario.name == "renamed"
    t = np.linspace(0.0, 8.0, 97)
    a, b = first.sample(t), again.sample(t + 0.5 * (t > 3.75))  # the second push starts 0.5 s later
    for k in ("force", "dV", "markers", "targets"):
        assert np.allclose(getattr(a, k), getattr(b, k), rtol=1e-9, atol=1e-15), k
    assert np.array_equal(first.events[1].x_peak, again.events[1].x_peak)
    assert again.summary()["cached"] is True and "cached" not in first.summary()
    assert [{**e, "start_s": 0} for e in again.summary()["events"]] == [{**e, "start_s": 0} for e in first.summary()["events"]]
    vt.write_snapshot(again, tmp_path / "snap.vtu")
    # what changes the truth changes the key: a load, a setting, the model
    key = vt.truth_key(vt._checked(sc, coarse_model), coarse_model, cfg, coarse_truth_p1)
    for other in (vt.truth_key(vt._checked(_scenario(force=[0.3, 2.1, -0.2]), coarse_model), coarse_model, cfg,
                               coarse_truth_p1),
                  vt.truth_key(vt._checked(sc, coarse_model), coarse_model, TruthConfig(order=1, levels=3),
                               coarse_truth_p1),
                  vt.truth_key(vt._checked(sc, coarse_model), coarse_model, cfg, None)):
        assert other != key
    with pytest.raises(AssertionError, match="solved again"):
        solve_truth(_scenario(force=[0.3, 2.1, -0.2]), coarse_model, cfg, truth_mesh=coarse_truth_p1, cache=True)
    # an entry that cannot be read is solved again (here: refused by the stub), not trusted
    entry = next((tmp_path / "truth").iterdir())
    (entry / "truth.npz").write_bytes(b"cut")
    with pytest.raises(AssertionError, match="solved again"):
        solve_truth(sc, coarse_model, cfg, truth_mesh=coarse_truth_p1, cache=True)


def test_no_truth_cache_when_the_variable_is_empty(coarse_model, coarse_truth_p1, tmp_path, monkeypatch):
    from softphantom.virtual.truth import truth_cache_dir

    monkeypatch.setenv("SOFTPHANTOM_CACHE_DIR", "")
    assert truth_cache_dir() is None
    monkeypatch.delenv("SOFTPHANTOM_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert truth_cache_dir() == tmp_path / "softphantom"
