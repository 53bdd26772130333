"""softphantom design --anatomy: a synthetic, lobed prostate label map at MRI-like spacing
(0.5 × 0.5 × 3 mm, seeded boundary noise, a urethra label) and a closed STL become a design's bulb;
mesh, FEM solve and molds run on the result; bad input is one line and exit 2.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

trimesh = pytest.importorskip("trimesh")
nib = pytest.importorskip("nibabel")
pytest.importorskip("skimage")

from softphantom.cli import main  # noqa: E402
from softphantom.design import BIPDesign, build_model  # noqa: E402
from softphantom.design.anatomy import (  # noqa: E402
    AnatomyOptions,
    anatomy_from_labels,
    anatomy_from_surface,
    design_from_anatomy,
    load_anatomy,
)
from softphantom.errors import DesignError  # noqa: E402
from label_maps import zonal_label_map  # noqa: E402

SPACING = (0.5, 0.5, 3.0)
SEMI_RAS = np.array([32.0, 30.0, 24.0])  # R-L, A-P, S-I half extents before the lobes


LESION_RAS = (np.array([-14.0, -8.0, -6.0]), np.array([5.0, 4.0, 7.5]))  # centre, semi-axes (R-L, A-P, S-I) mm


def synthetic_labels(seed: int = 0, spacing=SPACING, urethra_r: float = 3.5, lesion: bool = False):
    """A bilobed gland (label 1) with a urethra (label 2) along S-I, in RAS voxels, and with
    ``lesion`` an axis-aligned ellipsoidal lesion (label 3, :data:`LESION_RAS`); (data, affine)."""
    sp = np.asarray(spacing)
    shape = tuple(int(n) for n in np.ceil(np.array([92.0, 84.0, 72.0]) / sp))
    p = np.indices(shape).transpose(1, 2, 3, 0) * sp - np.array(shape) * sp / 2
    theta = np.arctan2(p[..., 1], p[..., 0])
    level = np.linalg.norm(p / SEMI_RAS, axis=-1) / (1.0 + 0.1 * np.cos(2.0 * theta))  # two lateral lobes
    level += np.random.default_rng(seed).normal(0.0, 0.01, level.shape)  # rough boundary, seeded
    inside = level < 1.0
    lab, _ = ndimage.label(inside, structure=np.ones((3, 3, 3), bool))
    data = (lab == np.argmax(np.bincount(lab.ravel())[1:]) + 1).astype(np.int16)  # noise leaves strays: keep the gland
    urethra = (np.hypot(p[..., 0], p[..., 1] - 4.0) < urethra_r) & (np.abs(p[..., 2]) < 14.0)
    data[urethra & (data > 0)] = 2
    if lesion:
        c, semi = LESION_RAS
        data[(np.sum(((p - c) / semi) ** 2, axis=-1) <= 1.0) & (data > 0)] = 3
    affine = np.diag([*sp, 1.0])
    affine[:3, 3] = -np.array(shape) * sp / 2
    return data, affine


@pytest.fixture(scope="module")
def gland():
    data, affine = synthetic_labels()
    return data, affine, anatomy_from_labels(data, affine)


@pytest.fixture(scope="module")
def lesion_gland():
    """The gland with its lesion label, its surface kept coarse (6 mm: every OCC boolean on the
    polyhedral bulb costs in proportion to its triangles), and its design."""
    data, affine = synthetic_labels(lesion=True)
    a = anatomy_from_labels(data, affine, AnatomyOptions(surface_size_mm=6.0, lesion_labels=(3,)))
    return data, affine, a, design_from_anatomy(a)


def test_label_map_surface_holds_the_voxel_volume_within_2_percent(gland):
    data, affine, a = gland
    voxels = float((data > 0).sum()) * abs(np.linalg.det(affine[:3, :3]))
    assert a.voxel_volume_mm3 == pytest.approx(voxels)
    assert abs(a.volume_mm3 / voxels - 1.0) < 0.02
    m = trimesh.Trimesh(a.vertices_mm, a.faces)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0


def test_placement_by_principal_axes_in_the_model_frame(gland):
    _, _, a = gland
    m = trimesh.Trimesh(a.vertices_mm, a.faces)
    assert np.linalg.norm(m.center_mass) < 0.05  # centroid at the origin
    inertia = m.moment_inertia
    off = np.abs(inertia - np.diag(np.diag(inertia))).max()
    assert off < 1e-3 * np.abs(np.diag(inertia)).max()  # principal axes along x, y, z
    half = 0.5 * np.ptp(a.vertices_mm, axis=0)
    # RAS R-L → x (widest, with the lobes), S-I → y, A-P → z
    assert half[0] > half[2] > half[1]
    assert np.linalg.det(a.rotation) == pytest.approx(1.0)
    u = a.urethra
    assert abs(u["axis"][1]) > 0.99  # the urethra runs along y (S-I)
    assert u["center_mm"][2] == pytest.approx(4.0, abs=0.3)  # 4 mm anterior of the centre


def test_rotated_label_map_lands_in_the_same_frame():
    """The same gland scanned tilted by 20° about R-L: the principal axes bring it back."""
    data, affine = synthetic_labels(seed=1, spacing=(1.0, 1.0, 1.0))
    a0 = anatomy_from_labels(data, affine)
    c, s = np.cos(np.radians(20.0)), np.sin(np.radians(20.0))
    rot = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0.0, 0.0, 0.0, 1.0]])
    a1 = anatomy_from_labels(data, rot @ affine)
    np.testing.assert_allclose(np.ptp(a1.vertices_mm, axis=0), np.ptp(a0.vertices_mm, axis=0), atol=0.3)
    assert a1.volume_mm3 == pytest.approx(a0.volume_mm3, rel=1e-3)


def test_stl_surface_import(tmp_path):
    ell = trimesh.creation.icosphere(subdivisions=5)
    ell.apply_scale([30.0, 26.0, 24.0])
    path = tmp_path / "gland.stl"
    ell.export(path)
    a = load_anatomy(path)
    assert abs(a.volume_mm3 / ell.volume - 1.0) < 0.02
    half = 0.5 * np.ptp(a.vertices_mm, axis=0)
    np.testing.assert_allclose(half, [30.0, 24.0, 26.0], atol=0.3)  # RAS (x, y, z) → model (x, z, y)


def _meshes_and_solves(model, volume_mm3):
    """The checks every imported gland's model must pass (12 mm mesh, one FEM solve): the mesh has
    no slivers where the arms cut the surface (min dihedral > 1°; 0.04–0.2° before
    anatomy._clear_of_arm_cuts, or no mesh at all)."""
    from softphantom.fem import fem_from_phantom, force_actuator, solve_static

    design = model.design
    # the vertices moved off the arms' cylinders (anatomy._clear_of_arm_cuts) change the volume by < 0.1 %
    assert design.bulb.is_surface and design.bulb.volume_mm3 == pytest.approx(volume_mm3, rel=1e-3)
    assert design.mesh.size_mm == 12.0
    assert model.bulb_volume() * 1e9 == pytest.approx(volume_mm3, rel=0.02)
    assert model.min_dihedral_deg() > 1.0
    # a coarse mesh inscribes the cavity: low by about (2π/n)²/6 with n segments around (mesh.py)
    n = model.design.mesh.cavity_segments
    expect = design.urethra.volume_mm3 * (1.0 - (2.0 * np.pi / n) ** 2 / 6.0)
    assert model.cavity_volume("urethra") * 1e9 == pytest.approx(expect, rel=0.02)
    fem = fem_from_phantom(model)
    sol = solve_static(fem, force_actuator(fem, model.p_ext["on-centre"], radius=5e-3) @ np.array([0.0, 1.0, 0.0]))
    assert sol.converged
    dy = (sol.x - model.nodes)[:, 1]
    assert dy.max() > 1e-4  # a 1 N push along +y moves the gland along +y


def _gets_its_bulb_mold(design):
    """The bulb mold of an imported gland: closed solids that leave the whole gland free."""
    from softphantom.design.solid_check import report_mesh, to_manifold
    from softphantom.molds import build_parts

    parts = {p.name: p for p in build_parts(design, bulb_only=True)}
    halves = [parts["bulb_mold_lower"], parts["bulb_mold_upper"]]
    for h in halves:
        assert report_mesh(h.mesh).ok
    hull = to_manifold(trimesh.util.concatenate([h.mesh for h in halves]).convex_hull)
    cavity = hull - to_manifold(halves[0].mesh) - to_manifold(halves[1].mesh)
    bulb = to_manifold(trimesh.Trimesh(np.asarray(design.bulb.surface_vertices_mm), np.asarray(design.bulb.surface_faces)))
    assert (bulb - cavity).volume() / bulb.volume() < 0.01  # the mold leaves the whole gland free
    assert (cavity ^ bulb).volume() == pytest.approx(bulb.volume(), rel=0.01)


def test_lesion_label_becomes_a_design_lesion_by_moments(lesion_gland, monkeypatch):
    """Label 3, an ellipsoid of semi-axes (5, 4, 7.5) mm (R-L, A-P, S-I) sampled at 0.5 × 0.5 × 3 mm:
    its moments give back the centre (< 0.3 mm) and the semi-axes (within half a voxel) in the model frame, and
    the design gets it as ``[layers.lesions.label3]`` in the bulb's material."""
    from softphantom.design.anatomy import lesion_report

    data, affine, a, d = lesion_gland
    les = a.lesions[3]
    c, semi = LESION_RAS
    np.testing.assert_allclose(les["center_mm"], a.rotation @ c + a.translation, atol=0.3)
    # within half a voxel along each axis: 0.25 mm in-plane, 1.5 mm across the 3 mm slices (the
    # stair-stepped ends of 5 slices weigh more in the second moment than the ellipsoid's caps)
    np.testing.assert_array_less(np.abs(les["semi_axes_mm"] - np.abs(a.rotation) @ semi),
                                 np.abs(a.rotation) @ (0.5 * np.asarray(SPACING)))
    assert les["tilt_deg"] < 3.0
    voxels = float((data == 3).sum()) * abs(np.linalg.det(affine[:3, :3]))
    assert les["volume_mm3"] == pytest.approx(voxels)
    assert les["ellipsoid_mm3"] == pytest.approx(voxels, rel=0.05)  # the fit's volume against the voxel count
    (line,) = lesion_report(a)
    assert line.startswith("lesion label 3 -> layers.lesions.label3: centre (") and "mm³ of voxels (" in line
    (x,) = d.layers.lesions
    assert x.region == "lesion_label3" and d.layers.shell_mm == 0.0
    np.testing.assert_allclose(x.semi_axes_mm, les["semi_axes_mm"])
    assert d.material_of_regions()["lesion_label3"] == d.material_of_regions()["bulb"]
    # refused before the gland's surface is built
    monkeypatch.setitem(anatomy_from_labels.__globals__, "_marching_cubes",  # the module this function runs in
                        lambda *args: pytest.fail("the surface was built"))
    with pytest.raises(DesignError, match="lesion label 4 has no voxels"):
        anatomy_from_labels(data, affine, AnatomyOptions(lesion_labels=(4,)))
    with pytest.raises(DesignError, match="lesion label 2 must be > 0 and not the urethra's"):
        anatomy_from_labels(data, affine, AnatomyOptions(lesion_labels=(2,)))


