"""The junction fillet (``ArmParams.junction_fillet_mm``): its solid against the rolling-ball
closed form, the meshed design with it, and its validation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import quad

from softphantom.design import ARM_NAMES, BIPDesign, build_model, design_from_dict
from softphantom.design.mesh import gmsh_session, predicted_cavity_error
from softphantom.design.model import MM
from softphantom.design.occ_shapes import bulb_solid, filleted_body, junction_fillets
from softphantom.errors import DesignError


def _ring_on_sphere(r_arm: float, r_sphere: float, r: float) -> float:
    """Volume of the rolling-ball fillet of radius r between a cylinder of radius r_arm and a sphere
    of radius r_sphere it leaves radially (axisymmetric): shells 2πρ·dρ between the sphere and the
    ball, whose centre is at ρ = r_arm + r, |c| = r_sphere + r; the ball touches the sphere at
    ρ = r_sphere (r_arm + r) / (r_sphere + r)."""
    rc = r_arm + r
    zc = math.sqrt((r_sphere + r) ** 2 - rc**2)
    rho_s = r_sphere * rc / (r_sphere + r)

    def height(p):
        return (zc - math.sqrt(r * r - (p - rc) ** 2)) - math.sqrt(r_sphere**2 - p * p)

    return quad(lambda p: 2 * math.pi * p * height(p), r_arm, rho_s, epsabs=1e-12, epsrel=1e-12)[0]


def _ring_on_plane(r_arm: float, r: float) -> float:
    """Pappus: the quarter-round spandrel (1 − π/4) r², its centroid (10 − 3π)/(12 − 3π) r off the cylinder."""
    return (1 - math.pi / 4) * r * r * 2 * math.pi * (r_arm + r * (10 - 3 * math.pi) / (12 - 3 * math.pi))


def _occ_ring(r_arm: float, r_sphere: float, r: float) -> float:
    with gmsh_session("fillet_test", "the fillet test") as gmsh:
        occ = gmsh.model.occ
        bulb = occ.addSphere(0.0, 0.0, 0.0, r_sphere)
        root, end = np.array([0.0, 0.0, r_sphere]), np.array([0.0, 0.0, r_sphere + 30.0])
        cyl = occ.addCylinder(0.0, 0.0, r_sphere - 8.0, 0.0, 0.0, 38.0, r_arm)
        rings = junction_fillets(occ, bulb, [(cyl, root, end, r_arm)], [r])
        occ.synchronize()
        assert len(rings[0]) == 1
        return occ.getMass(3, rings[0][0])


@pytest.mark.parametrize("r, r_sphere", [(1.0, 30.0), (2.0, 30.0), (3.0, 25.0), (1.0, 1000.0)])
def test_ring_volume_is_the_rolling_ball_integral(r, r_sphere):
    assert _occ_ring(6.0, r_sphere, r) == pytest.approx(_ring_on_sphere(6.0, r_sphere, r), rel=1e-5)


def test_rolling_ball_integral_tends_to_the_quarter_round_of_pappus():
    # on a flat bulb the ring is the spandrel revolved; a convex bulb tilts away and takes less
    # (the spandrel's area drops by r²/2 per radian of tilt: 1.6 % at 1 m, 6 mrad)
    assert _ring_on_sphere(6.0, 1e7, 1.0) == pytest.approx(_ring_on_plane(6.0, 1.0), rel=1e-5)
    assert _ring_on_sphere(6.0, 1e3, 1.0) / _ring_on_plane(6.0, 1.0) == pytest.approx(1 - 0.5 * 6.5e-3 / (1 - math.pi / 4),
                                                                                     abs=2e-3)


def _filleted(design: BIPDesign, r: float) -> BIPDesign:
    return dataclasses.replace(design, arms=tuple(dataclasses.replace(a, junction_fillet_mm=r) for a in design.arms))


@pytest.fixture(scope="module")
def coarse_pair(coarse_truth_p1):
    """(sharp, rounded): the design without and with 2 mm fillets (the default), at 9 mm. The
    rounded one is the virtual truth's P1 mesh of the coarse model (shared, conftest)."""
    d = BIPDesign()
    d = dataclasses.replace(d, mesh=d.mesh.scaled_to(9.0))
    assert {a.junction_fillet_mm for a in d.arms} == {2.0} and coarse_truth_p1.design == d
    return build_model(_filleted(d, 0.0), isolate=False), coarse_truth_p1


