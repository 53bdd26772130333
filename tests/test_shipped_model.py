"""The shipped quadratic model (softphantom/data/models/bip_p2) and the keys of its default atlas:
a change to anything an atlas key depends on (mesh reading, law, contact patch, tracked points,
envelope, grid, tolerance, what the numbers mean) fails here in one line naming the build to run."""

from __future__ import annotations

import json
from importlib import resources

import pytest

pytestmark = pytest.mark.slow


# the CPU variants a user's machine may be: OpenBLAS's kernels and numpy's SIMD level change the last
# bits of what they compute; the key and the staleness checks must not depend on them
CPU_VARIANTS = [{"OPENBLAS_CORETYPE": c} for c in ("Prescott", "Sandybridge", "Haswell", "Zen")] + [
    {"NPY_DISABLE_CPU_FEATURES": "AVX2,FMA3", "OPENBLAS_CORETYPE": "Sandybridge"}]

_KEYS_AND_VERIFY = """
import json, sys
from importlib import resources
from softphantom.cli import main
from softphantom.design import load_model
from softphantom.estimation import EstimatorConfig
from softphantom.estimation.atlas import atlas_key
from softphantom.estimation.atlas.config import default_atlas_config, draft_atlas_config
d = resources.files("softphantom") / "data" / "models" / "bip_p2"
model = load_model(d)
keys = {(c, draft): [atlas_key(model, EstimatorConfig(contact=c), p)[:32]
                     for p in (draft_atlas_config(2) if draft else default_atlas_config(2)).patches()]
        for c in ("on-centre", "off-centre") for draft in (False, True)}
keys = {f"{c} draft" if draft else c: v for (c, draft), v in keys.items()}
print(json.dumps(keys))
sys.exit(main(["atlas", "verify", "--model", str(d)]))
"""


def _manifest():
    d = resources.files("softphantom") / "data" / "models" / "bip_p2"
    return d, json.loads((d / "atlas.json").read_text())


@pytest.mark.parametrize("env", CPU_VARIANTS, ids=lambda e: ",".join(f"{k}={v}" for k, v in e.items()))
def test_the_shipped_atlas_keys_and_checks_hold_on_every_cpu_variant(env):
    """Under each CPU variant (a subprocess), the shipped model's keys are the manifest's and
    ``atlas verify`` passes: the key hashes inputs only, the checks compare numbers within tolerances."""
    import os
    import subprocess
    import sys

    from softphantom.estimation.atlas.config import default_atlas_config, draft_atlas_config

    d, manifest = _manifest()
    r = subprocess.run([sys.executable, "-c", _KEYS_AND_VERIFY], capture_output=True, text=True, timeout=300,
                       env={**os.environ, **env})
    assert r.returncode == 0, r.stdout + r.stderr
    keys = json.loads(r.stdout.splitlines()[0])
    for p in manifest["pieces"]:
        which = p["contact"] + " draft" * p.get("draft", False)  # a draft (atlas build --draft): one piece
        pieces = (draft_atlas_config(2) if p.get("draft") else default_atlas_config(2)).patches()
        i = [[c.force_min_N[1], c.force_max_N[1]] for c in pieces].index(p["f_y_N"])
        key = keys[which][i]
        assert key == p["key"], (f"the shipped atlas piece {which} f_y {p['f_y_N']} N is stale (key {p['key']}, "
                                 f"this code gives {key}): rebuild it with `{manifest['builds'][which]}` and "
                                 f"update atlas.json")
        assert f"ok  {d / 'atlas' / (p['key'] + '.npz')}" in r.stdout, r.stdout


