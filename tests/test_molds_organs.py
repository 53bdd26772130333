"""softphantom molds on the example organs (examples/organs/): the kidney's bent superellipsoid with a
capsule collecting system, the liver's boxy superellipsoid with two ellipsoid balloons.

Each internal cavity gets a core on its rod; the cores, molds and cast pieces are checked as in
tests/test_molds.py (closed, manifold, not self-intersecting, no interference) and against shapes
built independently with trimesh primitives, compared by manifold3d booleans (volumes in mm³).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("manifold3d")

from softphantom.design import geometry as geo  # noqa: E402
from softphantom.design.params import design_from_dict  # noqa: E402
from softphantom.design.solid_check import from_manifold, to_manifold  # noqa: E402
from softphantom.errors import DesignError  # noqa: E402
from softphantom.molds import build_parts, check_parts, interference  # noqa: E402
from softphantom.molds.parts import _Builder, rod_start_mm  # noqa: E402

ORGANS = Path(__file__).parents[1] / "examples" / "organs"
SEGMENTS = 24.0  # coarse facets: the volume checks below allow for their (2π/24)²/6 ≈ 1.1 % deficit
CORES = {"kidney": ("collecting_system",), "liver": ("tumour", "breathing")}


def organ_dict(organ: str, **extra) -> dict:
    data = tomllib.loads((ORGANS / f"{organ}.toml").read_text(encoding="utf-8"))
    data["molds"] = {"segments": SEGMENTS}
    return {**data, **extra}


def organ(name: str, **extra):
    return design_from_dict(organ_dict(name, **extra))


@pytest.fixture(scope="module", params=["kidney", "liver"])
def bulb_group(request):
    d = organ(request.param)
    parts = {p.name: p for p in build_parts(d, bulb_only=True)}
    return request.param, d, parts


def _vol(solid) -> float:
    return float(solid.volume())


def _reference(c):
    """The cavity's shape from trimesh primitives (not the molds' OCC code)."""
    if c.shape == "ellipsoid":
        e = trimesh.creation.icosphere(subdivisions=6)
        e.apply_scale(np.asarray(c.semi_axes_mm, float))
        return e.apply_translation(c.center_mm)
    a, b = (np.asarray(p, float) for p in c.segment_mm)
    cap = trimesh.creation.capsule(height=float(np.linalg.norm(b - a)), radius=c.radius_mm, count=[96, 96])
    T = trimesh.geometry.align_vectors([0, 0, 1], b - a)
    T[:3, 3] = 0.5 * (a + b)
    return cap.apply_transform(T)


def _rod_in_body_mm3(d, c) -> float:
    """The rod's channel between its cavity's wall and the inlet (bisection on the cavity's wall)."""
    start = rod_start_mm(c)
    inlet = np.asarray(c.inlet_mm, float)
    u = geo.unit(inlet - start)
    lo, hi = 0.0, float(np.linalg.norm(inlet - start))
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if c.signed_distance([start + mid * u])[0] < 0.0 else (lo, mid)
    return math.pi * d.molds.core_rod_radius_mm**2 * (float(np.linalg.norm(inlet - start)) - lo)


def test_each_internal_cavity_has_its_core_and_the_bulb_group_is_clean(bulb_group):
    name, d, parts = bulb_group
    assert d.internal_cavity_names == CORES[name]
    assert list(parts) == ["bulb_mold_lower", "bulb_mold_upper", *(f"{c}_core" for c in CORES[name]),
                           *(f"marker_socket_{m}" for m, _ in d.markers)]
    reports = check_parts(parts.values())
    for n, r in reports.items():
        assert r.watertight and r.winding_consistent and r.manifold, n
        assert r.self_intersections == 0 and r.components == 1 and r.volume > 0, n
    pairs = interference(list(parts.values()))
    assert len(pairs) == math.comb(len(parts), 2)
    for a, b, v in pairs:  # printed parts with a clearance between them (cores and halves, sockets)
        assert v < 0.05, (a, b, v)


def test_a_core_sits_where_its_cavity_is_held_by_a_rod_out_through_its_inlet(bulb_group):
    name, d, parts = bulb_group
    halves = np.vstack([parts[h].mesh.vertices for h in ("bulb_mold_lower", "bulb_mold_upper")])
    for cname in CORES[name]:
        c, core = d.cavity(cname), parts[f"{cname}_core"]
        ref = _reference(c)
        v_design = c.volume_mm3
        assert ref.volume == pytest.approx(v_design, rel=2e-3)  # the reference itself
        inside = to_manifold(core.mesh) ^ to_manifold(ref)
        assert abs(_vol(inside) - v_design) / v_design < 0.02, cname
        assert _vol(to_manifold(ref) - to_manifold(core.mesh)) / v_design < 0.02, cname  # nothing left unfilled
        centre = from_manifold(inside).center_mass  # the core within its cavity: centred on it
        assert np.linalg.norm(centre - np.asarray(c.center_mm)) < 0.05, (cname, centre)
        # the rod: whole at the inlet, and out beyond the mold
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5).apply_translation(c.inlet_mm)
        assert _vol(to_manifold(core.mesh) ^ to_manifold(ball)) == pytest.approx(ball.volume, rel=1e-6), cname
        u = geo.unit(np.asarray(c.inlet_mm, float) - rod_start_mm(c))
        assert (core.mesh.vertices @ u).max() > (halves @ u).max() + 5.0, cname
        # the whole core: its cavity, the rod from the cavity's wall to the inlet and on out
        assert core.mesh.volume == pytest.approx(
            v_design + _rod_in_body_mm3(d, c) + math.pi * d.molds.core_rod_radius_mm**2
            * ((core.mesh.vertices @ u).max() - float(np.asarray(c.inlet_mm) @ u)), rel=0.02), cname


