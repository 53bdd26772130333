"""softphantom molds: printable parts of the default design, checked against independent solids.

The parts come from gmsh's OpenCASCADE kernel; the references here are built independently with
trimesh primitives and compared by manifold3d booleans (volumes in mm³).
"""

from __future__ import annotations

import csv
import dataclasses
import math

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
m3 = pytest.importorskip("manifold3d")

from softphantom.cli import main  # noqa: E402
from softphantom.design import BIPDesign, design_from_dict, design_to_dict, save_design  # noqa: E402
from softphantom.design import geometry as geo  # noqa: E402
from softphantom.design.fabrication import BUILD_VOLUME_MM, MoldParams  # noqa: E402
from softphantom.errors import DesignError  # noqa: E402
from softphantom.molds import build_parts, interference, write_molds  # noqa: E402
from softphantom.design.solid_check import to_manifold  # noqa: E402


# facets per circle of the built parts: two thirds of the default's (48), a third fewer triangles;
# the volume checks below hold with room (the cavities within 0.4 %, the cores within 0.8 %) and the
# contacts' sagitta overlaps stay under their 1e-3 bound.
SEGMENTS = 32.0


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    design = dataclasses.replace(BIPDesign(), molds=MoldParams(segments=SEGMENTS))
    parts = build_parts(design)
    out = tmp_path_factory.mktemp("molds")
    result = write_molds(parts, out)
    from softphantom.viz.molds_view import render_assembly_png

    render_assembly_png(parts, out / "assembly.png")
    return design, {p.name: p for p in parts}, result, out


def _ellipsoid(axes, grow=0.0):
    e = trimesh.creation.icosphere(subdivisions=6)
    e.apply_scale(np.asarray(axes) + grow)
    return e


def _capsule_between(a, b, r):
    a, b = np.asarray(a, float), np.asarray(b, float)
    cap = trimesh.creation.capsule(height=float(np.linalg.norm(b - a)), radius=r, count=[96, 96])
    T = trimesh.geometry.align_vectors([0, 0, 1], b - a)
    T[:3, 3] = 0.5 * (a + b)
    return cap.apply_transform(T)


def _cylinder_between(a, b, r):
    return trimesh.creation.cylinder(radius=r, segment=[a, b], sections=256)


def _vol(solid) -> float:
    return float(solid.volume())


def _mold_cavity(halves, envelope):
    """The space the closed mold leaves inside its outer hull, clipped to ``envelope``."""
    hull = to_manifold(trimesh.util.concatenate([h.mesh for h in halves]).convex_hull)
    cavity = hull
    for h in halves:
        cavity = cavity - to_manifold(h.mesh)
    return cavity ^ to_manifold(envelope)


@pytest.mark.slow
def test_every_part_is_a_closed_manifold_solid_without_self_intersection(built):
    _, parts, result, _ = built
    assert len(parts) == 34  # 2 halves, core, 5 sockets, cast bulb, 4 × (2 + core + 2 + cast arm), frame
    for name, p in parts.items():
        r = result.reports[name]
        assert r.watertight and r.winding_consistent and r.manifold, name
        assert r.self_intersections == 0 and r.components == 1 and r.volume > 0, name
        # write_molds checked this very mesh (report_mesh, the slowest check: once is enough)
        assert r.ok and r.problem() is None and r.volume == pytest.approx(p.mesh.volume), name


@pytest.mark.slow
def test_bulb_mold_cavity_equals_the_design_bulb_within_1_percent(built):
    design, parts, _, _ = built
    axes = design.bulb.semi_axes_mm
    halves = [parts["bulb_mold_lower"], parts["bulb_mold_upper"]]
    # clip 1 mm outside the bulb: spout, vents and holes leave only short stubs
    cavity = _mold_cavity(halves, _ellipsoid(axes, grow=1.0))
    v_design = geo.ellipsoid_volume(axes)
    assert v_design == pytest.approx(100_410.0)
    assert abs(_vol(cavity) - v_design) / v_design < 0.01
    # and no mold material inside the bulb
    intruding = to_manifold(_ellipsoid(axes)) - cavity
    assert _vol(intruding) / v_design < 0.01


