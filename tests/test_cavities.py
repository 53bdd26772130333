"""Internal cavities (``[cavities.NAME]``): schema and refusals, M = 0 and M = 2 designs meshed and
solved, a pressurised spherical balloon against the thick-sphere closed form, superposition of
two cavities' pressures, and the refresh estimator with two known pressures."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from softphantom.design import geometry as geo
from softphantom.design.mesh import cavity_group_ids
from softphantom.design.model import build_model
from softphantom.design.params import (
    BIPDesign,
    CapsuleCavity,
    EllipsoidCavity,
    UrethraParams,
    design_from_dict,
    design_to_dict,
    design_to_toml,
    load_design,
)
from softphantom.errors import DesignError

COARSE = {"size_mm": 12.0, "surface_size_mm": 10.0, "arm_size_mm": 7.0, "cavity_segments": 18.0}
AXES = BIPDesign().bulb.semi_axes_mm
TUMOUR_INLET = [float(x) for x in geo.project_to_ellipsoid((-1.0, -0.3, -0.8), AXES)]
TUMOUR = {"shape": "ellipsoid", "center_mm": [-12.0, -4.0, -10.0], "semi_axes_mm": [4.0, 4.0, 4.0],
          "inlet_mm": TUMOUR_INLET}


def two_cavities(**over) -> dict:
    """The BIP's file with a tumour balloon beside its urethra."""
    return {"urethra": {}, "cavities": {"tumour": dict(TUMOUR, **over)}, "mesh": COARSE}


# --- schema -------------------------------------------------------------------------------------

def test_default_is_the_urethra_alone():
    d = BIPDesign()
    assert d.internal_cavity_names == ("urethra",) and isinstance(d.urethra, UrethraParams)
    assert d.cavity_names == (*d.arm_names, "urethra")
    out = design_to_dict(d)
    assert "cavities" not in out and "cavity_names" not in out and list(out)[:3] == ["name", "bulb", "urethra"]
    assert cavity_group_ids(d.arm_names, d.internal_cavity_names)["urethra"] == 15


def test_two_cavities_round_trip(tmp_path):
    d = design_from_dict(two_cavities())
    assert d.internal_cavity_names == ("urethra", "tumour")
    assert d.cavity_names[-2:] == ("urethra", "tumour")
    t = d.cavity("tumour")
    assert isinstance(t, EllipsoidCavity) and t.role == "actuated"
    assert d.cavity_volumes_mm3()["tumour"] == pytest.approx(4 / 3 * np.pi * 64)
    path = tmp_path / "d.toml"
    path.write_text(design_to_toml(d))
    assert load_design(path) == d
    # reordered: the file says so
    e = design_from_dict({**two_cavities(), "cavity_names": ["tumour", "urethra"]})
    assert e.internal_cavity_names == ("tumour", "urethra")
    assert design_to_dict(e)["cavity_names"] == ["tumour", "urethra"]
    assert design_from_dict(design_to_dict(e)) == e
    assert cavity_group_ids(e.arm_names, e.internal_cavity_names) == {**cavity_group_ids(), "tumour": 300}


def test_capsule_cavity_and_no_urethra():
    y_out = float(AXES[1] * np.sqrt(1 - (12.0 / AXES[0]) ** 2 - (12.0 / AXES[2]) ** 2))
    channel = {"radius_mm": 2.0, "volume_mm3": 300.0, "center_mm": [12.0, 0.0, -12.0], "axis": [0.0, 1.0, 0.0],
               "inlet_mm": [12.0, y_out, -12.0]}
    d = design_from_dict({"cavities": {"channel": channel}})  # [cavities] without [urethra]: no urethra
    assert d.internal_cavity_names == ("channel",) and d.urethra is None
    c = d.cavity("channel")
    assert isinstance(c, CapsuleCavity)
    assert c.cyl_length_mm == pytest.approx((300.0 - 4 / 3 * np.pi * 8.0) / (np.pi * 4.0))
    assert design_from_dict(design_to_dict(d)) == d
    none = design_from_dict({"cavities": {}})
    assert none.internal_cavity_names == () and none.cavity_names == none.arm_names
    assert design_from_dict(design_to_dict(none)) == none
    assert none.with_urethra(UrethraParams()).internal_cavity_names == ("urethra",)


