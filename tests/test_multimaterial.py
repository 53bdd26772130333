"""Multi-material designs ([layers]): a shell over the infill and lesion inclusions become named
mesh regions with their own materials; their meshed volumes against the closed forms, a stiffer
shell against a one-material run, and bad input (one line, exit 2)."""

from __future__ import annotations

import dataclasses

import math

import numpy as np
import pytest
import tomli_w

from softphantom.cli import main
from softphantom.design import BIPDesign, build_model, design_from_dict, design_to_dict, load_design, save_design
from softphantom.design.params import LayersParams, LesionParams
from softphantom.errors import DesignError

SHELL_MM = 3.0  # thick enough for the test mesh (6 mm: surface elements 4 mm)
LESIONS = (LesionParams("L1", (14.0, 0.0, -10.0), (6.0, 6.0, 6.0)), LesionParams("L2", (-14.0, 0.0, -10.0), (7.0, 5.0, 5.0)))


def _design(shell=SHELL_MM, lesions=LESIONS, shell_mat="ecoflex_00_50"):
    # sharp arm junctions: the closed forms below are the ellipsoid's (with the default fillets
    # the fillet rings and arm stubs belong to the outermost region, the shell here)
    base = BIPDesign()
    base = dataclasses.replace(base, arms=tuple(dataclasses.replace(a, junction_fillet_mm=0.0) for a in base.arms))
    rm = {"bulb": "ecoflex_00_50", "arms": "ecoflex_00_50", "lesions": "ecoflex_00_50"}
    if shell:
        rm["shell"] = shell_mat
    data = design_to_dict(base)
    data["layers"] = {"shell_mm": shell, "lesions": {x.name: {"center_mm": list(x.center_mm),
                                                              "semi_axes_mm": list(x.semi_axes_mm)} for x in lesions}}
    data["region_materials"] = rm
    return design_from_dict(data)


@pytest.fixture(scope="module")
def model():
    return build_model(_design(), 6.0, isolate=False)  # in-process: a spawned mesher costs ~5 s of imports


def test_layers_round_trip_through_the_design_file(tmp_path):
    d = _design(shell=1.5)
    assert d.region_names[-3:] == ("shell", "lesion_L1", "lesion_L2")
    assert design_from_dict(design_to_dict(d)) == d
    assert load_design(save_design(d, tmp_path / "d.toml")) == d
    assert "layers" not in design_to_dict(BIPDesign())  # a one-material file stays as it was


@pytest.mark.slow
def test_region_volumes_match_the_closed_forms(model):
    a, b, c = model.design.bulb.semi_axes_mm
    shell = 4.0 / 3.0 * math.pi * (a * b * c - (a - SHELL_MM) * (b - SHELL_MM) * (c - SHELL_MM))
    assert set(model.regions) >= {"bulb", "shell", "lesion_L1", "lesion_L2"}
    # inscribed polyhedra: each surface errs low by about 1 % at these sizes, the shell by the difference
    assert model.region_volume("shell") * 1e9 == pytest.approx(shell, rel=0.03)
    n = model.design.mesh.cavity_segments  # a lesion's wall is meshed like a cavity's: low by (2π/n)²/6
    for les in LESIONS:
        expect = les.volume_mm3 * (1.0 - (2.0 * math.pi / n) ** 2 / 6.0)
        assert model.region_volume(les.region) * 1e9 == pytest.approx(expect, rel=0.02)
    assert model.bulb_volume() * 1e9 == pytest.approx(model.design.bulb.volume_mm3, rel=0.02)
    # every tet centroid of a lesion region lies in its ellipsoid, and no infill tet does
    cent = model.nodes[model.tets].mean(axis=1) * 1e3
    for les in LESIONS:
        level = np.sum(((cent - les.center_mm) / les.semi_axes_mm) ** 2, axis=1)
        assert (level[model.tet_region == model.regions[les.region]] < 1.0).all()
        assert (level[model.tet_region == model.regions["bulb"]] > 0.95).all()


