"""The BIP parameter object: paper numbers, derived points, validation, files (no meshing)."""

from __future__ import annotations

import copy
import dataclasses
import difflib
import json
import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from softphantom.design import ARM_NAMES, BIPDesign, MeshParams, UrethraParams, load_design, save_design
from softphantom.design import geometry as geo
from softphantom.design.params import design_from_dict, design_to_dict, design_to_toml
from softphantom.errors import DesignError


def test_defaults_reproduce_the_paper_volumes():
    d = BIPDesign()
    assert d.bulb.volume_mm3 == pytest.approx(100_410.0, rel=1e-12)  # 100.41 mL
    a, b, c = d.bulb.semi_axes_mm
    assert (a, b) == (32.0, 25.0) and c == pytest.approx(29.96, abs=0.01)
    u = d.urethra
    assert geo.capsule_volume(u.radius_mm, u.cyl_length_mm) == pytest.approx(2078.0, rel=1e-12)
    vols = d.cavity_volumes_mm3()
    assert list(vols) == [*ARM_NAMES, "urethra"]
    assert [vols[n] for n in ARM_NAMES] == [514.0, 514.0, 486.0, 486.0]
    for arm in d.arms:
        r = arm.cavity_radius_mm
        assert r == arm.radius_mm - arm.wall_mm
        assert geo.capsule_volume(r, arm.cavity_cyl_length_mm) == pytest.approx(arm.cavity_volume_mm3, rel=1e-12)


def test_arm_layout_front_pair_at_minus_y_back_pair_at_plus_y():
    g = {a.name: a for a in BIPDesign().arm_geometry()}
    assert g["front_zpos"].root_mm[1] < 0 and g["front_zpos"].root_mm[2] > 0
    assert g["front_zneg"].root_mm[1] < 0 and g["front_zneg"].root_mm[2] < 0
    assert g["back_xpos"].root_mm[1] > 0 and g["back_xpos"].root_mm[0] > 0
    assert g["back_xneg"].root_mm[1] > 0 and g["back_xneg"].root_mm[0] < 0
    axes = BIPDesign().bulb.semi_axes_mm
    for a in g.values():
        assert geo.ellipsoid_level(a.root_mm, axes)[0] == pytest.approx(1.0, abs=1e-12)
        assert np.linalg.norm(a.end_mm - a.root_mm) == pytest.approx(32.0)
        assert np.allclose(a.tube_inlet_mm, a.end_mm)


def test_p_ext_on_and_off_centre():
    d = BIPDesign()
    p = d.p_ext_mm()
    np.testing.assert_allclose(p["on-centre"], [0.0, -25.0, 0.0])
    off = p["off-centre"]
    assert np.linalg.norm(off - p["on-centre"]) == pytest.approx(10.0, abs=1e-9)
    assert abs(geo.ellipsoid_signed_distance([off], d.bulb.semi_axes_mm)[0]) < 1e-9
    assert off[0] == pytest.approx(off[2]) and off[0] > 6.9  # diagonal, +x and +z
    assert off[1] < -23.0  # still on the needle side


def test_markers_and_targets():
    d = BIPDesign()
    m = np.array([v for _, v in d.markers])
    assert len(m) >= 4
    assert np.abs(geo.ellipsoid_signed_distance(m, d.bulb.semi_axes_mm)).max() < 1e-9
    assert np.linalg.svd(m - m.mean(0), compute_uv=False)[-1] > 5.0  # far from coplanar
    t = d.target_dict
    assert (geo.ellipsoid_signed_distance(np.array(list(t.values())), d.bulb.semi_axes_mm) < 0).all()
    ua, ub = d.urethra.segment_mm
    gap = geo.segment_distance([t["near_urethra"]], ua, ub)[0] - d.urethra.radius_mm
    assert gap == pytest.approx(3.0)
    assert abs(geo.ellipsoid_signed_distance([d.urethra.inlet_mm], d.bulb.semi_axes_mm)[0]) < 1e-9


def test_signed_distance_matches_a_sphere_and_a_brute_force_ellipsoid():
    rng = np.random.default_rng(0)
    p = rng.uniform(-40, 40, size=(200, 3))
    np.testing.assert_allclose(geo.ellipsoid_signed_distance(p, (20, 20, 20)), np.linalg.norm(p, axis=1) - 20, atol=1e-7)
    axes = (32.0, 25.0, 30.0)
    th, ph = np.meshgrid(np.linspace(0, np.pi, 500), np.linspace(0, 2 * np.pi, 1000))
    surf = np.stack([axes[0] * np.sin(th) * np.cos(ph), axes[1] * np.sin(th) * np.sin(ph), axes[2] * np.cos(th)], -1).reshape(-1, 3)
    q = rng.uniform(-45, 45, size=(300, 3))
    brute, _ = cKDTree(surf).query(q)
    np.testing.assert_allclose(np.abs(geo.ellipsoid_signed_distance(q, axes)), brute, atol=0.05)