@pytest.mark.parametrize("data, match", [
    (two_cavities(center_mm=[-2.0, 0.0, 0.0]), r"^urethra and cavities\.tumour: they overlap \(min wall 1 mm\)$"),
    (two_cavities(center_mm=[0.0, 0.0, -5.0]), r"^urethra and cavities\.tumour: 0\.\d+ mm apart"),
    (two_cavities(center_mm=[-12.0, -4.0, -25.0]), r"^cavities\.tumour: wall to the bulb surface is -?\d"),
    (two_cavities(inlet_mm=[0.0, 0.0, 0.0]), r"^cavities\.tumour\.inlet_mm is 2\d\.?\d* mm off the bulb surface"),
    (two_cavities(center_mm=[-16.0, 12.0, 0.0]), r"^arms\.back_xneg\.embed_mm = 8: the arm comes .* from the tumour "
                                                  r"cavity"),
    (two_cavities(role="sealed"), r"^cavities\.tumour\.role: 'sealed' is not one of actuated, measured$"),
    (two_cavities(shape="torus"), r"^cavities\.tumour\.shape = 'torus': expected capsule or ellipsoid$"),
    (two_cavities(radius_mm=3.0), r"^cavities\.tumour: unknown key 'radius_mm'"),
    ({"cavities": {"tumour": {k: v for k, v in TUMOUR.items() if k != "semi_axes_mm"}}},
     r"^cavities\.tumour\.semi_axes_mm: missing"),
    (two_cavities(semi_axes_mm=[4.0, -1.0, 4.0]), r"^cavities\.tumour\.semi_axes_mm\[1\] = -1 must be > 0"),
    ({"cavities": {"front_zpos": TUMOUR}}, r"^cavities\.front_zpos: an arm has this name"),
    ({"urethra": {}, "cavities": {"urethra": TUMOUR}}, r"^cavities\.urethra: the urethra is also given"),
    ({**two_cavities(), "cavity_names": ["tumour"]}, r"^cavity_names: \['tumour'\] must list each internal cavity"),
    ({**two_cavities(), "targets": {"t": [-12.0, -4.0, -9.0]}}, r"^targets\.t is inside the tumour cavity"),
])
def test_refusals(data, match):
    with pytest.raises(DesignError, match=match) as exc:
        design_from_dict(data)
    assert "\n" not in str(exc.value)


# --- mesh and FEM -------------------------------------------------------------------------------

def test_meshes_with_two_and_no_internal_cavities(two_cavities_model, no_cavities_model):
    """(The two designs are meshed once per run: conftest's ``two_cavities_model`` and ``no_cavities_model``.)"""
    two, none = two_cavities_model, no_cavities_model
    assert tuple(two.cavities) == two.design.cavity_names and tuple(none.cavities) == none.design.arm_names
    v = {k: two.cavity_volume(k) * 1e9 for k in two.cavities}
    # a sphere meshed with 18 segments around: an inscribed polyhedron, a few % low
    assert 0.9 < v["tumour"] / (4 / 3 * np.pi * 64) < 1.0
    assert 0.95 < v["urethra"] / 2078.0 < 1.0
    assert np.allclose(two.tube_inlets()["tumour"], np.asarray(TUMOUR_INLET) * 1e-3)
    # the bulb's outer volume counts the cavities inside it
    assert two.bulb_volume() == pytest.approx(none.bulb_volume(), rel=0.02)


def test_two_pressures_superpose(two_cavities_model):
    from softphantom.fem import cavity_volume, fem_from_phantom, solve_static

    fem = fem_from_phantom(two_cavities_model)
    x0 = fem.x_rest

    def dv(p):
        x = solve_static(fem, pressures=p).x
        return np.array([cavity_volume(x, fem.cavities[k]) - cavity_volume(x0, fem.cavities[k])
                         for k in ("urethra", "tumour", "front_zneg")])

    a, b, ab = dv({"urethra": 200.0}), dv({"tumour": 200.0}), dv({"urethra": 200.0, "tumour": 200.0})
    assert a[0] > 0 and b[1] > 0 and abs(a[1]) < 0.1 * b[1] and abs(b[0]) < 0.1 * a[0]
    assert np.allclose(ab, a + b, rtol=2e-3, atol=1e-4 * np.abs(ab).max())


