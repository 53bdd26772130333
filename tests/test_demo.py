"""`softphantom demo` on the coarse mesh with one short scenario: files, report, summary on screen;
bad options are one-line errors. `softphantom virtual run`'s files and summary are
test_cavities_e2e.py's (its end-to-end run starts with it)."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import pytest

from softphantom.cli import main

SHORT = """name = "demo-short"
description = "one push, 4 s"
duration_s = 4.0
rest_s = 1.0
[[push]]
point = "off-centre"
start_s = 1.2
rise_s = 1.0
hold_s = 0.5
fall_s = 1.0
force_N = [0.3, 2.5, 0.2]
"""


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs = []

    def handle_starttag(self, tag, attrs):
        for k, v in attrs:
            if k in ("href", "src") and v and not v.startswith(("http", "data:", "#")):
                self.refs.append(v)


@pytest.mark.slow
def test_demo_end_to_end_coarse(tmp_path, capsys, coarse_model_dir):
    sc = tmp_path / "short.toml"
    sc.write_text(SHORT)
    out = tmp_path / "demo"
    # the coarse (12 mm) model given with --model, as a calibrated one would be: not meshed again; one
    # worker process (the truth and the atlas take turns on it: a second costs its start-up, ~5 CPU-s);
    # a 27-solve atlas (3 points per force axis, the fewest it takes); the truth on the model's own mesh
    # (P1, scale 1: the fastest; a finer P2 truth is test_virtual's)
    assert main(["demo", "--out", str(out), "--model", str(coarse_model_dir), "--scenarios", str(sc), "--seed", "2",
                 "--atlas-grid", "3,3,3,2", "--truth-order", "1", "--truth-mesh-scale", "1", "--workers", "1"]) == 0
    text = capsys.readouterr().out
    assert "model: 2170 nodes" in text and "(mesh 12 mm)" in text and "truth model: " in text
    assert sorted(p.name for p in coarse_model_dir.iterdir()) == ["design.toml", "model.msh", "model.npz", "model.vtu"]
    d = out / "demo-short"
    for f in ("frames.bin", "recording.csv", "tracker_motive.csv", "truth.csv", "snapshot.vtu", "virtual.json",
              "estimate.csv", "report/report.html"):
        assert (d / f).stat().st_size > 0, f
    # the report and the index reference only files that exist
    for page in (d / "report" / "report.html", out / "index.html"):
        p = _Links()
        p.feed(page.read_text())
        assert p.refs, page
        for ref in p.refs:
            assert (page.parent / ref).is_file(), (page, ref)
    s = json.loads((out / "summary.json").read_text())
    row = s["scenarios"][0]
    assert row["scenario"] == "demo-short" and set(row["rmse"]) == {"x", "y", "z", "yaw", "pitch", "roll"}
    # the off-centre contact was used and the estimate follows the truth (coarse mesh: loose bounds,
    # the tight ones are in test_virtual_e2e.py)
    assert row["peak_truth"]["y"] > 2.0 and row["rmse"]["y"] < 0.2 * row["peak_truth"]["y"]
    assert row["force_rmse_N"]["|force|"] < 0.5
    # the 12 m tubes delay the transducers ~100 ms; the estimator compensates it (a lag of a few ms left)
    assert abs(row["lag_ms"]) < 30.0
    c = row["tracker_clock_offset_ms"]
    assert abs(c["recovered"] - c["injected"]) < 5.0
    assert {r["dof"] for r in row["table_i"]} == {"yaw", "pitch", "x", "y", "z"}
    # on screen: the summary table, Table I, the report path
    assert "demo-short" in text and "Table I" in text and "tracker clock offset" in text
    assert re.search(r"report: .*demo-short/report/report\.html", text)
    assert "index: " in text
    # output that is not a terminal (this capture, a CI log) still shows the long steps' progress
    assert "design → mesh (estimator model) …" in text and "design → mesh (estimator model): done in" in text
    assert re.search(r"demo-short: estimate: \d+/\d+ \(50 %\)", text)
    assert re.search(r"demo-short: truth: \d+/\d+ \(\d+ %\)", text)  # the Dask worker's progress reaches the bar
    # truth.csv and the estimate of the virtual board share the scenario clock: the lag is the latency
    report = (d / "report" / "report.html").read_text()
    assert "the estimator&#x27;s latency (both files on the same clock: scenario (s))" in report
    # the deformed phantom is drawn (the truth's snapshot holds 10-node or 4-node tets)
    assert '<img src="snapshot_3d.png"' in report and "nothing to draw" not in report
    # the summary names the files where they are, not the demo's staging folder
    assert ".partial" not in report
    for f in ("estimate.csv", "truth.csv"):
        assert f"<td>{d / f}</td>" in report, f


def test_a_demo_on_a_model_without_its_atlas_is_refused_before_any_solve(tmp_path, capsys, coarse_model_dir,
                                                                         monkeypatch):
    # no atlas in the model directory and (here) none that builds within the on-the-fly limit: one
    # line naming the build command and the way on (--atlas-grid is the demo's own; --estimator refresh)
    import softphantom.estimation.atlas.build as build

    monkeypatch.setattr(build, "MAX_BUILD_ON_THE_FLY_S", 0.0)
    sc = tmp_path / "short.toml"
    sc.write_text(SHORT)
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--model", str(coarse_model_dir), "--scenarios", str(sc),
                 "--truth-order", "1", "--workers", "1"]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert err.count("\n") == 0 and "softphantom atlas build --model" in err and "--at off-centre" in err, err
    assert "--estimator refresh" in err and "truth" not in cap.out  # refused before the truth is meshed
    assert not out.exists() and not list(tmp_path.glob("demo*.partial*"))
    assert sorted(p.name for p in coarse_model_dir.iterdir()) == ["design.toml", "model.msh", "model.npz", "model.vtu"]


def test_demo_and_virtual_bad_options_are_one_line(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "o"), "--scenarios", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nope" in err and "Traceback" not in err
    assert main(["demo", "--out", str(tmp_path / "o"), "--truth-mesh-scale", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--truth-mesh-scale" in err and err.count("\n") == 0
    assert main(["demo", "--out", str(tmp_path / "o"), "--truth-order", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--truth-order" in err and err.count("\n") == 0
    for args in (["--mesh-size-mm", "0"], ["--mesh-size-mm", "12", "--model", str(tmp_path)]):
        assert main(["demo", "--out", str(tmp_path / "o"), *args]) == 2
        err = capsys.readouterr().err.strip()
        assert "--mesh-size-mm" in err and err.count("\n") == 0
    bad = tmp_path / "bad.toml"
    bad.write_text('arm_names = ["front_zpos", "front_zneg"]\n')
    for args, word in ((["--design", str(bad)], "arms: 2 given"), (["--design", str(bad), "--model", str(tmp_path)],
                       "--design"), (["--design", str(bad), "--push-N", "0"], "--push-N")):
        assert main(["demo", "--out", str(tmp_path / "o"), *args]) == 2
        err = capsys.readouterr().err.strip()
        assert word in err and err.count("\n") == 0, err
    assert not (tmp_path / "o").exists()
    assert main(["virtual", "serve", "--scenario", "needle-insertion", "--model", str(tmp_path), "--speed", "0"]) == 2
    assert "--speed" in capsys.readouterr().err


def test_a_killed_demo_leaves_no_worker(tmp_path):
    # the demo's truth solves and atlas builds run on a Dask local cluster (softphantom.parallel):
    # its parent SIGKILLed (no clean-up runs), the worker processes must exit by themselves
    import os
    import subprocess
    import sys
    import time

    code = ("import os, time; from softphantom.parallel import dask_client\n"
            "with dask_client(n_workers=1) as c:\n"
            "    w = list(c.run(os.getpid).values())[0]\n"
            "    print(w, open(f'/proc/{w}/stat').read().split()[3], flush=True)\n"
            "    time.sleep(600)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    workers = [int(v) for v in parent.stdout.readline().split()]  # the worker and its nanny
    assert len(workers) == 2 and all(Path(f"/proc/{p}").exists() for p in workers)  # alive while the parent is
    parent.kill()
    parent.wait()

    def gone(pid: int) -> bool:
        try:
            return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
        except OSError:
            return True

    deadline = time.monotonic() + 30
    while not all(gone(p) for p in workers):
        if time.monotonic() > deadline:
            raise AssertionError("a worker outlived its killed parent")
        time.sleep(0.05)