@pytest.mark.slow
@pytest.mark.parametrize("arm", ["front_zpos", "back_xneg"])
def test_arm_mold_cavity_equals_the_design_arm_within_1_percent(built, arm):
    design, parts, _, _ = built
    g = next(x for x in design.arm_geometry() if x.name == arm)
    solid = to_manifold(_cylinder_between(g.start_mm, g.end_mm, g.radius_mm)) - to_manifold(
        _ellipsoid(design.bulb.semi_axes_mm))
    envelope = _cylinder_between(g.start_mm, g.end_mm, g.radius_mm + 0.5)
    cavity = _mold_cavity([parts[f"arm_mold_{arm}_a"], parts[f"arm_mold_{arm}_b"]], envelope)
    assert abs(_vol(cavity) - _vol(solid)) / _vol(solid) < 0.01
    assert _vol(solid - cavity) / _vol(solid) < 0.01


@pytest.mark.slow
def test_each_core_fills_its_design_cavity_within_2_percent(built):
    design, parts, _, _ = built
    u = design.urethra
    cases = [("urethra_core", _capsule_between(*u.segment_mm, u.radius_mm), u.volume_mm3)]
    for g in design.arm_geometry():
        cases.append((f"arm_core_{g.name}", _capsule_between(*g.cavity_segment_mm, g.cavity_radius_mm),
                      g.cavity_volume_mm3))
    for name, cap, v_design in cases:
        assert cap.volume == pytest.approx(v_design, rel=2e-3)  # the reference itself
        core, ref = to_manifold(parts[name].mesh), to_manifold(cap)
        inside = _vol(core ^ ref)
        assert abs(inside - v_design) / v_design < 0.02, name
        assert _vol(ref - core) / v_design < 0.02, name  # the core leaves no part of the cavity unfilled


@pytest.mark.slow
def test_assembled_parts_do_not_interfere(built):
    _, parts, _, _ = built
    pairs = interference(list(parts.values()))
    assert len(pairs) > 40
    for a, b, v in pairs:
        pa, pb = parts[a], parts[b]
        if "cast" in (pa.kind, pb.kind) or {pa.kind, pb.kind} == {"mold", "core"} and pa.group.startswith("core_"):
            # surfaces in contact by design (a cast piece in its mold, a core in its mold, the
            # arms on the bulb): only the facets' sagitta overlaps
            assert v <= 1e-3 * min(pa.volume_mm3, pb.volume_mm3), (a, b, v)
        else:  # printed parts with a clearance between them
            assert v < 0.05, (a, b, v)


@pytest.mark.slow
def test_parts_fit_the_build_volume_and_files_read_back(built):
    _, parts, result, out = built
    assert result.printed and all(r["fits_build_volume"] for r in result.printed)
    assert BUILD_VOLUME_MM == (220.0, 220.0, 250.0)
    for row in result.printed:
        stl = trimesh.load(out / "parts" / f"{row['part']}.stl")
        assert stl.is_watertight
        assert stl.volume == pytest.approx(parts[row["part"]].volume_mm3, rel=1e-4)
        assert np.all(stl.bounds[0] > -1e-6)  # print pose: on the plate, at the origin
        assert (out / "parts" / f"{row['part']}.3mf").stat().st_size > 0
    assert (out / "assembly.png").stat().st_size > 20_000
    assert len(list((out / "cast").glob("*.stl"))) == 5


@pytest.mark.slow
def test_bom_volumes_and_masses(built):
    design, parts, result, out = built
    rows = {r["part"]: r for r in csv.DictReader((out / "bom.csv").open())}
    assert set(rows) == {"cast_bulb", *(f"cast_arm_{a}" for a in ("front_zpos", "front_zneg", "back_xpos",
                                                                 "back_xneg")),
                         *(f"arm_core_{a}" for a in ("front_zpos", "front_zneg", "back_xpos", "back_xneg"))}
    # the cast bulb: the ellipsoid less the urethra, the rod channel in the bulb and the socket posts
    u, ms = design.urethra, design.molds
    rod_in = np.linalg.norm(np.asarray(u.inlet_mm) - u.segment_mm[1]) - math.sqrt(u.radius_mm**2 - ms.core_rod_radius_mm**2)
    expect = (geo.ellipsoid_volume(design.bulb.semi_axes_mm) - u.volume_mm3 - math.pi * ms.core_rod_radius_mm**2 * rod_in
              - len(design.markers) * math.pi * ms.marker_socket_radius_mm**2 * ms.marker_socket_depth_mm)
    assert float(rows["cast_bulb"]["volume_mL"]) * 1000 == pytest.approx(expect, rel=5e-3)
    assert float(rows["cast_bulb"]["mass_g"]) == pytest.approx(float(rows["cast_bulb"]["volume_mL"]) * 1.07, rel=1e-3)
    assert rows["arm_core_front_zpos"]["material"] == "Dragon Skin 30"
    md = (out / "bom.md").read_text()
    assert "Ecoflex 00-50" in md and "| frame |" in md