def _sphere_in_sphere(a_mm: float, b_mm: float, h_mm: float):
    """A P2 mesh of a hollow sphere (inner radius a, outer b, mm) and its inner wall, SI."""
    from softphantom.design.mesh import GMSH_TET10, gmsh_session
    from softphantom.design.model import _orient

    with gmsh_session("hollow_sphere", "the hollow sphere") as gmsh:
        occ = gmsh.model.occ
        out, inn = occ.addSphere(0, 0, 0, b_mm), occ.addSphere(0, 0, 0, a_mm)
        occ.cut([(3, out)], [(3, inn)])
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", h_mm)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 14)  # segments around a circle
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        pos = np.zeros(int(tags.max()) + 1, np.int64)
        pos[tags.astype(np.int64)] = np.arange(len(tags))
        _, et, en = gmsh.model.mesh.getElements(3)
        tets = pos[np.asarray(en[0], np.int64)].reshape(-1, 10)[:, GMSH_TET10]
        walls = {}
        for _, s in gmsh.model.getEntities(2):
            _, _, fn = gmsh.model.mesh.getElements(2, s)
            walls[s] = pos[np.asarray(fn[0], np.int64)].reshape(-1, 6)
    nodes = np.asarray(xyz).reshape(-1, 3) * 1e-3
    r = {s: float(np.linalg.norm(nodes[t[:, 0]], axis=1).mean()) for s, t in walls.items()}
    inner = min(r, key=r.get)
    outer = np.unique(np.vstack([t for s, t in walls.items() if s != inner]))
    return nodes, tets, _orient(tets[:, :4], nodes, walls[inner], into_solid=True), outer


def test_pressurised_sphere_matches_the_thick_sphere():
    """A spherical cavity of radius a in a sphere of radius b with its outer surface held: at a
    small pressure p, u(r) = A r + B / r² with σ_rr(a) = −p and u(b) = 0 gives
    B = p / (3K / b³ + 4G / a³), u(a)/a = B (1/a³ − 1/b³), ΔV = 3 V u(a)/a (to first order); for
    b → ∞ that is Lamé's ΔV = 3 V p / (4G)."""
    from softphantom.fem import build_fem, cavity_volume, solve_static
    from softphantom.fem.laws import NeoHookean

    a, b, E, nu, p = 5e-3, 20e-3, 100e3, 0.45, 100.0
    nodes, tets, wall, outer = _sphere_in_sphere(a * 1e3, b * 1e3, 4.0)
    fem = build_fem(nodes, tets, NeoHookean(E, nu, 1000.0), fixed_nodes=outer, cavities={"balloon": wall})
    V0 = cavity_volume(fem.x_rest, wall)
    dV = cavity_volume(solve_static(fem, pressures={"balloon": p}).x, wall) - V0
    G, K = E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))
    B = p / (3 * K / b**3 + 4 * G / a**3)
    want = 3 * V0 * B * (1 / a**3 - 1 / b**3)
    assert dV == pytest.approx(want, rel=0.03)
    assert not dV == pytest.approx(3 * V0 * p / (4 * G), rel=0.03)  # the finite body is measurably stiffer


# --- estimation ---------------------------------------------------------------------------------