@pytest.mark.slow
def test_anatomy_design_meshes_solves_and_gets_molds(lesion_gland):
    """The label map end to end, kept coarse (a 6 mm surface, a 12 mm mesh). With its lesion label:
    the lesion's mesh region holds the fitted ellipsoid's volume less the facet deficit, within 2 %."""
    _, _, a, design = lesion_gland
    model = build_model(design, 12.0, isolate=False)  # in-process: the CLI test below meshes in a child
    _meshes_and_solves(model, a.volume_mm3)
    _gets_its_bulb_mold(design)
    n = model.design.mesh.cavity_segments  # a lesion's wall is meshed like a cavity's: low by (2π/n)²/6
    expect = a.lesions[3]["ellipsoid_mm3"] * (1.0 - (2.0 * np.pi / n) ** 2 / 6.0)
    assert model.region_volume("lesion_label3") * 1e9 == pytest.approx(expect, rel=0.02)


@pytest.mark.slow
def test_stl_anatomy_end_to_end_through_the_cli(tmp_path, capsys):
    """A closed, lobed STL through ``softphantom design --anatomy`` (6 mm surface, 12 mm mesh): the
    written design keeps the STL's volume and the written model passes the mesh checks and
    solves. (The bulb mold of an imported gland: test_anatomy_design_meshes_solves_and_gets_molds.)"""
    from softphantom.design import load_design, load_model

    sphere = trimesh.creation.icosphere(subdivisions=4)
    v = sphere.vertices
    lobes = 1.0 + 0.1 * (v[:, 0] ** 2 - v[:, 1] ** 2)  # two lateral lobes: 0.1 cos 2θ sin²φ, smooth at the poles
    surf = trimesh.Trimesh(v * SEMI_RAS * lobes[:, None], sphere.faces)
    path = tmp_path / "gland.stl"
    surf.export(path)
    out = tmp_path / "model"
    assert main(["design", "--anatomy", str(path), "--surface-size-mm", "6", "--mesh-size-mm", "12",
                 "--no-png", "--out", str(out)]) == 0
    capsys.readouterr()
    design = load_design(out / "design.toml")
    vol = float(trimesh.Trimesh(np.asarray(design.bulb.surface_vertices_mm), np.asarray(design.bulb.surface_faces)).volume)
    assert vol == pytest.approx(surf.volume, rel=0.02)
    model = load_model(out)  # the model the command meshed and wrote
    assert model.design == design
    _meshes_and_solves(model, vol)