@pytest.mark.slow
def test_a_stiffer_shell_makes_a_stiffer_phantom(model):
    """Same mesh, same push: a Sorta-Clear 12 shell (E ≈ 2.3× Ecoflex 00-50's) over the infill
    moves the push point less than the one-material phantom does."""
    from softphantom.fem import fem_from_phantom, force_actuator, solve_static
    from softphantom.fem.material import SORTA_CLEAR_12

    p = model.p_ext["on-centre"]

    def push(materials):
        fem = fem_from_phantom(model, materials)
        sol = solve_static(fem, force_actuator(fem, p, radius=4e-3) @ np.array([0.0, 1.0, 0.0]))
        assert sol.converged
        k = int(np.argmin(np.linalg.norm(model.nodes - p, axis=1)))
        return float(sol.x[k, 1] - model.nodes[k, 1])

    one, shelled = push(None), push({"shell": SORTA_CLEAR_12})
    assert one > 1e-4 and shelled > 0.0
    assert shelled < 0.9 * one


@pytest.mark.parametrize("lesion, message", [
    (LesionParams("out", (30.0, 0.0, 0.0), (5.0, 5.0, 5.0)), "beyond the infill's surface"),
    (LesionParams("inside", (0.0, 8.0, 4.0), (3.0, 3.0, 3.0)), "cuts the urethra cavity"),
    (LesionParams("wall", (7.0, 0.0, 4.0), (3.0, 3.0, 3.0)), "cuts the urethra cavity"),
    (LesionParams("twin", (14.0, 3.0, -10.0), (4.0, 4.0, 4.0)), "they overlap"),
])
def test_a_lesion_outside_or_cutting_a_cavity_is_refused(lesion, message):
    with pytest.raises(DesignError, match=message):
        _design(lesions=(*LESIONS, lesion))