def test_the_cast_body_has_a_void_at_each_cavity_and_a_channel_to_its_inlet(bulb_group):
    name, d, _ = bulb_group
    cast = _Builder(d).cast_bulb()
    m = cast.mesh
    assert m.is_watertight and m.is_winding_consistent
    body = geo.surface_enclosed_volume(np.asarray(d.bulb.surface_vertices_mm), np.asarray(d.bulb.surface_faces))
    assert body == pytest.approx(d.bulb.volume_mm3, rel=3e-3)  # the body's triangles against Barr's closed form
    ms = d.molds
    sockets = len(d.markers) * math.pi * ms.marker_socket_radius_mm**2 * ms.marker_socket_depth_mm
    cavities = sum(d.cavity(c).volume_mm3 + _rod_in_body_mm3(d, d.cavity(c)) for c in CORES[name])
    expect = body - cavities - sockets
    # the tools' facets (≈ 1.1 % of each at 24 segments) and the rods' ends on curved walls
    assert abs(m.volume - expect) < 0.02 * (cavities + sockets), (m.volume, expect)
    for cname in CORES[name]:
        c = d.cavity(cname)
        # only the band between the void's facets and the true wall: twice an inscribed polygon's deficit
        overlap = _vol(to_manifold(m) ^ to_manifold(_reference(c))) / c.volume_mm3
        assert overlap < 2 * (2 * math.pi / SEGMENTS) ** 2 / 6, (cname, overlap)


def test_a_lesion_in_a_superellipsoid_is_an_ellipsoid():
    """The lesion's mold and cast piece are its ellipsoid (not the body's exponents and bend), and
    the infill cast of a superellipsoid body is the body less its cores and lesions."""
    lesion = {"center_mm": [-14.0, 0.0, 20.0], "semi_axes_mm": [6.0, 5.0, 4.0]}
    materials = {"bulb": "ecoflex_00_50", "arms": "ecoflex_00_50", "lesions": "sorta_clear_12"}
    d = organ("kidney", layers={"lesions": {"L1": lesion}}, region_materials=materials)
    b = _Builder(d)
    pieces = {p.name: p for p in b.cast_layers()}
    assert list(pieces) == ["cast_infill", "cast_lesion_L1"]
    v_les = geo.ellipsoid_volume(lesion["semi_axes_mm"])
    les = pieces["cast_lesion_L1"].mesh
    assert 0.0 < (v_les - les.volume) / v_les < 2 * (2 * math.pi / SEGMENTS) ** 2 / 6.0
    ref = trimesh.creation.icosphere(subdivisions=6).apply_scale(lesion["semi_axes_mm"]).apply_translation(
        lesion["center_mm"])
    assert _vol(to_manifold(ref) - to_manifold(les)) / v_les < 0.02  # where and what shape it is
    c = d.cavity("collecting_system")
    body = geo.surface_enclosed_volume(np.asarray(d.bulb.surface_vertices_mm), np.asarray(d.bulb.surface_faces))
    infill = pieces["cast_infill"].mesh
    tools = c.volume_mm3 + _rod_in_body_mm3(d, c) + les.volume
    assert abs(infill.volume - (body - tools)) < 0.02 * tools
    half = b.lesion_half(d.layers.lesions[0], upper=False)
    assert check_parts([half])[half.name].ok


def test_a_shell_on_a_superellipsoid_is_refused_naming_the_body():
    with pytest.raises(DesignError, match=r"^layers.shell_mm = 2: a shell needs an ellipsoid bulb \(a superellipsoid "
                                          r"has no inner offset yet; use 0\)$"):
        organ("liver", layers={"shell_mm": 2.0})


def test_a_rod_through_another_cavity_is_refused_in_one_line():
    data = organ_dict("liver")
    # the tumour's inlet moved to the top face straight above it: its rod would cross the balloon
    s = organ("liver").bulb.ray_exit((0.0, -2.0, -8.0), (0.0, 0.0, 1.0))
    data["cavities"]["tumour"]["inlet_mm"] = [0.0, -2.0, -8.0 + s]
    d = design_from_dict(data)
    with pytest.raises(DesignError, match=r"^cavities.tumour.inlet_mm: the molds' rod from the tumour core to its "
                                          r"inlet .* cuts into the breathing cavity .*move the inlet\)$"):
        build_parts(d, bulb_only=True)


def test_no_internal_cavity_no_core():
    d = design_from_dict({"cavities": {}, "molds": {"segments": SEGMENTS}})
    parts = build_parts(d, bulb_only=True)
    assert [p.name for p in parts] == ["bulb_mold_lower", "bulb_mold_upper",
                                       *(f"marker_socket_{m}" for m, _ in d.markers)]
    lo, up = parts[0].mesh.bounds, parts[1].mesh.bounds  # parted at z = 0 (the lower half's pins above it)
    assert up[0][2] == pytest.approx(0.0, abs=1e-9) and lo[1][2] == pytest.approx(d.molds.key_height_mm, abs=1e-9)
