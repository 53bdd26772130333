"""The shipped quadratic model (softphantom/data/models/bip_p2) and the keys of its default atlas:
a change to anything an atlas key depends on (mesh reading, law, contact patch, tracked points,
envelope, grid, tolerance, what the numbers mean) fails here in one line naming the build to run."""

from __future__ import annotations

import json
from importlib import resources

import pytest

pytestmark = pytest.mark.slow


def test_the_shipped_models_atlas_keys_are_current():
    from softphantom.design import load_model
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas import atlas_key
    from softphantom.estimation.atlas.config import default_atlas_config
    from softphantom.estimation.forward import ForwardModel

    d = resources.files("softphantom") / "data" / "models" / "bip_p2"
    manifest = json.loads((d / "atlas.json").read_text())
    model = load_model(d)
    assert len(model.nodes) == 28329 and model.element_order == 2
    fwd = ForwardModel(model, EstimatorConfig(contact=manifest["contact"]))
    pieces = default_atlas_config(2).patches()
    assert [[c.force_min_N[1], c.force_max_N[1]] for c in pieces] == [p["f_y_N"] for p in manifest["pieces"]]
    for c, p in zip(pieces, manifest["pieces"]):
        key = atlas_key(fwd, c)[:32]
        assert key == p["key"], (f"the shipped atlas piece f_y {p['f_y_N']} N is stale (key {p['key']}, this code "
                                 f"gives {key}): rebuild it with `{manifest['build']}` and update atlas.json")


def test_the_shipped_atlas_verifies_and_holds_at_held_out_full_solves(capsys):
    """The default model's atlas ships in the package (one file per piece, by key): intact, of this
    model (``atlas verify`` recomputes the keys), found by a model directory that ``design`` writes
    by default (no build), and at two seeded held-out full solves (``atlas check``) within the worst
    errors measured over 9 held-out loads at its release (0.073 N, 0.16 mm, 0.33°, near_urethra
    0.18 mm), rounded up: what an atlas of another model or a damaged one would exceed many times.
    These are not the accuracy goals (0.05 N, 0.05 mm, 0.1°, 0.02 mm): this atlas's 90th
    percentiles over those loads were 0.019 N, 0.041 mm, 0.11°, and its worst loads miss them
    (``benchmarks/bench_shipped_atlas.py`` measures it; docs/estimation.md says so)."""
    from softphantom.cli import main
    from softphantom.design import default_design, load_model, shipped_model
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.build import load_or_build
    from softphantom.estimation.atlas.store import shipped_atlas

    d = resources.files("softphantom") / "data" / "models" / "bip_p2"
    manifest = json.loads((d / "atlas.json").read_text())
    for p in manifest["pieces"]:
        path = d / "atlas" / f"{p['key']}.npz"
        assert path.is_file(), f"the shipped atlas piece {path} is missing: build it with `{manifest['build']}`"
        assert path.stat().st_size <= p["size_MB"] * 1.01e6 and shipped_atlas(p["key"]) == path
    assert sum(p["size_MB"] for p in manifest["pieces"]) <= 25.0
    assert main(["atlas", "verify", "--model", str(d)]) == 0
    out = capsys.readouterr().out
    assert all(f"ok  {d / 'atlas' / (p['key'] + '.npz')}" in out for p in manifest["pieces"]), out
    model = shipped_model(default_design())
    assert model is not None and model.nodes.shape == load_model(d).nodes.shape
    found = load_or_build(model, EstimatorConfig(contact=manifest["contact"]), None, max_build_s=0.0)
    assert [a.key[:32] for a in found.patches] == [p["key"] for p in manifest["pieces"]]
    assert main(["atlas", "check", "--model", str(d), "--workers", "0", "--loads", "2", "--seed", "1",
                 "--max-force-N", "0.1", "--max-pos-mm", "0.2", "--max-ang-deg", "0.4",
                 "--max-near-urethra-mm", "0.2"]) == 0, capsys.readouterr().err