def test_signed_distance_along_surface_normals_and_at_the_centre():
    """A point h along the outward normal of a surface point is h away (inside too, for h below the
    smallest radius of curvature); the centre is the smallest semi-axis deep (1e-8 mm: nudged 1e-9 mm off it)."""
    rng = np.random.default_rng(1)
    for axes in [(32.0, 25.0, 29.96), (10.0, 8.0, 4.0), (50.0, 2.0, 2.0)]:
        a = np.asarray(axes)
        u = rng.normal(size=(300, 3))
        x0 = a * u / np.linalg.norm(u, axis=1)[:, None]
        n = x0 / a**2
        n /= np.linalg.norm(n, axis=1)[:, None]
        h = rng.uniform(0.0, 10.0, 300)
        np.testing.assert_allclose(geo.ellipsoid_signed_distance(x0 + h[:, None] * n, a), h, atol=1e-9)
        h_in = rng.uniform(0.0, 0.99, 300) * a.min() ** 2 / a.max()
        np.testing.assert_allclose(geo.ellipsoid_signed_distance(x0 - h_in[:, None] * n, a), -h_in, atol=1e-9)
        assert geo.ellipsoid_signed_distance([0.0, 0.0, 0.0], a)[0] == pytest.approx(-a.min(), abs=1e-8)


def _arm(d: BIPDesign, name: str, **kw) -> BIPDesign:
    arms = tuple(dataclasses.replace(a, **kw) if a.name == name else a for a in d.arms)
    return dataclasses.replace(d, arms=arms)