def test_a_missing_or_stale_shipped_file_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    """A manifest's file that is missing is named; a shipped file whose numbers are not the model's
    (the rest state it recorded changed) fails ``atlas verify`` naming the file and the quantity."""
    import io
    import shutil

    import numpy as np

    from softphantom.cli import main
    from softphantom.design import load_model
    from softphantom.design import model as design_model
    from softphantom.estimation.atlas.catalogue import ShippedMissing, shipped_atlas

    d, manifest = _manifest()
    pkg = tmp_path / "models"
    (pkg / "bip_p2" / "atlas").mkdir(parents=True)
    for f in ("model.npz", "design.toml", "atlas.json"):
        shutil.copy(d / f, pkg / "bip_p2" / f)
    monkeypatch.setattr(design_model, "SHIPPED_MODELS", pkg)
    key = manifest["pieces"][0]["key"]
    with pytest.raises(ShippedMissing, match=f"{key}.npz: listed in .*atlas.json but missing"):
        shipped_atlas(key)
    # a copy whose recorded rest volumes are another model's: verify names the quantity
    src = d / "atlas" / f"{key}.npz"
    with np.load(src, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k: z[k] for k in z.files if k != "meta"}
    meta["provenance"]["rest"]["cavity_volumes_mm3"]["urethra"] *= 1.01
    buf = io.BytesIO()
    np.savez_compressed(buf, meta=np.array(json.dumps(meta)), **arrays)
    bad = pkg / "bip_p2" / "atlas" / f"{key}.npz"
    bad.write_bytes(buf.getvalue())
    assert load_model(pkg / "bip_p2").nodes.shape[0] == 28329
    capsys.readouterr()
    assert main(["atlas", "verify", "--model", str(pkg / "bip_p2"), str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: rest cavity volumes differ" in err and "Traceback" not in err, err


def test_the_shipped_atlas_is_found_whole_and_holds_at_a_held_out_full_solve(tmp_path):
    """The default model's atlas ships in the package (one file per piece, by key): intact, of this
    model, found by a model directory that ``design`` writes by default and the demo's scenarios (no
    build), and at one seeded held-out full solve within the worst errors measured over 9 held-out
    loads at its release (0.073 N, 0.16 mm, 0.33°, near_urethra 0.18 mm), rounded up: what an atlas
    of another model or a damaged one would exceed many times (a full solve in the lower piece: 7 s).
    Its numbers against the model are ``atlas verify``'s (the CPU-variant test above); the upper
    piece's estimates, fold included, are pinned by test_bip_unchanged; the whole envelope is
    ``benchmarks/bench_shipped_atlas.py``'s."""
    from softphantom.design import default_design, load_model, shipped_model
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.catalogue import load_or_build, shipped_atlas
    from softphantom.estimation.atlas.check import check_held_out, held_out_loads

    d, manifest = _manifest()
    for p in manifest["pieces"]:
        path = d / "atlas" / f"{p['key']}.npz"
        assert path.stat().st_size <= p["size_MB"] * 1.01e6 and shipped_atlas(p["key"]) == path
    assert sum(p["size_MB"] for p in manifest["pieces"]) <= 30.0
    model = shipped_model(default_design())
    assert model is not None and model.nodes.shape == load_model(d).nodes.shape
    cfg = EstimatorConfig(contact="on-centre")
    found = load_or_build(model, cfg, None, max_build_s=0.0)
    assert [a.key[:32] for a in found.patches] == [p["key"] for p in manifest["pieces"] if p["contact"] == "on-centre"]
    # the demo's scenarios find every atlas they need (from the package, by key; nothing built or written)
    from softphantom.virtual import load_scenario
    from softphantom.virtual.demo import DEMO_SCENARIOS, model_atlases

    demo = model_atlases([load_scenario(n) for n in DEMO_SCENARIOS], model, tmp_path / "model")
    for c, f in demo.items():
        assert {p.origin for p in f.pieces} == {"shipped"}, (c, f.describe())
    assert [a.key for a in demo["on-centre"].atlas.patches] == [a.key for a in found.patches]
    assert not (tmp_path / "model").exists()
    # the demo's summary row of what it found (an estimate file of the shipped atlas read back)
    import gzip
    from pathlib import Path

    from softphantom.virtual.demo import _atlas_row

    est = tmp_path / "estimate.csv"
    est.write_bytes(gzip.decompress((Path(__file__).parent / "data" / "bip_outputs" /
                                     "push-on-centre.estimate.csv.gz").read_bytes()))
    row = _atlas_row(demo["on-centre"], est)
    assert row["pieces"] == 2 and 0.9 <= row["in_envelope_fraction"] <= 1.0 and "draft" not in row, row
    # the off-centre pushes' atlas ships as a draft (atlas.json "draft": true), its measured error with it
    off = _atlas_row(demo["off-centre"], est)
    assert off["draft"] and off["grid"] == (5, 4, 3, 2) and off["held_out"]["loads"] >= 10, off
    lo_y, split = manifest["pieces"][0]["f_y_N"]
    loads = held_out_loads([-1, max(lo_y, 0.0), -1, 0], [1, split, 1, 10e3], 1, seed=3)
    res = check_held_out(model, cfg, found, loads, seed=1)
    assert len(res.loads) == 1 and not res.failed and not res.skipped, res
    w = res.worst()
    assert w["force_N"] < 0.1 and w["pos_mm"] < 0.2 and w["ang_deg"] < 0.4 and w["near_urethra_mm"] < 0.2, w


def test_the_shipped_rest_sensitivity_is_the_shipped_atlas_s_at_zero_load():
    """The rest sensitivity shipped with the model (observability.json, what ``design`` reports for
    the default design instead of solving) against the shipped atlas's Jacobian at zero load (an
    interpolant of other converged solves): the force columns within 1 %. The pressure column is
    not compared: the atlas has 3 points over -2…40 kPa, too few for its slope at zero."""
    import numpy as np

    from softphantom.design import load_model
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.catalogue import load_or_build
    from softphantom.estimation.observability import observability_at_rest, shipped_rest_W

    d, _ = _manifest()
    model = load_model(d)
    W = shipped_rest_W(d)
    piece = load_or_build(model, EstimatorConfig(), None, max_build_s=0.0).piece(np.zeros(4))
    lam = piece.coords(np.zeros(3), 0.0)
    J = piece.by_force(lam, piece.volumes(lam)[1])
    rel = np.abs(J[:, :3] - W[:, :3]).max(axis=0) / np.abs(W[:, :3]).max(axis=0)
    assert rel.max() < 0.01, rel
    obs = observability_at_rest(model, W)
    assert obs.rest.cond_force < 10 and not obs.loaded