def test_refresh_estimate_with_two_known_pressures(two_cavities_model):
    """The truth: the equilibrium at a force and both pressures; the estimator, given the arm
    volumes and the two pressures, recovers the force (a Gauss–Newton fixed point on the volumes)."""
    from types import SimpleNamespace

    from softphantom.estimation import Estimator

    model = two_cavities_model
    est = Estimator(model)
    assert est.pressure_names == ("urethra", "tumour") and est.arm_names == model.design.arm_names
    assert est.rest.W.shape == (4, 5)
    truth = np.array([0.2, 0.8, -0.3, 3000.0, 2000.0])
    lin = est.forward.solve(truth)
    m = SimpleNamespace(t=1.0, dV=lin.V.copy(), p_urethra=float("nan"), status="ok",
                        pressures_Pa={"urethra": 3000.0, "tumour": 2000.0})
    e = est.settle(m)
    assert e.status == "ok"
    assert np.allclose(e.force, truth[:3], atol=1e-4)
    assert e.p_urethra == 3000.0 and e.extra["pressures_Pa"] == {"urethra": 3000.0, "tumour": 2000.0}
    missing = SimpleNamespace(**{**vars(m), "pressures_Pa": {"urethra": 3000.0}})
    assert est.step(missing).status.startswith("failed:the sample has no pressure of cavity tumour")
    # the tumour's pressure is a load the arms feel: taken as 0 it biases the force
    est.reset()
    wrong = est.settle(SimpleNamespace(**{**vars(m), "pressures_Pa": {"urethra": 3000.0, "tumour": 0.0}}))
    assert np.linalg.norm(wrong.force - truth[:3]) > 100 * np.linalg.norm(e.force - truth[:3])


def test_atlas_refuses_other_cavities(no_cavities_model):
    # two actuated cavities: a stack of atlases (tests/test_atlas_stack.py)
    from softphantom.errors import UserError
    from softphantom.estimation.select import open_estimator

    with pytest.raises(UserError, match=r"this design has 0: use --estimator refresh$"):
        open_estimator("atlas", no_cavities_model)


@pytest.mark.slow
def test_the_atlas_tabulates_the_one_cavity_whatever_its_name():
    """A design whose one internal cavity is a balloon named ``pelvis`` (no urethra): the atlas's
    pressure axis is that cavity's, read from each sample's ``pressures_Pa``; its inverse of a full
    solve at a known load is the load, within the small atlas's interpolation error."""
    from types import SimpleNamespace

    from softphantom.estimation import AtlasConfig, Estimator, EstimatorConfig
    from softphantom.estimation.atlas.build import build_atlas
    from softphantom.estimation.atlas.estimator import AtlasEstimator

    m = build_model(design_from_dict({"cavities": {"pelvis": TUMOUR}, "mesh": COARSE}), isolate=False)
    assert m.design.internal_cavity_names == ("pelvis",)
    cfg = EstimatorConfig(mode="sync")
    lam = np.array([0.3, 1.5, -0.2, 3e3])
    lin = Estimator(m, cfg).forward.solve(lam)
    acfg = AtlasConfig(force_min_N=(-0.5, 0.5, -0.5), force_max_N=(0.5, 2.0, 0.5), p_min_kPa=-2, p_max_kPa=8,
                       n_force=(3, 3, 3), n_pressure=2, linear_pressure=True)  # one plane: 27 solves
    at = AtlasEstimator(m, cfg, build_atlas(m, cfg, acfg, n_workers=1, processes=False))
    assert at.cavity == "pelvis"
    e = at.step(SimpleNamespace(t=0.0, dV=lin.V, p_urethra=float("nan"), pressures_Pa={"pelvis": 3e3}, status="ok"))
    assert e.status == "ok" and np.allclose(e.force, lam[:3], atol=0.05), e.force
    assert e.pressures_Pa == {"pelvis": 3e3}
    # the pressure is the sample's, not a default: 20 kPa is beyond the atlas's 8 kPa face
    off = at.step(SimpleNamespace(t=0.1, dV=lin.V, p_urethra=float("nan"), pressures_Pa={"pelvis": 20e3}, status="ok"))
    assert e.in_envelope and not off.in_envelope and off.pressures_Pa == {"pelvis": 20e3}


# --- the stages that read the urethra alone so far: one line each -------------------------------

def test_the_molds_core_every_internal_cavity():
    # a core per cavity, checked against its cavity on the example organs: tests/test_molds_organs.py
    from softphantom.molds.parts import build_parts

    d = design_from_dict({**two_cavities(), "molds": {"segments": 24.0}})
    cores = [p for p in build_parts(d, bulb_only=True) if p.kind == "core"]
    assert [p.name for p in cores] == ["urethra_core", "tumour_core"]
    # the tumour's: its 4 mm ball (just inside its rim across the rod, not just outside it opposite
    # the rod) and its rod at the inlet, clear of the urethra
    t = d.cavity("tumour")
    c, u = np.asarray(t.center_mm), geo.unit(np.subtract(t.inlet_mm, t.center_mm))
    side = geo.orthonormal_frame(u)[0]
    assert cores[1].mesh.contains([c, c + 3.8 * side, t.inlet_mm]).all()
    assert not cores[1].mesh.contains([c - 4.2 * u, c + 4.2 * side]).any()
    assert float(np.min(d.urethra.signed_distance(cores[1].mesh.vertices))) > 1.0