def test_bad_anatomy_is_one_line_exit_2(tmp_path, capsys):
    empty = np.zeros((20, 20, 8), np.int16)
    two = np.zeros((40, 20, 8), np.int16)
    two[2:10, 5:15, 2:6] = 1
    two[25:35, 5:15, 2:6] = 1
    for name, arr, msg in (("empty", empty, "no labelled voxels"), ("two", two, "2 disconnected components")):
        path = tmp_path / f"{name}.nii.gz"
        nib.save(nib.Nifti1Image(arr, np.diag([0.5, 0.5, 3.0, 1.0])), str(path))
        assert main(["design", "--anatomy", str(path), "--out", str(tmp_path / f"o_{name}")]) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    box = trimesh.creation.box((40.0, 30.0, 30.0))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)
    crossing = trimesh.util.concatenate([box, trimesh.creation.box((40.0, 30.0, 30.0)).apply_translation((10.0, 7.3, 5.1))])
    for name, mesh, msg in (("open", open_box, "not closed"), ("crossing", crossing, "self-intersecting")):
        path = tmp_path / f"{name}.stl"
        mesh.export(path)
        assert main(["design", "--anatomy", str(path), "--out", str(tmp_path / f"o_{name}")]) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err
    with pytest.raises(DesignError, match="no labelled voxels"):
        anatomy_from_labels(empty, np.eye(4))
    with pytest.raises(DesignError, match="not closed"):
        anatomy_from_surface(open_box, AnatomyOptions())


