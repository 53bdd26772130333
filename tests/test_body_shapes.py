"""Parametric bodies: Barr's superellipsoid and the bent bean (design/shapes.py, ``[bulb] shape``).

Truths: Barr's closed-form volume (against scipy's beta function and a grid count of the inside-
outside function), the shear's unit Jacobian (a bent body holds the same volume), the analytic
surface (distance of the triangles to it), and the design checks of the rest of the toolkit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import beta

from softphantom.cli import main
from softphantom.design import geometry as geo
from softphantom.design.params import (BIPDesign, BulbParams, design_from_dict, design_to_dict, design_to_toml,
                                       load_design)
from softphantom.design.shapes import bend_axes, bend_points, body_surface, superellipsoid_surface
from softphantom.errors import DesignError

AXES = (30.0, 26.0, 24.0)


def barr_volume(axes, ex) -> float:
    a, b, c = axes
    e1, e2 = ex
    return 2 * a * b * c * e1 * e2 * beta(e1 / 2 + 1, e1) * beta(e2 / 2, e2 / 2)


def grid_volume(axes, ex, bend=0.0, h=0.5) -> float:
    """Count of grid cells whose centre is inside (the bent body: its points unbent first)."""
    lo = -np.asarray(axes) - h
    lo[bend_axes(axes)[1]] -= abs(bend)
    axes_g = [np.arange(lo[i] + h / 2, -lo[i], h) for i in range(3)]
    p = np.stack(np.meshgrid(*axes_g, indexing="ij"), axis=-1).reshape(-1, 3)
    q = bend_points(p, axes, -bend) if bend else p
    return float((geo.superellipsoid_level(q, axes, ex) < 1.0).sum() * h**3)


def surface_distance(points, axes, ex) -> np.ndarray:
    """First-order distance to the analytic surface, (F^(e1/2) - 1) / |∇(F^(e1/2))| (F^(e1/2) is
    homogeneous of degree 1, so this is exact on a sphere and close to the surface)."""
    def g(p):
        return geo.superellipsoid_level(p, axes, ex) ** (ex[0] / 2)
    p = np.atleast_2d(points)
    grad = np.stack([(g(p + d) - g(p - d)) / 2e-4 for d in np.eye(3) * 1e-4], axis=1)
    return (g(p) - 1.0) / np.linalg.norm(grad, axis=1)


@pytest.mark.parametrize("ex", [(1.0, 1.0), (0.3, 0.3), (0.5, 1.5), (1.5, 0.8)])
def test_barr_volume_against_beta_and_a_grid_count(ex):
    assert geo.superellipsoid_volume(AXES, ex) == pytest.approx(barr_volume(AXES, ex), rel=1e-12)
    assert geo.superellipsoid_volume(AXES, ex) == pytest.approx(grid_volume(AXES, ex), rel=5e-3)
    if ex == (1.0, 1.0):
        assert geo.superellipsoid_volume(AXES, ex) == pytest.approx(4 / 3 * math.pi * math.prod(AXES), rel=1e-12)


@pytest.mark.parametrize("ex", [(1.0, 1.0), (0.3, 0.3), (0.6, 0.8), (1.5, 0.5)])
def test_triangulation_is_closed_outward_close_to_the_shape_and_converges(ex):
    import trimesh

    errors = []
    for tol, edge in ((0.5, 16.0), (0.1, 8.0), (0.02, 4.0)):
        v, f = superellipsoid_surface(AXES, ex, tol_mm=tol, max_edge_mm=edge)
        errors.append(abs(geo.surface_enclosed_volume(v, f) / barr_volume(AXES, ex) - 1.0))
    assert errors[0] > errors[1] > errors[2] and errors[2] < 4e-3  # ~ tol: the facets' deficit
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.euler_number == 2
    assert geo.surface_enclosed_volume(v, f) > 0.0  # outward
    np.testing.assert_allclose(geo.superellipsoid_level(v, AXES, ex), 1.0, atol=1e-9)  # vertices on it
    w = np.random.default_rng(1).dirichlet([1.0, 1.0, 1.0], size=8)
    inside = np.einsum("kj,fjd->fkd", w, v[f]).reshape(-1, 3)  # points across every triangle
    d = surface_distance(inside, AXES, ex)
    assert d.max() < 1e-6 and d.min() > -0.05  # chords lie inside a convex body, within 0.05 mm


@pytest.mark.parametrize("bend", [12.0, -20.0])
def test_bend_keeps_the_volume_and_puts_the_ends_off_the_middle(bend):
    axes, ex = (20.0, 50.0, 15.0), (0.8, 0.8)  # long axis y, bent towards x
    v, f = body_surface(axes, ex, bend)
    vol = barr_volume(axes, ex)
    assert geo.surface_enclosed_volume(v, f) == pytest.approx(vol, rel=4e-3)
    assert grid_volume(axes, ex, bend) == pytest.approx(vol, rel=5e-3)
    tips = v[np.argsort(np.abs(v[:, 1]))[-2:]]  # the ends of the long axis
    np.testing.assert_allclose(tips, [[bend, -50.0, 0.0], [bend, 50.0, 0.0]][:: 1 if tips[0, 1] < 0 else -1],
                               atol=1e-9)
    np.testing.assert_allclose(bend_points(bend_points(v, axes, bend), axes, -bend), v, atol=1e-12)


def test_loft_the_mesher_uses_holds_the_volume():
    """The smooth OpenCASCADE body (design/occ_shapes.bulb_solid) against Barr's volume."""
    from softphantom.design.mesh import gmsh_session
    from softphantom.design.occ_shapes import bulb_solid

    for ex, bend, rel in (((1.0, 1.0), 0.0, 1e-4), ((0.4, 0.7), 0.0, 1e-3), ((0.8, 0.9), 15.0, 1e-3)):
        bulb = BulbParams(semi_axes_mm=AXES, shape="superellipsoid", exponents=ex, bend_mm=bend)
        with gmsh_session("loft", "loft") as gmsh:
            tag = bulb_solid(gmsh.model.occ, bulb)
            assert gmsh.model.occ.getMass(3, tag) == pytest.approx(bulb.volume_mm3, rel=rel)