def test_observability_of_two_pressures(two_cavities_model):
    from softphantom.estimation.observability import observability, observability_md

    obs = observability(two_cavities_model, loaded=False)
    assert obs.ranges.shape == (5,) and obs.ranges[3] == obs.ranges[4]
    assert obs.rest.J.shape == (4, 5) and len(obs.rest.sv_mm3) == 4
    md = observability_md(obs)
    assert "`sv1..4`: force and the pressures of urethra, tumour" in md and "| sv4_mm3 | cond |" in md
    assert "p_urethra 42 kPa, p_tumour 42 kPa" in md and "p_tumour +" in md  # each pressure by its cavity's name


def test_the_documented_example_is_valid():
    import re
    import tomllib
    from pathlib import Path

    text = (Path(__file__).parents[1] / "docs" / "architecture.md").read_text(encoding="utf-8")
    block = re.search(r"```toml\n(\[urethra\].*?)```", text, re.S).group(1)
    d = design_from_dict(tomllib.loads(block))
    assert d.internal_cavity_names == ("urethra", "tumour", "channel")


def test_simulate_takes_each_cavitys_pressure(tmp_path, capsys, two_cavities_model):
    """``simulate --pressure-kPa tumour=0.2`` is the FEM's solve at 200 Pa in the tumour alone; a
    cavity the model lacks, a malformed value, or the urethra given twice is one line, exit 2."""
    import json

    from softphantom.cli import main
    from softphantom.design import save_model
    from softphantom.fem import cavity_volume, fem_from_phantom, solve_static

    model = two_cavities_model
    save_model(model, tmp_path / "m")
    assert main(["simulate", "--model", str(tmp_path / "m"), "--pressure-kPa", "tumour=0.2", "--out",
                 str(tmp_path / "s")]) == 0
    res = json.loads((tmp_path / "s" / "result.json").read_text())
    fem = fem_from_phantom(model)
    x = solve_static(fem, pressures={"tumour": 200.0}).x
    want = (cavity_volume(x, fem.cavities["tumour"]) - cavity_volume(fem.x_rest, fem.cavities["tumour"])) * 1e9
    assert res["pressures_kPa"] == {"tumour": 0.2} and res["dV_mm3"]["tumour"] == pytest.approx(want, rel=1e-6)
    capsys.readouterr()
    for args, word in ((["--pressure-kPa", "tumor=1"], "not an internal cavity of this model (urethra, tumour)"),
                       (["--pressure-kPa", "tumour"], "expected CAVITY=KPA"),
                       (["--urethra-kPa", "1", "--pressure-kPa", "urethra=1"], "given twice")):
        assert main(["simulate", "--model", str(tmp_path / "m"), *args, "--out", str(tmp_path / "t")]) == 2
        err = capsys.readouterr().err.strip()
        assert word in err and err.count("\n") == 0, err


@pytest.mark.slow
def test_a_sweep_variant_of_a_design_with_two_cavities():
    """``sweep`` evaluates a design of two internal cavities: its equilibrium takes both pressures
    (0 at the probe loads), its columns follow the design's arms."""
    from softphantom.design.params import design_to_dict
    from softphantom.study import evaluate_variant
    from softphantom.study.config import EvalSettings, SweepConfig

    base = design_to_dict(design_from_dict(two_cavities()))
    cfg = SweepConfig(name="t", method="grid", samples=1, base=base, settings=EvalSettings(directions=("ypos",)))
    r = evaluate_variant(cfg.resolve(0, {}))
    assert r["status"] == "ok", r["error"]
    assert all(r[f"count_{a}_mm3"] > 0 for a in BIPDesign().arm_names) and r["obs_sv_min_mm3"] > 0
    assert 0 < r["res_force_worst_N"] < 0.1