D = BIPDesign()
INVALID = {
    "negative semi-axis": (lambda: design_from_dict({"bulb": {"semi_axes_mm": [32, 0, 30]}}), "bulb.semi_axes_mm[1]"),
    "negative urethra radius": (lambda: UrethraParams(radius_mm=-1.0), "urethra.radius_mm"),
    "negative arm length": (lambda: _arm(D, "back_xneg", length_mm=-3.0), "arms.back_xneg.length_mm"),
    "zero cavity volume": (lambda: _arm(D, "front_zpos", cavity_volume_mm3=0.0), "arms.front_zpos.cavity_volume_mm3"),
    "thin arm wall": (lambda: _arm(D, "front_zpos", wall_mm=0.6), "minimum wall of 1 mm"),
    "urethra cuts the surface": (
        lambda: D.with_urethra(dataclasses.replace(D.urethra, center_mm=(0.0, 0.0, 24.0))),
        "urethra: wall to the bulb surface",
    ),
    "urethra too long": (
        lambda: D.with_urethra(dataclasses.replace(D.urethra, volume_mm3=4000.0)),
        "urethra: wall to the bulb surface",
    ),
    "arm cavity cuts the bulb": (lambda: _arm(D, "back_xpos", cavity_offset_mm=4.0), r"the cavity cuts 3\.\d+ mm into the bulb \(min wall 1 mm\)"),
    "arm cavity near the bulb": (lambda: _arm(D, "back_xpos", cavity_offset_mm=8.0), r"the cavity comes 0\.\d+ mm from the bulb \(min wall 1 mm\)"),
    "arm cavity cuts the end face": (lambda: _arm(D, "back_xpos", cavity_offset_mm=26.0), "from the fixed end face"),
    "arm's axis point outside the bulb": (
        lambda: _arm(D, "front_zpos", axis_point_mm=(0.0, 0.0, 60.0), direction=(1.0, 0.0, 0.0)),
        r"arms.front_zpos.axis_point_mm = \[0, 0, 60\] is outside the body \(30.04 mm from it\)",
    ),
    "arm grazes the bulb": (
        lambda: _arm(D, "front_zpos", axis_point_mm=(0.0, 0.0, 29.0), direction=(1.0, 0.0, 0.0)),
        "arms.front_zpos: the arm misses the bulb",
    ),
    "arm into the urethra": (lambda: _arm(D, "front_zneg", embed_mm=22.0), "from the urethra cavity"),
    "arms overlap": (lambda: _arm(D, "front_zneg", direction=(0.0, -0.6, 0.9)), "overlap"),
    "marker off the surface": (
        lambda: dataclasses.replace(D, markers=(*D.markers[:-1], ("m5", (0.0, 30.0, 0.0)))),
        "markers.m5 is 5 mm off the bulb surface (tolerance 0.1 mm; snap_to_surface = true moves it onto the surface)",
    ),
    "too few markers": (lambda: dataclasses.replace(D, markers=D.markers[:3]), "markers: 3 given (min 4"),
    "coplanar markers": (
        lambda: dataclasses.replace(
            D, markers=tuple((f"k{i}", (32 * math.cos(t), 25 * math.sin(t), 0.0)) for i, t in enumerate((-0.3, -1.2, -2.0, -2.8)))
        ),
        "markers are coplanar",
    ),
    "target outside": (lambda: dataclasses.replace(D, targets=(("t", (0.0, 0.0, 31.0)),)), "targets.t is outside the bulb"),
    "target in the urethra": (lambda: dataclasses.replace(D, targets=(("t", (0.0, 5.0, 4.0)),)), "targets.t is inside the urethra"),
    "off-centre too far": (lambda: design_from_dict({"interaction": {"offcentre_mm": 80}}), "interaction.offcentre_mm"),
    "unknown key": (lambda: design_from_dict({"arms": {"front_zpos": {"lenght_mm": 3}}}), "unknown key 'lenght_mm'"),
    "name inside a named table": (
        lambda: design_from_dict({"layers": {"lesions": {"L1": {"name": "x", "center_mm": [14, 0, -10], "semi_axes_mm": [6, 6, 6]}}}}),
        "layers.lesions.L1: unknown key 'name' (known: center_mm, semi_axes_mm)",
    ),
    "volume's unit": (lambda: _arm(D, "front_zpos", cavity_volume_mm3=-1.0), "arms.front_zpos.cavity_volume_mm3 = -1 must be > 0 mm³"),
    "wrong type": (lambda: design_from_dict({"urethra": {"radius_mm": "big"}}), "urethra.radius_mm: expected a number"),
    "bad mesh size": (lambda: MeshParams(size_mm=0.0), "mesh.size_mm"),
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_designs_give_one_line_errors(case):
    make, expected = INVALID[case]
    with pytest.raises(DesignError) as err:
        make()
    msg = str(err.value)
    assert expected in msg or re.search(expected, msg), msg
    assert "\n" not in msg


def _bounded_fields():
    """(file path to a table, field) of every scalar field with a range (a bound or softphantom.schema.between)."""
    from softphantom.design.fabrication import MoldParams
    from softphantom.design.params import ArmParams, InteractionParams, LayersParams, SensorParams

    tables = {"mesh": MeshParams, "sensors": SensorParams, "molds": MoldParams, "interaction": InteractionParams,
              "urethra": UrethraParams, "layers": LayersParams, "arms.front_zpos": ArmParams}
    return [(t, n) for t, cls in tables.items() for n, f in cls.__pydantic_fields__.items()
            if f.annotation is float and len(f.metadata) > 1]


@pytest.mark.parametrize("table, key", _bounded_fields())
def test_every_bounded_field_names_itself_its_value_and_its_range(table, key):
    data: dict = {key: -1e6}
    for part in reversed(table.split(".")):
        data = {part: data}
    with pytest.raises(DesignError) as err:
        design_from_dict(data)
    unit = {"mm": " mm", "mm3": " mm³", "deg": " deg"}.get(key.rsplit("_", 1)[-1], " facets" if key == "segments" else "")
    assert re.fullmatch(rf"{re.escape(table)}\.{key} = -1e\+06 must be (> 0|>= 0|in \[[0-9.]+, [0-9.]+\]){unit}",
                        str(err.value)), str(err.value)


def test_toml_and_json_round_trip_exactly(tmp_path):
    d = _arm(BIPDesign(name="variant \"A\""), "back_xpos", length_mm=30.5, radius_mm=6.5)
    d = dataclasses.replace(d, markers=(("marker 1", d.markers[0][1]), *d.markers[1:]), targets=(("t.x", (1e-7, 0.1, -12.0)),))
    for suffix in (".toml", ".json"):
        path = save_design(d, tmp_path / f"d{suffix}")
        assert load_design(path) == d
    assert json.loads((tmp_path / "d.json").read_text())["arms"]["back_xpos"]["radius_mm"] == 6.5


BASE = design_to_dict(BIPDesign())
_names = st.text(min_size=1, max_size=12)  # any Unicode but surrogates: quotes, control characters, DEL
_bare = st.from_regex(r"[A-Za-z0-9_-]{1,12}", fullmatch=True)
_finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def valid_designs(draw) -> BIPDesign:
    """Designs near the default with free names and extreme-but-finite material numbers; drawn
    values that make an unbuildable design are rejected (a few percent)."""
    data = copy.deepcopy(BASE)
    data["name"] = draw(_names)
    for arm in data["arms"].values():
        arm["length_mm"] = draw(st.floats(30.0, 36.0))
        arm["radius_mm"] = draw(st.floats(5.8, 6.2))
        arm["wall_mm"] = draw(st.floats(2.2, 2.8))
        arm["junction_fillet_mm"] = draw(st.sampled_from([0.0, 2.0]))
    data["urethra"]["radius_mm"] = draw(st.floats(4.0, 5.0))
    data["mesh"].update(size_mm=draw(st.floats(1.0, 20.0)), cavity_segments=draw(st.floats(6.0, 256.0)),
                        element_order=draw(st.sampled_from([1, 2])))
    data["sensors"] = {"gains": draw(st.lists(st.floats(0.5, 2.0), min_size=4, max_size=4)),
                       "tube_volume_factor": draw(st.floats(0.2, 5.0))}
    names = draw(st.lists(_names, min_size=5, max_size=5, unique=True))
    data["markers"] = dict(zip(names, data["markers"].values()))
    tnames = draw(st.lists(_names, min_size=0, max_size=4, unique=True))
    data["targets"] = dict(zip(tnames, data["targets"].values()))
    mat = draw(_bare.filter(lambda n: n != "ecoflex_00_50"))
    data["materials"][mat] = {"law": draw(_names), **draw(st.dictionaries(_names.filter(lambda k: k != "law"), _finite,
                                                                           max_size=4))}
    data["region_materials"]["arm_back_xpos"] = mat
    if draw(st.booleans()):
        shell = draw(st.sampled_from([0.0, 1.5]))
        data["layers"] = {"shell_mm": shell,
                          "lesions": {draw(_bare): {"center_mm": [14.0, 0.0, -10.0], "semi_axes_mm": [6.0, 6.0, 6.0]}}}
        data["region_materials"].update({"lesions": mat, **({"shell": "ecoflex_00_50"} if shell else {})})
    try:
        return design_from_dict(data)
    except DesignError:
        assume(False)


@settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(valid_designs())
def test_design_file_round_trips_any_valid_design(d):
    assert design_from_dict(tomllib.loads(design_to_toml(d))) == d


def test_a_changed_value_is_a_one_line_diff():
    before = design_to_toml(D).splitlines()
    after = design_to_toml(_arm(D, "back_xpos", direction=(1.0, 0.7, 0.0))).splitlines()
    changed = [x for x in difflib.unified_diff(before, after, lineterm="", n=0)
               if x[:1] in "+-" and not x.startswith(("+++", "---"))]
    assert changed == ["-    0.6,", "+    0.7,"]


OLD_FILES = Path(__file__).parent / "fixtures" / "design_files"


@pytest.mark.parametrize("name", ["old_default", "old_layers_names", "old_surface"])
def test_files_of_the_earlier_writer_still_read(name):
    """Written by the hand-made TOML writer (inline vectors); their JSON twins hold the same design."""
    toml = OLD_FILES / f"{name}.toml"
    assert "_mm = [" in toml.read_text() and load_design(toml) == load_design(OLD_FILES / f"{name}.json")
    if name == "old_default":
        assert load_design(toml) == BIPDesign()


def test_partial_toml_overrides_the_defaults(tmp_path):
    p = tmp_path / "partial.toml"
    p.write_text('name = "short-arms"\n[arms.front_zpos]\nlength_mm = 28.0\n[mesh]\nsize_mm = 8.0\n')
    d = load_design(p)
    assert d.name == "short-arms" and d.arms[0].length_mm == 28.0 and d.mesh.size_mm == 8.0
    assert d.arms[1] == BIPDesign().arms[1] and d.bulb == BIPDesign().bulb
    assert design_from_dict(design_to_dict(d)) == d


def test_bad_files_are_design_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[bulb\nsemi_axes_mm = 3")
    with pytest.raises(DesignError, match="not valid TOML"):
        load_design(bad)
    with pytest.raises(DesignError, match="cannot read"):
        load_design(tmp_path / "missing.toml")


def test_packaged_default_toml_is_the_default_design():
    from importlib.resources import files

    path = files("softphantom") / "data" / "bip_default.toml"
    assert load_design(path) == BIPDesign()