# --- label maps as public data sets publish them: zones, no urethra label, thick slices -------

ZONAL_SPACING = (0.6, 0.6, 4.0)


def _zonal_anatomy(tmp_path, volume_mL, tilt_deg=0.0, surface_size_mm=6.0):
    """The zonal map written as NIfTI (as the data sets ship it) and imported with its zones as the gland."""
    data, affine, semi, axes = zonal_label_map(volume_mL, tilt_deg)
    path = tmp_path / f"zones_{volume_mL:g}mL.nii.gz"
    nib.save(nib.Nifti1Image(data, affine), str(path))
    a = load_anatomy(path, AnatomyOptions(gland_labels=(1, 2), urethra_label=0, surface_size_mm=surface_size_mm))
    return data, affine, semi, axes, a


@pytest.fixture(scope="module")
def zonal(tmp_path_factory):
    """:func:`_zonal_anatomy` of a (volume, tilt), imported once per module (several tests read the
    30 and 47 mL glands; the import is deterministic and its result frozen)."""
    made: dict = {}

    def get(volume_mL: float, tilt_deg: float = 0.0):
        if (volume_mL, tilt_deg) not in made:
            made[volume_mL, tilt_deg] = _zonal_anatomy(tmp_path_factory.mktemp("zonal"), volume_mL, tilt_deg)
        return made[volume_mL, tilt_deg]

    return get


