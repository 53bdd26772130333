"""The sweep file: parameter paths, sampling (grid, random, Latin hypercube), cache keys, bad input."""

import math

import numpy as np
import pytest

from softphantom.design import design_from_dict
from softphantom.errors import UserError
from softphantom.study.config import load_sweep_config, sweep_config_from_dict


def _cfg(params, **sweep):
    return sweep_config_from_dict({"sweep": sweep, "parameters": params})


def test_paths_reach_vectors_wildcards_and_extras():
    cfg = _cfg({}, method="grid")
    v = cfg.resolve(0, {"arms.*.radius_mm": 6.5, "arms.back_xneg.direction[1]": 0.4,
                        "urethra.center_mm[2]": 3.5, "sensing.tube_length_m": 3.0, "materials.*.E_kPa": 120.0})
    d = design_from_dict(v.design)
    assert [a.radius_mm for a in d.arms] == [6.5] * 4
    assert d.arms[3].direction == (-1.0, 0.4, 0.0)
    assert d.urethra.center_mm == (0.0, 0.0, 3.5)
    assert v.extra["sensing.tube_length_m"] == 3.0
    assert [m.values for m in d.materials] == [(("E_kPa", 120.0), ("nu", 0.45), ("density_kg_m3", 1070.0))]
    assert cfg.base["arms"]["front_zpos"]["radius_mm"] == 6.0  # the base is not modified


def test_cavity_length_sets_the_capsule_volume():
    cfg = _cfg({}, method="grid")
    v = cfg.resolve(0, {"arms.front_zpos.cavity_length_mm": 10.0})
    r = 6.0 - 2.5
    want = math.pi * r * r * 10.0 + 4 / 3 * math.pi * r**3
    arm = design_from_dict(v.design).arms[0]
    assert arm.cavity_volume_mm3 == pytest.approx(want)
    assert arm.cavity_cyl_length_mm == pytest.approx(10.0)


def test_grid_is_the_product_and_lhs_is_stratified_and_seeded():
    g = _cfg({"arms.*.wall_mm": {"min": 1.5, "max": 3.0, "steps": 4}, "sensing.osr": {"values": [16, 64]}},
             method="grid").variants()
    assert len(g) == 8 and g[0].params == {"arms.*.wall_mm": 1.5, "sensing.osr": 16}
    assert g[-1].params == {"arms.*.wall_mm": 3.0, "sensing.osr": 64}
    spec = {"arms.*.radius_mm": {"min": 5.0, "max": 7.0}, "sensing.tube_length_m": {"min": 0.5, "max": 12.0, "log": True}}
    a = _cfg(spec, method="lhs", samples=10, seed=3).variants()
    b = _cfg(spec, method="lhs", samples=10, seed=3).variants()
    c = _cfg(spec, method="lhs", samples=10, seed=4).variants()
    assert [v.params for v in a] == [v.params for v in b] != [v.params for v in c]
    r = np.array([v.params["arms.*.radius_mm"] for v in a])
    # Latin hypercube: exactly one sample in each tenth of the range
    assert sorted(np.floor((r - 5.0) / 0.2).astype(int).tolist()) == list(range(10))
    t = np.log(np.array([v.params["sensing.tube_length_m"] for v in a]))
    assert sorted(np.floor((t - math.log(0.5)) / (math.log(24.0) / 10)).astype(int).tolist()) == list(range(10))
    rnd = _cfg(spec, method="random", samples=50, seed=1).variants()
    assert all(5.0 <= v.params["arms.*.radius_mm"] <= 7.0 for v in rnd)


def test_key_depends_on_what_is_evaluated_not_on_the_index():
    cfg = _cfg({}, method="grid")
    a, b = cfg.resolve(0, {"arms.*.wall_mm": 2.0}), cfg.resolve(7, {"arms.*.wall_mm": 2.0})
    assert a.key == b.key
    assert cfg.resolve(0, {"arms.*.wall_mm": 2.1}).key != a.key
    assert cfg.resolve(0, {"sensing.tube_id_mm": 1.0}).key != cfg.resolve(0, {}).key