@pytest.mark.slow
def test_filleted_design_meshes_conforming_with_the_cavities_unchanged(coarse_pair):
    sharp, m = coarse_pair
    t = m.tets
    assert m.tet_volumes().min() > 0.0 and m.min_dihedral_deg() > 5.0
    faces = np.sort(np.vstack([t[:, [1, 2, 3]], t[:, [0, 2, 3]], t[:, [0, 1, 3]], t[:, [0, 1, 2]]]), axis=1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2  # one conforming solid
    boundary = {tuple(f) for f in uniq[counts == 1]}
    tagged = {tuple(f) for tr in [m.outer_faces, m.fixed_faces, *m.cavities.values()] for f in np.sort(tr, axis=1)}
    assert boundary == tagged
    for name in m.cavities:  # the cavities as without the fillet (the paper's 514 / 486 mm³)
        assert m.cavity_volume(name) == pytest.approx(sharp.cavity_volume(name), rel=3e-3), name
        assert m.cavity_volume(name) / MM**3 == pytest.approx(m.design.cavity_volumes_mm3()[name],
                                                              rel=predicted_cavity_error(m.design.mesh) + 0.01)
    # the meshed solid against the exact one (OCC: the bulb fused with the arms, rounded or not,
    # less the design's cavities): an inscribed faceting, a little below it, and the rounded solid
    # is the sharp one plus its four rings
    exact = {}
    with gmsh_session("fillet_exact", "the exact solids") as gmsh:
        occ = gmsh.model.occ
        bulb = bulb_solid(occ, m.design.bulb)
        arms = [(occ.addCylinder(*g.start_mm, *(g.end_mm - g.start_mm), g.radius_mm), g.root_mm, g.end_mm, g.radius_mm)
                for g in m.design.arm_geometry()]
        for key, r in (("sharp", 0.0), ("rounded", 2.0)):
            tag, _ = filleted_body(occ, bulb, arms, [r] * 4)
            exact[key] = occ.getMass(3, tag) - sum(m.design.cavity_volumes_mm3().values())
        rings = junction_fillets(occ, bulb, arms, [2.0] * 4)
        ring_volume = sum(occ.getMass(3, t) for ts in rings for t in ts)
    assert exact["rounded"] - exact["sharp"] == pytest.approx(ring_volume, abs=0.5)  # OCC integrates 1e5 mm³ to ≈ 3e-6
    assert 60.0 < ring_volume < 100.0  # the quarter round of a flat bulb would be 4 × 34.8 mm³; it tilts away
    for key, model in (("sharp", sharp), ("rounded", m)):
        v = model.tet_volumes().sum() / MM**3
        assert -0.02 < (v - exact[key]) / exact[key] < 0.0, key
    # every arm region starts above its fillet: a tube of the arm's radius, clamped at its end
    d = m.design
    for g in d.arm_geometry():
        x = m.nodes[np.unique(t[m.tet_region == m.regions[f"arm_{g.name}"]])] / MM
        rel = x - g.root_mm
        assert np.linalg.norm(np.cross(rel, g.direction), axis=1).max() < g.radius_mm + 1e-3
        assert (rel @ g.direction).min() > g.fillet_mm
    # the fillet faces are outer surface off both the arm's side and the bulb's surface
    x = m.nodes[np.unique(m.outer_faces)] / MM
    g = d.arm_geometry()[0]
    rho = np.linalg.norm(np.cross(x - g.root_mm, g.direction), axis=1)
    assert ((rho > g.radius_mm + 0.2) & (rho < g.radius_mm + 1.8) & (d.bulb.signed_distance(x) > 0.2)).sum() >= 3


@pytest.mark.slow
def test_junction_refinement_follows_the_fillet():
    d = BIPDesign()
    d = _filleted(dataclasses.replace(d, mesh=dataclasses.replace(d.mesh.scaled_to(12.0), junction_size_mm=2.0)), 2.0)
    m = build_model(d, isolate=False)
    g = d.arm_geometry()[2]
    x = m.nodes / MM
    rho = np.linalg.norm(np.cross(x - g.root_mm, g.direction), axis=1)
    near = (np.abs(rho - g.radius_mm - 1.0) < 1.5) & (np.abs(d.bulb.signed_distance(x)) < 3.0)
    assert near.sum() > 40  # along the 44 mm ring at ≈ 2 mm


@pytest.mark.parametrize("value, message", [
    (-0.5, "arms.front_zpos.junction_fillet_mm = -0.5 must be in [0, radius_mm = 6] mm"),
    (6.5, "arms.front_zpos.junction_fillet_mm = 6.5 must be in [0, radius_mm = 6] mm"),
    ("2", "arms.front_zpos.junction_fillet_mm: expected a number"),
    (float("nan"), "arms.front_zpos.junction_fillet_mm = nan must be finite"),
])
def test_bad_fillet_is_refused_naming_the_field(value, message):
    with pytest.raises(DesignError) as e:
        design_from_dict({"arms": {"front_zpos": {"junction_fillet_mm": value}}})
    assert str(e.value).startswith(message) and "\n" not in str(e.value)


def test_fillet_round_trips_through_the_design_file(tmp_path):
    from softphantom.design import load_design, save_design

    d = _filleted(BIPDesign(), 1.5)
    assert load_design(save_design(d, tmp_path / "d.toml")) == d
    assert d.arm_geometry()[1].fillet_mm == 1.5


@pytest.mark.slow
def test_arm_is_cast_with_its_fillet():
    """The arm's mold rounds into the bulb: the cast arm gains its ring, the mold halves lose it
    (within their tessellation: ≈ 10 mm³ of a 3 100 mm³ arm at 24 facets a circle, so a 4 mm fillet of
    ≈ 80 mm³), and every part stays a closed solid."""
    pytest.importorskip("trimesh")
    pytest.importorskip("manifold3d")
    from softphantom.design.solid_check import report_mesh
    from softphantom.molds.parts import _Builder

    from softphantom.design.fabrication import MoldParams

    vols = {}
    for r in (0.0, 4.0):  # 24 facets a circle: half the default's, a quarter of its triangles
        b = _Builder(dataclasses.replace(_filleted(BIPDesign(), r), molds=MoldParams(segments=24.0)))
        parts = {p.name: p for p in b.arm_parts(b.arms[0])}
        assert all(report_mesh(p.mesh).ok for p in parts.values())
        vols[r] = {k: p.volume_mm3 for k, p in parts.items()}
    with gmsh_session("fillet_ring", "the ring") as gmsh:
        occ = gmsh.model.occ
        g = BIPDesign().arm_geometry()[0]
        cyl = occ.addCylinder(*g.start_mm, *(g.end_mm - g.start_mm), g.radius_mm)
        ring = occ.getMass(3, junction_fillets(occ, bulb_solid(occ, BIPDesign().bulb),
                                               [(cyl, g.root_mm, g.end_mm, g.radius_mm)], [4.0])[0][0])
    name = "front_zpos"
    cast_gain = vols[4.0][f"cast_arm_{name}"] - vols[0.0][f"cast_arm_{name}"]
    mold_loss = sum(vols[0.0][f"arm_mold_{name}_{s}"] - vols[4.0][f"arm_mold_{name}_{s}"] for s in "ab")
    assert cast_gain == pytest.approx(ring, rel=0.2) and mold_loss == pytest.approx(ring, rel=0.2)
    assert vols[4.0][f"arm_core_{name}"] == vols[0.0][f"arm_core_{name}"]  # the cavity is the same


def test_an_imported_bulb_refuses_a_fillet():
    from softphantom.design import BulbParams

    v = [(-30.0, -25.0, -28.0), (30.0, -25.0, -28.0), (0.0, 30.0, -28.0), (0.0, 0.0, 35.0)]
    tetra = BulbParams(surface_vertices_mm=tuple(v), surface_faces=((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)))
    with pytest.raises(DesignError, match=r"^arms\.front_zpos\.junction_fillet_mm = 2: an imported"):
        # the fillet is checked before the geometry this crude surface would fail
        BIPDesign(bulb=tetra, arms=_filleted(BIPDesign(), 2.0).arms)


def test_a_design_file_with_an_imported_bulb_keeps_sharp_junctions_unless_it_sets_one():
    from softphantom.design import design_from_dict

    assert BIPDesign().arms[0].junction_fillet_mm == 2.0  # the default: rounded
    v = [(-30.0, -25.0, -28.0), (30.0, -25.0, -28.0), (0.0, 30.0, -28.0), (0.0, 0.0, 35.0)]
    bulb = {"surface_vertices_mm": v, "surface_faces": [(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)]}
    # the crude surface fails a later geometry check; what matters is which check stops it
    with pytest.raises(DesignError) as exc:
        design_from_dict({"bulb": bulb})
    assert "junction_fillet_mm" not in str(exc.value)
    with pytest.raises(DesignError, match=r"^arms\.back_xpos\.junction_fillet_mm = 1\.5: an imported"):
        design_from_dict({"bulb": bulb, "arms": {"back_xpos": {"junction_fillet_mm": 1.5}}})