def test_zonal_gland_is_the_union_of_its_labels(tmp_path):
    """Labels 1 and 2 together are the gland: the voxel volume is theirs, and a label outside the
    gland (5, a detached blob) is left out, where without --gland-labels it is a second component."""
    data, affine, _, _ = zonal_label_map(45.0)
    data[2:6, 2:6, 0:2] = 5
    voxel = abs(np.linalg.det(affine[:3, :3]))
    opt = AnatomyOptions(gland_labels=(1, 2), urethra_label=0)
    a = anatomy_from_labels(data, affine, opt)
    assert a.voxel_volume_mm3 == pytest.approx(float(np.isin(data, (1, 2)).sum()) * voxel)
    assert abs(a.volume_mm3 / a.voxel_volume_mm3 - 1.0) < 0.02  # at the default 3 mm surface
    assert a.urethra is None
    with pytest.raises(DesignError, match="2 disconnected components"):
        anatomy_from_labels(data, affine, AnatomyOptions(urethra_label=0))
    with pytest.raises(DesignError, match="gland label 7 has no voxels"):
        anatomy_from_labels(data, affine, AnatomyOptions(gland_labels=(1, 7), urethra_label=0))
    with pytest.raises(DesignError, match="gland label 2 is also the urethra's"):
        anatomy_from_labels(data, affine, AnatomyOptions(gland_labels=(1, 2), urethra_label=2))


def test_urethra_on_the_principal_axis_of_a_tilted_ellipsoid(zonal):
    """No urethra label: the urethra runs along the gland's S-I axis (tilted 15° towards anterior,
    the principal axis nearest the template's urethra axis) through its centre, inside it by more
    than the minimum wall, its inlet on the surface at the superior end; radius 4.5 mm × the cube
    root of the volume ratio, length the template's fraction (0.72) of the gland's chord on that axis."""
    from softphantom.design import geometry as geo
    from softphantom.design.anatomy import part_scale
    from softphantom.design.params import MIN_WALL_MM

    _, _, semi, axes, a = zonal(45.0, tilt_deg=15.0)
    template = BIPDesign()
    d = design_from_anatomy(a, template)
    u = d.urethra
    to_ras = a.rotation.T  # model → input (RAS) frame: p_ras = Rᵀ (p − t)
    axis_ras = to_ras @ np.asarray(u.axis)
    assert np.degrees(np.arccos(axis_ras @ axes[:, 2])) < 1.5  # along the tilted S-I axis, towards superior
    centre = to_ras @ (np.asarray(u.center_mm) - a.translation)
    assert np.linalg.norm(centre) < 0.5  # through the ellipsoid's centre (the gland's centroid)
    s = part_scale(a, template)
    assert s == pytest.approx((a.volume_mm3 / template.bulb.volume_mm3) ** (1 / 3))
    assert u.radius_mm == pytest.approx(template.urethra.radius_mm * s)
    ta, tb = template.urethra.segment_mm
    t_len = np.linalg.norm(tb - ta) + 2 * template.urethra.radius_mm
    frac = t_len / (2 * 25.0 * np.sqrt(1 - (4.0 / template.bulb.semi_axes_mm[2]) ** 2))  # its chord at z = 4 mm
    # the voxels' chord is the ellipsoid's within half a 4 mm slice at each end
    assert u.cyl_length_mm + 2 * u.radius_mm == pytest.approx(frac * 2 * semi[2], abs=frac * ZONAL_SPACING[2])
    ua, ub = (to_ras @ (p - a.translation) for p in u.segment_mm)
    wall = -geo.ellipsoid_signed_distance(geo.capsule_surface_points(ua, ub, u.radius_mm) @ axes, semi).max()
    assert wall > MIN_WALL_MM  # inside the analytic gland
    inlet = to_ras @ (np.asarray(u.inlet_mm) - a.translation)
    assert abs(geo.ellipsoid_signed_distance(inlet[None] @ axes, semi)[0]) < 0.5 * ZONAL_SPACING[2]  # on its surface
    assert inlet @ axes[:, 2] > 0.9 * semi[2]  # at the superior end