def _on_surface(direction, axes, ex, bend=0.0) -> list[float]:
    d = np.asarray(direction, float)
    p = d * geo.superellipsoid_level(d, axes, ex)[0] ** (-ex[0] / 2)
    return [float(x) for x in bend_points(p, axes, bend)[0]]


def _superbody_toml(ex=(0.7, 0.9), bend=6.0) -> str:
    """A superellipsoid phantom of its own: four arms named for the compass, aimed at it from the
    centre, five markers on its analytic surface, the urethra's inlet where its axis leaves it."""
    y = np.linspace(0.0, 40.0, 40001)
    axis = bend_points(np.column_stack([np.zeros_like(y), y, np.full_like(y, 4.0)]), AXES, -bend)
    inlet = float(y[geo.superellipsoid_level(axis, AXES, ex) < 1.0].max())
    markers = "\n".join(f"m{i} = {_on_surface(d, AXES, ex, bend)}" for i, d in enumerate(
        [(1, -0.3, 0.35), (-1, -0.3, 0.35), (0.3, 0.5, 1), (-0.3, 0.5, -1), (0.2, 1, 0.6)]))
    return f"""name = "superbody"
arm_names = ["north", "south", "east", "west"]

[bulb]
shape = "superellipsoid"
semi_axes_mm = {list(AXES)}
exponents = {list(ex)}
bend_mm = {bend}

[urethra]
inlet_mm = [0.0, {inlet}, 4.0]

[arms.north]
direction = [0.0, -0.5, 1.0]
cavity_volume_mm3 = 500.0
[arms.south]
direction = [0.0, -0.5, -1.0]
cavity_volume_mm3 = 500.0
[arms.east]
direction = [1.0, 0.6, 0.0]
cavity_volume_mm3 = 480.0
[arms.west]
direction = [-1.0, 0.6, 0.0]
cavity_volume_mm3 = 480.0

[markers]
{markers}

[targets]
t1 = [-8.0, -10.0, -6.0]
t2 = [8.0, 2.0, -8.0]
"""


