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


def test_sweep_where_every_variant_is_invalid_exits_2_and_writes_nothing(client, tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[sweep]\nmethod = "grid"\n[fixed]\nmesh_size_mm = 12.0\n'
                   '[parameters]\n"arms.*.wall_mm" = { values = [7.0, 8.0] }\n')
    out = tmp_path / "o"
    assert main(["sweep", "--config", str(cfg), "--out", str(out), "--scheduler", client.scheduler.address,
                 "--no-progress"]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert err.count("\n") == 0 and "all 2 variants are invalid" in err, err
    assert "variant 0 invalid: DesignError: arms.front_zpos.wall_mm = 7 leaves no cavity" in cap.out
    assert not out.exists()


def test_sweep_with_one_valid_variant_still_exits_0(client, tmp_path, capsys):
    cfg = tmp_path / "mixed.toml"
    cfg.write_text('[sweep]\nmethod = "grid"\n[fixed]\nmesh_size_mm = 12.0\n[evaluate]\ndirections = ["zneg"]\n'
                   '[parameters]\n"arms.*.wall_mm" = { values = [2.5, 7.0] }\n')
    out = tmp_path / "o"
    assert main(["sweep", "--config", str(cfg), "--out", str(out), "--scheduler", client.scheduler.address,
                 "--no-progress"]) == 0
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