@pytest.mark.parametrize("volume_mL, mesh", [(30.0, True), (47.0, False), (60.0, False), (120.0, True)])
def test_zonal_map_design_validates_meshes_and_solves(zonal, volume_mL, mesh):
    """30-120 mL zonal maps at 0.6 × 0.6 × 4 mm, no urethra label: the template's parts scaled by
    the cube root of the volume ratio make a valid design (47 mL: the issue's gland, refused before
    with the template's parts). The smallest and the largest mesh (12 mm, P1) with every cavity and
    the bulb within the mesh's tolerance of the design, and a 1 N push along +y solves and moves
    the gland along +y (`design` meshes the 47 mL one in test_zonal_map_through_the_cli)."""
    from softphantom.design.anatomy import part_scale
    from softphantom.fem import fem_from_phantom, force_actuator, solve_static

    *_, a = zonal(volume_mL)
    template = BIPDesign()
    d = design_from_anatomy(a, template)
    s = part_scale(a, template)
    assert s == pytest.approx((volume_mL / 100.41) ** (1 / 3), rel=0.03)  # the surface holds the volume within 3 %
    for arm, t in zip(d.arms, template.arms):
        assert arm.radius_mm == pytest.approx(t.radius_mm * s) and arm.length_mm == pytest.approx(t.length_mm * s)
        assert arm.cavity_volume_mm3 == pytest.approx(t.cavity_volume_mm3 * s**3)
        assert arm.wall_mm >= 1.0
    assert d.urethra.axis == (0.0, 1.0, 0.0) and abs(d.urethra.center_mm[0]) + abs(d.urethra.center_mm[2]) < 1e-9
    if not mesh:
        return
    model = build_model(d, 12.0, isolate=False)  # checks every cavity's and the bulb's meshed volume
    # no slivers where the arms cut the surface: 0.03-0.45° with the arm cylinders' seams where
    # OCC puts them (in the arms' planes, along the surface's edges; occ_shapes.seam_side)
    assert model.min_dihedral_deg() > 1.0
    assert model.design.mesh.element_order == 1 and model.bulb_volume() * 1e9 == pytest.approx(d.bulb.volume_mm3,
                                                                                                rel=0.02)
    fem = fem_from_phantom(model)
    sol = solve_static(fem, force_actuator(fem, model.p_ext["on-centre"], radius=5e-3) @ np.array([0.0, 1.0, 0.0]))
    assert sol.converged
    assert (sol.x - model.nodes)[:, 1].max() > 1e-4


def test_part_that_cannot_be_made_valid_is_one_line_naming_the_fix(zonal):
    """A template whose off-centre point lies 32 mm from the on-centre one (the paper's bulb has
    room up to 39.8 mm at 45°, a 30 mL gland 27.6 mm): one line naming the field, the gland, the
    scale and the option that fixes it."""
    from softphantom.design.params import InteractionParams

    *_, a = zonal(30.0)
    far = BIPDesign(interaction=InteractionParams(offcentre_mm=32.0))
    with pytest.raises(DesignError) as exc:
        design_from_anatomy(a, far)
    msg = str(exc.value)
    assert msg.startswith("interaction.offcentre_mm = 32 is beyond the front of the bulb"), msg
    assert "\n" not in msg and f"a {a.volume_mm3 / 1e3:.1f} mL gland" in msg, msg
    assert msg.endswith("fix: [interaction] offcentre_mm in --config]"), msg


