"""The tagged tetra mesh: volumes against the design, validity, closed oriented cavities, files."""

from __future__ import annotations

import threading

import meshio
import numpy as np
import pytest

from softphantom.design import ARM_NAMES, BIPDesign, build_model, load_model, save_model
from softphantom.design import geometry as geo
from softphantom.design.model import MM

MIN_DIHEDRAL_BOUND_DEG = 5.0  # the default mesh reaches ~10°; gmsh's optimiser keeps slivers out


def _outside_bulb(m):
    """Bulb-region tets whose centroid lies outside the ellipsoid: (mask over the bulb's tets,
    whether each is explained by a junction fillet: within radius + fillet of an arm's axis and
    less than a radius above its root)."""
    d = m.design
    in_bulb = m.tet_region == m.regions["bulb"]
    c = m.nodes[m.tets[in_bulb]].mean(axis=1) / MM
    out = geo.ellipsoid_level(c, np.asarray(d.bulb.semi_axes_mm)) >= 1.0
    near = np.zeros(len(c), bool)
    for g in d.arm_geometry():
        t = (c - g.root_mm) @ g.direction
        rad = np.linalg.norm(c - g.root_mm - np.outer(t, g.direction), axis=1)
        near |= (g.fillet_mm > 0) & (rad <= g.radius_mm + g.fillet_mm) & (t < g.radius_mm)
    return in_bulb, out, near


def test_meshed_volumes_match_the_design(default_model):
    m = default_model
    d = m.design
    assert d.arms[0].junction_fillet_mm == 2.0  # the default design rounds its arm junctions
    # the bulb region also holds the fillets and the arms' first millimetres (docs/architecture.md):
    # its part inside the ellipsoid, with the urethra, is the design's bulb; an inscribed polyhedron
    # can only lose volume on convex walls
    in_bulb, out, _ = _outside_bulb(m)
    inside = (m.tet_volumes()[in_bulb][~out].sum() + m.cavity_volume("urethra")) / MM**3
    assert inside == pytest.approx(d.bulb.volume_mm3, rel=0.01) and inside < d.bulb.volume_mm3
    assert m.bulb_volume() / MM**3 == pytest.approx(inside, rel=1e-12)
    assert m.junction_volume() / MM**3 > 4 * 100.0  # each fillet ring and arm stub adds ≈ 400 mm³
    for name, v in d.cavity_volumes_mm3().items():
        assert m.cavity_volume(name) / MM**3 == pytest.approx(v, rel=0.03), name
    assert 3000 < len(m.nodes) < 9000  # "about 6 000 nodes"


def test_tets_positive_and_quality(default_model):
    m = default_model
    vol = m.tet_volumes()
    assert vol.min() > 0.0
    mean_edge = np.cbrt(vol.mean() * 6 * np.sqrt(2))
    assert vol.min() > 1e-4 * mean_edge**3  # no degenerate tets
    assert m.min_dihedral_deg() > MIN_DIHEDRAL_BOUND_DEG
    assert np.unique(m.tets).size == len(m.nodes)  # no orphan nodes


def _directed_edges(tris):
    return np.vstack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])


def _assert_closed_and_consistent(tris, label):
    e = _directed_edges(tris)
    und = np.sort(e, axis=1)
    _, counts = np.unique(und, axis=0, return_counts=True)
    assert (counts == 2).all(), f"{label}: an edge not shared by exactly two triangles"
    _, dcounts = np.unique(e, axis=0, return_counts=True)
    assert (dcounts == 1).all(), f"{label}: inconsistent orientation"


def test_cavity_surfaces_closed_oriented_positive(default_model):
    m = default_model
    assert list(m.cavities) == [*ARM_NAMES, "urethra"]
    for name, tris in m.cavities.items():
        _assert_closed_and_consistent(tris, name)
        assert m.cavity_volume(name) > 0.0
        # normals point out of the air into the silicone: away from the cavity centre
        x = m.nodes[tris]
        n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
        c = m.nodes[np.unique(tris)].mean(axis=0)
        assert (np.einsum("ij,ij->i", n, x.mean(axis=1) - c) > 0).mean() > 0.99