def test_molds_table_is_validated_and_round_trips():
    d = dataclasses.replace(BIPDesign(), molds=MoldParams(wall_mm=8.0, clearance_mm=0.2))
    assert design_from_dict(design_to_dict(d)) == d
    with pytest.raises(DesignError, match=r"molds.draft_deg = 20 must be in \[0, 10\] deg"):
        design_from_dict({"molds": {"draft_deg": 20}})
    with pytest.raises(DesignError, match="molds.wall_mm = 3 is too thin for keys"):
        design_from_dict({"molds": {"wall_mm": 3.0}})
    with pytest.raises(DesignError, match="molds: unknown key 'wal_mm'"):
        design_from_dict({"molds": {"wal_mm": 3.0}})


def test_cli_molds_bad_input_is_one_line_exit_2(tmp_path, capsys):
    assert main(["molds", "--model", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "design.toml: no such file" in capsys.readouterr().err
    save_design(BIPDesign(), tmp_path / "design.toml")
    text = (tmp_path / "design.toml").read_text().replace("clearance_mm = 0.3", "clearance_mm = -1.0")
    (tmp_path / "design.toml").write_text(text)
    assert main(["molds", "--model", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "molds.clearance_mm = -1 must be in [0, 2] mm" in err and "Traceback" not in err


def test_cli_molds_out_follows_the_staged_output_policy(tmp_path, capsys, monkeypatch):
    """An existing, non-empty --out is refused before any part is built (exit 2, its contents
    kept); an error while building leaves no output and no staging directory behind."""
    import softphantom.molds

    model = tmp_path / "model"
    model.mkdir()
    save_design(BIPDesign(), model / "design.toml")
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["molds", "--model", str(model), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "exists and is not empty" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert (out / "keep.txt").read_text() == "mine"

    def fails(design, bulb_only=False):
        raise DesignError("molds.wall_mm = 6: no room for the registration keys beside the bulb (raise wall_mm)")

    monkeypatch.setattr(softphantom.molds, "build_parts", fails)
    for target, flags in ((tmp_path / "fresh", []), (out, ["--overwrite"])):
        assert main(["molds", "--model", str(model), "--out", str(target), "--no-png", *flags]) == 2
        assert "no room for the registration keys" in capsys.readouterr().err
    assert not (tmp_path / "fresh").exists() and (out / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "o"]  # no staging directory left


@pytest.mark.slow
def test_the_frame_tessellates_at_facet_counts_gmsh_once_failed_on(monkeypatch):
    """The frame at segments 24 (its beams' end faces once lay on the posts' tangent planes, a face
    gmsh could not mesh at 24, 36 and 64; all of 16–128 by hand, docs/fabrication.md): a clean
    closed solid whose volume is below the exact OCC solid's by less than an inscribed polygon's
    area deficit, (2π/n)²/6."""
    import softphantom.molds.parts as parts_mod
    from softphantom.design.mesh import gmsh_session
    from softphantom.design.solid_check import report_mesh

    builds = {}

    def recording(name, build, segments):
        builds[name] = build
        return occ_solid(name, build, segments)

    occ_solid = parts_mod.occ_solid
    monkeypatch.setattr(parts_mod, "occ_solid", recording)
    for n in (24,):
        frame = parts_mod._Builder(dataclasses.replace(BIPDesign(), molds=MoldParams(segments=float(n)))).frame()
        assert report_mesh(frame.mesh).problem() is None
        with gmsh_session("frame_exact", "the exact frame") as gmsh:
            exact = gmsh.model.occ.getMass(3, builds["frame"](gmsh.model.occ))
        assert 0.0 < (exact - frame.mesh.volume) / exact < (2.0 * math.pi / n) ** 2 / 6.0


def test_a_part_gmsh_cannot_tessellate_is_one_line_naming_the_setting(tmp_path, capsys, monkeypatch):
    """A gmsh meshing failure names the part and the [molds] segments value, exit 2, no traceback."""
    import gmsh

    def fails(dim=3):
        raise Exception("Impossible to mesh periodic surface 63\nmore detail")

    save_design(dataclasses.replace(BIPDesign(), molds=MoldParams(segments=24.0)), tmp_path / "design.toml")
    monkeypatch.setattr(gmsh.model.mesh, "generate", fails)
    assert main(["molds", "--model", str(tmp_path), "--out", str(tmp_path / "o"), "--no-png"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert ("[molds] segments = 24: gmsh could not tessellate part 'bulb_mold_lower' "
            "(Impossible to mesh periodic surface 63)") in err
    assert not (tmp_path / "o").exists()


def test_surfaces_flipped_at_random_are_made_consistent():
    """consistent_surfaces on an icosphere cut into patches, some patches' triangles reversed: the
    result is winding-consistent (every edge used once each way) with each patch whole."""
    import trimesh

    from softphantom.molds.occ import consistent_surfaces

    sphere = trimesh.creation.icosphere(subdivisions=3)
    c = sphere.triangles_center
    patch = (c[:, 0] > 0).astype(int) * 4 + (c[:, 1] > 0) * 2 + (c[:, 2] > 0)  # 8 octant patches
    rng = np.random.default_rng(2)
    tris = [sphere.faces[patch == k][:, ::-1] if rng.uniform() < 0.5 else sphere.faces[patch == k]
            for k in range(8)]
    out = consistent_surfaces(tris)
    assert sorted(map(tuple, np.sort(out, axis=1))) == sorted(map(tuple, np.sort(sphere.faces, axis=1)))
    mesh = trimesh.Trimesh(sphere.vertices, out, process=False)
    assert mesh.is_winding_consistent and mesh.is_watertight
    assert not trimesh.Trimesh(sphere.vertices, np.vstack(tris), process=False).is_winding_consistent


def test_overlapping_boxes_are_every_overlapping_pair_once():
    """The grid's box pairs against all pairs compared: boxes of mixed sizes, flat ones, points and
    one box across everything (which coarsens the grid)."""
    from softphantom.design.solid_check import overlapping_boxes

    rng = np.random.default_rng(3)
    for trial in range(12):
        n = int(rng.integers(2, 300))
        lo = rng.uniform(0.0, 20.0, (n, 3))
        hi = lo + rng.uniform(0.0, 1.0, (n, 3)) ** 3 * [0.5, 5.0, 20.0][trial % 3]
        if trial % 4 == 0:
            hi[:, 2] = lo[:, 2]  # flat, as a facet in a plane z = const
        if trial % 4 == 1:
            hi[: n // 3] = lo[: n // 3]  # points
        if trial % 4 == 2:
            lo[0], hi[0] = -1.0, 21.0
        a, b = overlapping_boxes(lo, hi)
        got = list(zip(a.tolist(), b.tolist()))
        overlap = np.all(np.maximum(lo[:, None], lo[None]) <= np.minimum(hi[:, None], hi[None]), axis=2)
        i, j = np.nonzero(np.triu(overlap, 1))
        assert len(got) == len(set(got)) and set(got) == set(zip(i.tolist(), j.tolist())), trial


def test_self_intersections_count_every_crossing_pair():
    """Two spheres through each other in one mesh: the count is that of all face pairs without a
    shared vertex tested alike; each sphere alone, and the two apart, have none."""
    from softphantom.design.solid_check import crossing, self_intersections

    a = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    b = trimesh.creation.icosphere(subdivisions=1, radius=7.0).apply_translation((9.0, 2.0, 1.0))
    both = trimesh.util.concatenate([a, b])
    i, j = np.triu_indices(len(both.faces), 1)
    free = ~(both.faces[i][:, :, None] == both.faces[j][:, None, :]).any(axis=(1, 2))
    expect = int(crossing(both.vertices[both.faces], i[free], j[free]).sum())
    assert expect > 20 and self_intersections(both) == expect
    assert self_intersections(a) == self_intersections(b) == 0
    apart = trimesh.util.concatenate([a, b.copy().apply_translation((30.0, 0.0, 0.0))])
    assert self_intersections(apart) == 0


def test_a_solid_built_once_is_imported_whole_with_its_boolean_tolerance(tmp_path):
    """built_once: the solid of one gmsh model (a cube less an eighth of a ball at its corner) in
    another model, exactly (its volume in closed form), and the boolean tolerance its build set."""
    from softphantom.design.mesh import gmsh_session
    from softphantom.molds.occ import built_once, one_volume

    def build(occ):
        import gmsh

        gmsh.option.setNumber("Geometry.ToleranceBoolean", 1e-3)
        return one_volume(occ.cut([(3, occ.addBox(0, 0, 0, 10, 10, 10))], [(3, occ.addSphere(10, 10, 10, 4))]), "cut")

    imported = built_once("corner", build, tmp_path)
    with gmsh_session("built_once_test", "the test") as gmsh:
        assert gmsh.option.getNumber("Geometry.ToleranceBoolean") == 0.0
        vol = imported(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        assert gmsh.model.occ.getMass(3, vol) == pytest.approx(1000.0 - math.pi * 4**3 / 6, rel=1e-9)
        assert gmsh.option.getNumber("Geometry.ToleranceBoolean") == 1e-3
