"""An atlas build killed at a random point and started again: it loses at most the task in flight,
refuses other settings while the interrupted build waits, and ends with the atlas an uninterrupted
build gives (the same coefficients, bit for bit)."""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from shared_models import atlas_config, cached_atlas

from softphantom.estimation.atlas.catalogue import atlases_of as model_atlases
from softphantom.estimation.atlas.store import ARRAYS, load_atlas

pytestmark = pytest.mark.slow

# the CLI options of shared_models.atlas_config("displacement"): faces, then lines depending on them
OPTIONS = ["--atlas-grid", "3,4,3,2", "--envelope", "-0.5:0.5,-0.3:1.2,-0.5:0.5,-1:4",
           "--atlas-x-axis", "displacement", "--atlas-f-y-split-N", ""]


def _build(model_dir: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.Popen([sys.executable, "-m", "softphantom", "atlas", "build", "--model", str(model_dir),
                             "--workers", "1", *OPTIONS, *extra], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env, start_new_session=True)


@pytest.mark.parametrize("seed", [3])
def test_a_build_killed_at_a_random_point_resumes_to_the_same_atlas(shared_dir, coarse_model_dir, tmp_path, seed):
    reference = cached_atlas(shared_dir, "displacement")  # built in one go, in-process
    # each face (2 per pressure) a spine and a branch per f_z point; a line per f_y, f_z and pressure
    n_tasks = 2 * 2 * (1 + 3) + 4 * 3 * 2
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    shutil.copy(coarse_model_dir / "model.npz", model_dir)
    rng = np.random.default_rng(seed)
    stop_after = int(rng.integers(1, n_tasks))  # finished tasks before the kill
    partial = model_dir / "atlas" / "partial"
    proc = _build(model_dir)
    t_end = time.monotonic() + 600
    while len(list(partial.glob("*/*.task"))) < stop_after and proc.poll() is None and time.monotonic() < t_end:
        time.sleep(0.05)
    time.sleep(float(rng.uniform(0.0, 1.0)))  # and a random moment into the next task
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    kept = len(list(partial.glob("*/*.task")))
    assert stop_after <= kept < n_tasks, (stop_after, kept)

    # other settings while the interrupted build waits: refused in one line naming the setting
    other = subprocess.run([sys.executable, "-m", "softphantom", "atlas", "build", "--model", str(model_dir),
                            "--workers", "1", *OPTIONS[:1], "3,5,3,2", *OPTIONS[2:]], capture_output=True,
                           text=True, env={**os.environ, "COLUMNS": "300"})
    assert other.returncode == 2, other.stdout + other.stderr
    err = (other.stdout + other.stderr).strip().splitlines()
    assert len(err) == 1 and "interrupted atlas build with other settings" in err[0] and "n_force" in err[0], err
    assert "--discard-partial" in err[0] and len(list(partial.glob("*/*.task"))) == kept  # nothing dropped

    # the same command goes on: the kept tasks are loaded, not solved again
    proc = _build(model_dir)
    out, _ = proc.communicate(timeout=600)
    assert proc.returncode == 0, out
    assert f"resuming, {kept} of {n_tasks} tasks kept" in out, out
    files = model_atlases(model_dir)
    assert len(files) == 1 and not partial.exists()  # the kept tasks go once the atlas is saved
    at = load_atlas(files[0])
    assert at.key == reference.key
    for name in ARRAYS:
        assert np.array_equal(getattr(at, name), getattr(reference, name)), name
    assert at.provenance["build"]["kept_tasks"] == kept
    assert at.provenance["command"].startswith("softphantom atlas build --model")


def test_discard_partial_drops_an_interrupted_build_of_other_settings(coarse_model, tmp_path):
    from softphantom.errors import UserError
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.build import build_settings
    from softphantom.estimation.atlas.tasks import TaskStore, check_partials, partial_dir
    from softphantom.estimation.forward import ForwardModel

    fwd = ForwardModel(coarse_model, EstimatorConfig(contact="on-centre"))
    mine = build_settings(fwd.config, atlas_config("displacement"), fwd.fem.n_dof // 3)
    theirs = build_settings(fwd.config, atlas_config("force"), fwd.fem.n_dof // 3)
    store = TaskStore(partial_dir(tmp_path, "ab" * 32), {"build": theirs, "key": "ab" * 32})
    store.save("p0-plane-0-0", {"x": np.arange(3.0)}, 1.0, 2.0)
    check_partials(tmp_path, theirs)  # the same settings: left to be resumed
    with pytest.raises(UserError, match=r"atlas\.x_control \"force\" there, \"displacement\" here"):
        check_partials(tmp_path, mine)
    value, cpu, wall = store.load("p0-plane-0-0")
    assert np.array_equal(value["x"], np.arange(3.0)) and (cpu, wall) == (1.0, 2.0)
    (store.dir / "p0-plane-1-0.task").write_bytes(b"softphantom-atlas-task-1\ntruncat")
    assert store.load("p0-plane-1-0") is None  # damaged: run again
    check_partials(tmp_path, mine, discard=True)
    assert not store.dir.exists()


def test_a_model_without_its_atlas_says_how_long_it_takes_and_what_to_do(coarse_p2_model, tmp_path):
    """estimate and live (max_build_s) do not start a build that takes longer than a command should
    wait: one line with the estimated time, the command that builds it, and the refresh estimator."""
    from softphantom.estimation import EstimatorConfig, load_or_build
    from softphantom.estimation.atlas.build import AtlasMissing, estimated_build
    from softphantom.estimation.atlas.config import default_atlas_config
    from softphantom.estimation.forward import ForwardModel

    cfg = EstimatorConfig(contact="off-centre")
    fwd = ForwardModel(coarse_p2_model, cfg)
    cpu, wall = estimated_build(fwd.fem.order, fwd.fem.n_dof // 3, default_atlas_config(2), workers=2)
    assert wall >= cpu / 2 and wall > 600  # the quadratic model's default atlas: longer than a command waits
    with pytest.raises(AtlasMissing) as exc:
        load_or_build(coarse_p2_model, cfg, cache_dir=tmp_path, fwd=fwd, n_workers=2, max_build_s=600)
    msg = str(exc.value)
    assert "\n" not in msg and f"softphantom atlas build --model {tmp_path} --at off-centre" in msg
    assert "--estimator refresh" in msg and "on 2 cores" in msg and f"{cpu:.0f} CPU-s" in msg
    # the smaller atlas a new organ's first hour wants: its options and its time, and where it is shown
    small = dataclasses.replace(default_atlas_config(2), n_force=(3, 3, 3), n_pressure=2, f_y_splits_N=())
    from softphantom.estimation.atlas.build import duration_text

    t_small = duration_text(estimated_build(fwd.fem.order, fwd.fem.n_dof // 3, small, workers=2)[1])
    assert f"--atlas-grid 3,3,3,2 --envelope FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX (N, kPa; about {t_small}" in msg
    assert "docs/organs.md" in msg
    assert not (tmp_path / "atlas").exists()  # nothing started