def test_bad_layers_are_one_line_exit_2(tmp_path, capsys):
    for shell, lesions, message in (
        (1.0, LESIONS, "layers.shell_mm = 1 mm is thinner than the mesh resolves"),
        (1.5, (LesionParams("out", (30.0, 0.0, 0.0), (5.0, 5.0, 5.0)),), "layers.lesions.out.center_mm"),
    ):
        path = tmp_path / "d.toml"
        data = design_to_dict(_design(shell=1.5))
        data["layers"] = {"shell_mm": shell, "lesions": {x.name: {"center_mm": list(x.center_mm),
                                                                  "semi_axes_mm": list(x.semi_axes_mm)} for x in lesions}}
        path.write_text(tomli_w.dumps(data))
        assert main(["design", "--config", str(path), "--out", str(tmp_path / "o"), "--no-png"]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    with pytest.raises(DesignError, match=r"layers.shell_mm = -1 must be >= 0 mm"):
        LayersParams(shell_mm=-1.0)


@pytest.mark.parametrize("shell, ok", [(3.0, True), (4.0, False), (5.0, False), (6.0, False)])
def test_a_shell_whose_inner_surface_grazes_an_arm_end_is_refused(shell, ok, tmp_path, capsys):
    """The default arms end 8 mm deep: a 4–6 mm shell puts the infill's surface within 1.5 mm of an
    arm end's rim, where gmsh failed ("two facets intersect", 5 mm at an 8 mm mesh): refused before
    meshing, naming the value and the arm; 3 mm (2.1 mm off the rim) passes."""
    if ok:
        _design(shell=shell)
        return
    with pytest.raises(DesignError, match=rf"layers.shell_mm = {shell:g}: the infill's surface passes [0-9.]+ mm "
                                          r"from the rim of arms\.\w+'s end in the bulb \(min 1.5 mm"):
        _design(shell=shell)
    path = tmp_path / "d.toml"
    path.write_text(save_design(_design(shell=1.5), path).read_text().replace("shell_mm = 1.5", f"shell_mm = {shell}"))
    assert main(["design", "--config", str(path), "--out", str(tmp_path / "o"), "--mesh-size-mm", "8", "--no-png"]) == 2
    err = capsys.readouterr().err
    assert f"layers.shell_mm = {shell:g}: the infill" in err and len(err.strip().splitlines()) == 1


def test_a_gmsh_failure_on_a_shell_names_the_shell_and_the_mesh_size(monkeypatch):
    """A failure the checks did not predict: gmsh's own message, reworded to name [layers] shell_mm
    and the mesh size (a MeshError, i.e. one line and exit 2 from the CLI)."""
    from softphantom.design import mesh as mesh_mod
    from softphantom.errors import MeshError, UserError

    def fails(design, mp):
        raise RuntimeError("PLC Error:  Two facets intersect at point 4.4")

    monkeypatch.setattr(mesh_mod, "_build", fails)
    d = _design()
    with pytest.raises(MeshError, match=r"^layers.shell_mm = 3 mm at mesh.size_mm = 8 mm \(surface 5.33 mm\): gmsh "
                                        r"could not mesh the shell \(gmsh failed on design 'bip': PLC Error:  Two facets"):
        mesh_mod.mesh_design(d, d.mesh.scaled_to(8.0), isolate=False)
    assert issubclass(MeshError, UserError)
    one = BIPDesign()  # without a shell the message is gmsh's, unchanged
    with pytest.raises(MeshError, match=r"^gmsh failed on design 'bip': PLC Error"):
        mesh_mod.mesh_design(one, one.mesh, isolate=False)


@pytest.mark.slow
def test_two_step_cast_molds():
    """Shell first: the bulb mold closed on the infill core leaves the shell's volume free (within
    2 %); the halves, the core and the lesion molds are closed manifold solids, and each lesion
    mold leaves its lesion free. (The cast shell itself, the slowest piece to build, is checked in
    benchmarks/bench_multimaterial.py.)"""
    trimesh = pytest.importorskip("trimesh")
    from softphantom.design.solid_check import report_mesh, to_manifold
    from softphantom.molds.parts import _Builder

    d = _design(shell=1.5, shell_mat="sorta_clear_12")
    assert d.material_of_regions()["shell"] == "sorta_clear_12"  # the preset, written into the design
    b = _Builder(d)
    assert b._material("shell") == "Sorta-Clear 12"
    lower, upper, core = b.bulb_half(False), b.bulb_half(True), b.infill_core()
    lesion_molds = [b.lesion_half(x, up) for x in LESIONS for up in (False, True)]
    for p in [lower, upper, core, *lesion_molds]:
        assert report_mesh(p.mesh).ok, p.name
    a, bb, c = d.bulb.semi_axes_mm
    t = 1.5
    shell = 4.0 / 3.0 * math.pi * (a * bb * c - (a - t) * (bb - t) * (c - t))
    hull = to_manifold(trimesh.util.concatenate([lower.mesh, upper.mesh]).convex_hull)
    env = trimesh.creation.icosphere(subdivisions=4)  # 1 mm outside the bulb (its facets' sagitta 0.02 mm)
    env.apply_scale(np.asarray(d.bulb.semi_axes_mm) + 1.0)
    cavity = (hull - to_manifold(lower.mesh) - to_manifold(upper.mesh)) ^ to_manifold(env)
    assert (cavity - to_manifold(core.mesh)).volume() == pytest.approx(shell, rel=0.02)
    for x in LESIONS:
        halves = [m for m in lesion_molds if m.group == f"lesion_{x.name}"]
        h = to_manifold(trimesh.util.concatenate([m.mesh for m in halves]).convex_hull)
        e = trimesh.creation.icosphere(subdivisions=3)
        e.apply_scale(np.asarray(x.semi_axes_mm) + 0.5)
        e.apply_translation(x.center_mm)
        free = (h - to_manifold(halves[0].mesh) - to_manifold(halves[1].mesh)) ^ to_manifold(e)
        assert free.volume() == pytest.approx(x.volume_mm3, rel=0.02)


def test_cast_pieces_of_a_lesion_design():
    """Lesions without a shell: the infill is one solid with a void per lesion and holds the bulb
    less the urethra and the lesions (within 2 %); each cast lesion is its ellipsoid within 1 %."""
    from softphantom.design.solid_check import report_mesh
    from softphantom.molds import _one_solid_with_voids
    from softphantom.molds.parts import _Builder

    d = _design(shell=0.0)
    casts = {p.name: p for p in _Builder(d).cast_layers()}
    assert set(casts) == {"cast_infill", *(f"cast_{x.region}" for x in LESIONS)}
    for p in casts.values():
        r = report_mesh(p.mesh)
        if p.name == "cast_infill":  # poured around the lesions: one void shell each, accepted as such
            assert r.components == 1 + len(LESIONS) and _one_solid_with_voids(p.mesh, r), p.name
        else:
            assert r.ok, p.name
    for x in LESIONS:
        assert casts[f"cast_{x.region}"].volume_mm3 == pytest.approx(x.volume_mm3, rel=0.01)
    infill = d.bulb.volume_mm3 - d.urethra.volume_mm3 - sum(x.volume_mm3 for x in LESIONS)
    assert casts["cast_infill"].volume_mm3 == pytest.approx(infill, rel=0.02)