def test_conforming_boundary_is_exactly_the_tagged_surfaces(default_model):
    m = default_model
    t = m.tets
    faces = np.sort(np.vstack([t[:, [1, 2, 3]], t[:, [0, 2, 3]], t[:, [0, 1, 3]], t[:, [0, 1, 2]]]), axis=1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2  # every interior face shared by two tets: bulb and arms are conforming
    boundary = {tuple(f) for f in uniq[counts == 1]}
    tagged = [m.outer_faces, m.fixed_faces, *m.cavities.values()]
    tagged_set = {tuple(f) for tr in tagged for f in np.sort(tr, axis=1)}
    assert boundary == tagged_set and sum(len(x) for x in tagged) == len(boundary)
    # bulb and arms share nodes at their interface
    bulb_nodes = set(np.unique(t[m.tet_region == m.regions["bulb"]]).tolist())
    for name in ARM_NAMES:
        arm_nodes = set(np.unique(t[m.tet_region == m.regions[f"arm_{name}"]]).tolist())
        assert len(arm_nodes & bulb_nodes) > 20


def test_divergence_theorem_on_the_whole_solid(default_model):
    m = default_model
    closed = np.vstack([m.outer_faces, m.fixed_faces])
    _assert_closed_and_consistent(closed, "outer+fixed")
    enclosed = geo.surface_enclosed_volume(m.nodes, closed)
    cavities = sum(m.cavity_volume(n) for n in m.cavities)
    assert enclosed - cavities == pytest.approx(m.tet_volumes().sum(), rel=1e-10)


def test_regions_fixed_faces_and_points(default_model):
    m = default_model
    d = m.design
    axes_m = np.asarray(d.bulb.semi_axes_mm) * MM
    centroids = m.nodes[m.tets].mean(axis=1)
    level = geo.ellipsoid_level(centroids, axes_m)
    assert set(np.unique(m.tet_region)) == set(m.regions.values())
    _, out, near = _outside_bulb(m)
    assert out.sum() > 0 and near[out].all()  # outside the ellipsoid only at the rounded junctions
    assert level[m.tet_region != m.regions["bulb"]].min() > 1.0
    for g in d.arm_geometry():
        # each arm's end face: its nodes on the end plane, inside the arm radius
        on_plane = np.abs((m.nodes[m.fixed_nodes] - g.end_mm * MM) @ g.direction) < 1e-9
        sel = m.nodes[m.fixed_nodes[on_plane]]
        assert len(sel) > 10
        assert np.linalg.norm(sel - g.end_mm * MM, axis=1).max() <= g.radius_mm * MM * (1 + 1e-9)
    assert np.array_equal(m.fixed_nodes, np.unique(m.fixed_faces))
    for name, xyz in d.markers:
        np.testing.assert_allclose(m.markers[name], np.asarray(xyz) * MM)
    np.testing.assert_allclose(m.p_ext["on-centre"], [0.0, -0.025, 0.0])
    assert set(m.targets) == {n for n, _ in d.targets} and "near_urethra" in m.targets


def test_round_trip_files(default_model, tmp_path):
    save_model(default_model, tmp_path)
    back = load_model(tmp_path)
    assert back == default_model
    save_model(back, tmp_path / "again")  # written again from what was read: the same bytes
    for f in ("model.msh", "model.vtu", "model.npz", "design.toml"):
        assert (tmp_path / "again" / f).read_bytes() == (tmp_path / f).read_bytes(), f
    vtu = meshio.read(tmp_path / "model.vtu")
    np.testing.assert_array_equal(vtu.points, default_model.nodes)
    msh = meshio.read(tmp_path / "model.msh")
    np.testing.assert_allclose(msh.points, default_model.nodes, rtol=1e-15, atol=1e-15)
    assert sum(len(c.data) for c in msh.cells if c.type == "tetra") == len(default_model.tets)
    assert set(msh.field_data) >= {"bulb", "cavity_urethra", "cavity_front_zpos", "fixed", "outer"}


@pytest.mark.slow
def test_deterministic_off_main_thread_with_one_distance_field_per_wall_size(coarse_model, tmp_path, monkeypatch):
    """The model's design alone reproduces its mesh, node for node and byte for byte in the files,
    meshed again in a thread (not the main one) of this process; and there with a distance field
    per cavity instead of one per wall size (the default design's four arm cavities share a size: a
    third of the size-field work, docs/performance/design-fem.md), which must not change the mesh."""
    from softphantom.design import mesh as mesh_mod

    d = coarse_model.design
    assert d.mesh != BIPDesign().mesh  # the model's design records its mesh sizes
    sizes = {n: d.mesh.cavity_size_mm(r) for n, r in
             [*((g.name, g.cavity_radius_mm) for g in d.arm_geometry()), ("urethra", d.urethra.radius_mm)]}
    assert [names for _, names in mesh_mod._walls_by_size(sizes)] == [list(ARM_NAMES), ["urethra"]]
    apart: list = []
    monkeypatch.setattr(mesh_mod, "_walls_by_size", lambda s: apart.append(s) or [(h, [n]) for n, h in s.items()])
    box: dict = {}
    th = threading.Thread(target=lambda: box.setdefault("m", build_model(d)))
    th.start()
    th.join()
    again = box["m"]
    assert apart and again == coarse_model  # meshed in this process, a field per cavity
    save_model(coarse_model, tmp_path / "a")
    save_model(again, tmp_path / "b")
    for f in ("model.msh", "model.vtu", "design.toml"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f


def test_meshing_keeps_sigpipe_ignored(tmp_path):
    """gmsh.initialize resets SIGPIPE to 'terminate'; after meshing, a write to a closed pipe must
    still be an EPIPE error in this process (the live page and the stream rely on it). Meshed in
    this process (build_model meshes in a child process on a main thread): gmsh_session, the one
    entry to gmsh of the mesher and the molds, on a box."""
    import os
    import signal

    import gmsh

    from softphantom.design.mesh import gmsh_session

    assert not gmsh.isInitialized()  # gmsh_session initializes it here (and finalizes it after)
    with gmsh_session("sigpipe_box", "the SIGPIPE test") as g:
        g.model.occ.addBox(0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
        g.model.occ.synchronize()
        g.model.mesh.generate(3)
        assert len(g.model.mesh.getNodes()[0]) > 8
    assert signal.getsignal(signal.SIGPIPE) == signal.SIG_IGN
    r, w = os.pipe()
    os.close(r)
    try:
        with pytest.raises(BrokenPipeError):
            os.write(w, b"x")  # with SIGPIPE at its default the process would die here
    finally:
        os.close(w)


def _outer_edge_mm(m, near, radius_mm):
    """Mean edge length (mm) of the outer triangles with a corner within ``radius_mm`` of ``near``."""
    t = m.outer_faces
    x = m.nodes[t] / MM
    sel = np.linalg.norm(x - near, axis=2).min(axis=1) < radius_mm
    e = np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2)
    return float(e[sel].mean()), int(sel.sum())


def _junction_nodes(m):
    """Outer nodes on the bulb's ellipsoid and on an arm's cylinder: the arm–bulb edges."""
    d = m.design
    x = m.nodes[np.unique(m.outer_faces)] / MM
    on_bulb = np.abs(((x / np.asarray(d.bulb.semi_axes_mm)) ** 2).sum(1) - 1) < 1e-6
    on_arm = np.zeros(len(x), bool)
    for g in d.arm_geometry():
        a = (g.end_mm - g.start_mm) / np.linalg.norm(g.end_mm - g.start_mm)
        r = x - g.start_mm
        on_arm |= np.abs(np.linalg.norm(r - np.outer(r @ a, a), axis=1) - g.radius_mm) < 1e-6
    return int((on_bulb & on_arm).sum())


@pytest.mark.slow
def test_local_refinements_shrink_elements_only_where_asked(sharp_coarse_model):
    import dataclasses

    from softphantom.design import MeshParams
    from softphantom.errors import DesignError

    base = MeshParams().scaled_to(12.0)  # the coarse model's sizes: surface 8 mm, arms 6 mm
    # sharp junctions: a fillet's edges are meshed at its radius (2 mm) anyway
    coarse_model = sharp_coarse_model
    sharp = coarse_model.design
    assert sharp.mesh == base and {a.junction_fillet_mm for a in sharp.arms} == {0.0}
    fine = build_model(dataclasses.replace(sharp, mesh=dataclasses.replace(base, contact_size_mm=2.0,
                                                                          junction_size_mm=1.5)), isolate=False)
    p = BIPDesign().p_ext_mm()
    for name in ("on-centre", "off-centre"):
        h0, n0 = _outer_edge_mm(coarse_model, p[name], 8.0)
        h1, n1 = _outer_edge_mm(fine, p[name], 8.0)
        assert h0 > 4.0 and h1 < 3.0 and n1 > 4 * n0, (name, h0, h1)
    # far from both points and from the arms (the back pole) the surface keeps its size
    far = np.array([0.0, BIPDesign().bulb.semi_axes_mm[1], 0.0])
    assert min(np.linalg.norm(far - q) for q in p.values()) > 20
    h0, _ = _outer_edge_mm(coarse_model, far, 10.0)
    h1, _ = _outer_edge_mm(fine, far, 10.0)
    assert abs(h1 / h0 - 1) < 0.25, (h0, h1)
    # the arm–bulb edges: about 2π r / 1.5 mm nodes each instead of 2π r / 6 mm
    j0, j1 = _junction_nodes(coarse_model), _junction_nodes(fine)
    assert j0 >= 4 * 3 and j1 > 3 * j0, (j0, j1)
    with pytest.raises(DesignError, match=r"mesh.contact_size_mm = -1 must be >= 0"):
        MeshParams(contact_size_mm=-1.0)