def test_zonal_map_through_the_cli(tmp_path, capsys):
    """``design --anatomy MAP --gland-labels 1,2``: no urethra label to give, the urethra placed on
    the principal axis (said so), the model written; ``--urethra none`` and a urethra label among
    the gland's are one line, exit 2."""
    from softphantom.design import load_design

    data, affine, _, _ = zonal_label_map(47.0)
    path = tmp_path / "zones.nii.gz"
    nib.save(nib.Nifti1Image(data, affine), str(path))
    out = tmp_path / "model"
    assert main(["design", "--anatomy", str(path), "--gland-labels", "1,2", "--surface-size-mm", "6",
                 "--mesh-size-mm", "12", "--no-png", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "urethra: not labelled, placed along the gland's principal axis" in " ".join(text.split())
    d = load_design(out / "design.toml")
    assert d.bulb.is_surface and d.urethra.axis == (0.0, 1.0, 0.0)
    assert d.arms[0].radius_mm < BIPDesign().arms[0].radius_mm  # a 47 mL gland (the issue's): smaller arms
    for args, names in ((["--urethra", "none"], "--urethra none: only with --anatomy"),
                        (["--anatomy", str(path), "--gland-labels", "1,2", "--urethra-label", "2"],
                         "--urethra-label 2 is one of --gland-labels")):
        assert main(["design", *args, "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip()
        assert names in err and "\n" not in err and "Traceback" not in err, err


def test_a_templates_contacts_and_other_cavities_follow_the_gland(zonal):
    """A template with a named contact and a tumour balloon on a 47 mL zonal map: the contact is
    projected onto the gland (on its surface, as the markers), the balloon scaled with it (its
    centre with the gland's extent, its volume by s³), and the design is valid; the template's
    own points would lie outside the smaller gland."""
    from test_cavities import AXES, TUMOUR

    from softphantom.design import design_from_dict
    from softphantom.design import geometry as geo
    from softphantom.design.anatomy import part_scale

    needle = [float(x) for x in geo.project_to_ellipsoid((0.7, -1.0, 0.3), AXES)]
    base = design_from_dict({"urethra": {}, "cavities": {"tumour": TUMOUR}, "contacts": {"needle": needle}})
    *_, a = zonal(47.0)
    d = design_from_anatomy(a, base)
    s = part_scale(a, base)
    assert d.internal_cavity_names == ("urethra", "tumour") and d.contact_names[-1] == "needle"
    t = d.cavity("tumour")
    assert t.volume_mm3 == pytest.approx(base.cavity("tumour").volume_mm3 * s**3)
    needle = np.asarray(d.contacts[0][1])
    dist = np.abs(d.bulb.signed_distance(np.stack([needle, np.asarray(t.inlet_mm)])))
    assert dist.max() < 0.05 * d.bulb.semi_axes_mm[0], dist  # both on the gland's surface
    assert float(d.bulb.signed_distance(np.asarray(base.contacts[0][1])[None])[0]) > 1.0  # the template's: outside


def test_the_urethra_is_left_out_on_request(zonal, gland):
    """``--urethra none`` (``urethra=False``): the 47 mL zonal gland without any urethra cavity (the
    template's dropped, its arms kept at their scaled embedding, none shortened for a urethra), which
    meshes without a urethra wall and solves a 1 N push; a label map with a urethra label is refused
    in one line naming the option."""
    from softphantom.design.anatomy import part_scale
    from softphantom.fem import fem_from_phantom, force_actuator, solve_static

    *_, a = zonal(47.0)
    d = design_from_anatomy(a, urethra=False)
    assert d.urethra is None and d.internal_cavity_names == () and d.cavity_names == d.arm_names
    s = part_scale(a, BIPDesign())
    assert [arm.embed_mm for arm in d.arms] == pytest.approx([arm.embed_mm * s for arm in BIPDesign().arms])
    model = build_model(d, 12.0, isolate=False)
    assert tuple(model.cavities) == d.arm_names
    fem = fem_from_phantom(model)
    sol = solve_static(fem, force_actuator(fem, model.p_ext["on-centre"], radius=5e-3) @ np.array([0.0, 1.0, 0.0]))
    assert sol.converged and (sol.x - model.nodes)[:, 1].max() > 1e-4
    with pytest.raises(DesignError, match=r"^urethra: the label map has a urethra label .*--urethra-label 0"):
        design_from_anatomy(gland[2], urethra=False)  # label 2, the urethra