@pytest.mark.parametrize("data, where", [
    ({"parameters": {"arms.front_zpos.colour": {"values": [1]}}}, 'parameters."arms.front_zpos.colour": unknown parameter'),
    ({"parameters": {"arms.left.radius_mm": {"values": [1]}}}, 'parameters."arms.left.radius_mm": unknown parameter (arms has back_xneg'),
    ({"parameters": {"bulb.semi_axes_mm[3]": {"values": [1]}}}, "semi_axes_mm has no element [3]"),
    ({"parameters": {"arms.*.radius_mm": {"min": 7, "max": 5}}}, "max 5 is below min 7"),
    ({"parameters": {"arms.*.radius_mm": {"min": 5}}}, "needs min and max"),
    ({"parameters": {"arms.*.radius_mm": {"min": 5, "max": 6, "step": 2}}}, "unknown key 'step'"),
    ({"sweep": {"method": "sobol"}}, "sweep.method: 'sobol' is not one of grid, random, lhs"),
    ({"sweep": {"samples": 0}}, "sweep.samples = 0 must be >= 1"),
    ({"evaluate": {"directions": ["up"]}}, "evaluate.directions[0]: 'up' is not one of xpos"),
    ({"evaluate": {"probe_force_N": 0}}, "evaluate.probe_force_N = 0 must be > 0 N"),
    ({"fixed": {"tube_length_m": 3}}, "fixed: unknown key 'tube_length_m'"),
    ({"fixed": {"sensing.tube_length_m": -3}}, 'fixed."sensing.tube_length_m" = -3 must be > 0 m'),
    ({"swep": {}}, "sweep file: unknown key 'swep'"),
])
def test_bad_sweep_files_name_the_field(data, where):
    with pytest.raises(UserError) as err:
        sweep_config_from_dict(data)
    assert where in str(err.value) and "\n" not in str(err.value)


def test_unreadable_or_malformed_file(tmp_path):
    with pytest.raises(UserError, match="cannot read"):
        load_sweep_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[sweep\n")
    with pytest.raises(UserError, match="not valid TOML"):
        load_sweep_config(bad)


def test_invalid_design_is_not_a_config_error():
    # a range that produces invalid designs is reported per variant, not refused up front
    cfg = _cfg({"arms.*.wall_mm": {"values": [2.5, 7.0]}}, method="grid")
    assert len(cfg.variants()) == 2


def test_example_file_loads():
    from pathlib import Path

    cfg = load_sweep_config(Path(__file__).parents[1] / "examples" / "sweep_arms.toml")
    assert cfg.method == "lhs" and len(cfg.variants()) == cfg.samples


def test_example_variants_are_valid_designs():
    """Every variant of examples/sweep_arms.toml, and every corner of its parameter box (so another
    seed's or size's sample is valid too), passes the design's checks: the example sweeps designs,
    not refusals. Validation only (no mesh)."""
    from pathlib import Path

    from softphantom.study import design_problem

    cfg = load_sweep_config(Path(__file__).parents[1] / "examples" / "sweep_arms.toml")
    geometric = [p for p in cfg.params if p.continuous and not p.path.startswith("sensing.")]
    assert len(geometric) == 4
    corners = sweep_config_from_dict({"sweep": {"method": "grid"},
                                      "parameters": {p.path: {"values": [p.lo, p.hi]} for p in geometric}})
    problems = {f"{v.index} {v.params}": design_problem(v) for v in (*cfg.variants(), *corners.variants())}
    assert len(problems) == cfg.samples + 16
    assert {k: w for k, w in problems.items() if w} == {}


def test_the_element_order_is_a_setting_of_the_study():
    """``[fixed] element_order`` sets every variant's elements (and its cache key); left out, the
    base design's; anything but 1 or 2 is refused naming the field."""
    params = {"arms.*.radius_mm": {"values": [6.0]}}
    base = sweep_config_from_dict({"sweep": {"method": "grid"}, "parameters": params})
    (v1,) = base.variants()
    assert design_from_dict(v1.design).mesh.element_order == 1  # the built-in base design's
    quad = sweep_config_from_dict({"sweep": {"method": "grid"}, "fixed": {"element_order": 2}, "parameters": params})
    (v2,) = quad.variants()
    assert design_from_dict(v2.design).mesh.element_order == 2 and v2.key != v1.key
    with pytest.raises(UserError, match="element_order"):
        sweep_config_from_dict({"fixed": {"element_order": 3}, "parameters": params})
    from pathlib import Path

    example = load_sweep_config(Path(__file__).parents[1] / "examples" / "sweep_arms.toml")
    assert design_from_dict(example.variants()[0].design).mesh.element_order == 1