@pytest.mark.slow
def test_superellipsoid_design_file_validates_round_trips_and_meshes(tmp_path):
    from softphantom.design.model import build_model

    path = tmp_path / "superbody.toml"
    path.write_text(_superbody_toml())
    d = load_design(path)
    assert d.bulb.is_surface and d.arm_names == ("north", "south", "east", "west")
    assert all(a.junction_fillet_mm == 0.0 for a in d.arms)  # a triangulated body: sharp junctions
    text = design_to_toml(d)
    assert "surface_vertices_mm" not in text and len(text) < 4000  # the parameters, not the triangles
    assert design_from_dict(design_to_dict(d)) == d
    model = build_model(d, 12.0, isolate=False)  # checks each cavity's and the bulb's meshed volume (10 %)
    assert model.element_order == 1 and model.min_dihedral_deg() > 3.0
    # the body and the urethra cavity as meshed: low by the facets' deficit at a 12 mm mesh (8 mm on the
    # surface, 2.6 %; the cavities' walls 6 %, as on the BIP), not more
    assert model.bulb_volume() * 1e9 == pytest.approx(d.bulb.volume_mm3, rel=0.035)
    assert model.bulb_volume() * 1e9 < d.bulb.volume_mm3
    for name, xyz in model.markers.items():
        assert abs(d.bulb.signed_distance(np.asarray(xyz)[None] * 1e3)[0]) < 0.1, name


def test_ellipsoid_file_unchanged_and_shape_keys_only_when_used():
    assert design_to_dict(BIPDesign())["bulb"] == {"semi_axes_mm": list(BIPDesign().bulb.semi_axes_mm)}
    assert "shape" not in design_to_toml(BIPDesign())
    axes = list(BIPDesign().bulb.semi_axes_mm)  # the BIP's own markers and arms then fit
    d = design_from_dict({"bulb": {"shape": "superellipsoid", "semi_axes_mm": axes, "exponents": [1, 1]}})
    assert design_to_dict(d)["bulb"] == {"shape": "superellipsoid", "semi_axes_mm": axes, "exponents": [1.0, 1.0],
                                         "bend_mm": 0.0}
    assert d.bulb.volume_mm3 == pytest.approx(BIPDesign().bulb.volume_mm3, rel=1e-12)


@pytest.mark.parametrize("bulb, message", [
    ({"shape": "superellipsoid", "exponents": [0.2, 1.0]}, "bulb.exponents[0] = 0.2 must be in [0.3, 1.5]"),
    ({"shape": "superellipsoid", "exponents": [1.0]}, "bulb.exponents: expected at least 2 entries"),
    ({"exponents": [0.5, 1.0]}, 'bulb.exponents = [0.5, 1.0]: only with shape = "superellipsoid"'),
    ({"bend_mm": 3.0}, 'bulb.bend_mm = 3: only with shape = "superellipsoid"'),
    ({"shape": "superellipsoid", "bend_mm": 40.0}, "bulb.bend_mm = 40 bends the body by more than its half-width "
                                                   "along z (max 29.96 mm"),
    ({"shape": "box"}, "bulb.shape: 'box' is not one of"),
    ({"shape": "superellipsoid", "surface_faces": [[0, 1, 2]]}, "bulb.surface_faces: not with shape"),
])
def test_bad_shape_is_one_line_naming_the_field(bulb, message):
    with pytest.raises(DesignError) as exc:
        design_from_dict({"bulb": bulb})
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_bad_shape_through_the_cli_is_exit_2(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[bulb]\nshape = "superellipsoid"\nexponents = [3, 1]\n')
    assert main(["design", "--config", str(cfg), "--out", str(tmp_path / "o"), "--no-png"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err and "bulb.exponents[0] = 3" in err
