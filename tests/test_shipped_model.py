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
