"""Quadratic (10-node) tetrahedra: quadrature exactness, the P2 patch test, curved cavity volumes and
their exact gradient / pressure load / tangent, consistent contact-patch loads, probes, quadratic
Newton convergence, thick-walled sphere inflation against a hyperelastic shooting reference, and
much less locking than P1 at ν = 0.49."""

import math

import gmsh
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
import scipy.sparse.linalg

from softphantom.fem import (
    ContactPatch,
    Corotational,
    NeoHookean,
    build_fem,
    cavity_volume,
    cavity_volume_gradient,
    free_tangent,
    internal_force,
    pressure_load,
    pressure_load_tangent,
    probe_matrix,
    solve_static,
)
from softphantom.fem.elements import tet_rule, tet_shape, tri_rule
from softphantom.fem.meshes import box_mesh, quadratic_mesh


def _tet_monomial(a, b, c):
    return math.factorial(a) * math.factorial(b) * math.factorial(c) / math.factorial(a + b + c + 3)


def test_quadrature_rules_are_exact_for_their_degree():
    for degree in (1, 2):
        xi, w = tet_rule(degree)
        for a in range(degree + 1):
            for b in range(degree + 1 - a):
                for c in range(degree + 1 - a - b):
                    q = np.sum(w * xi[:, 0] ** a * xi[:, 1] ** b * xi[:, 2] ** c)
                    assert abs(q - _tet_monomial(a, b, c)) < 1e-15
    xi, w = tet_rule(2)
    assert abs(np.sum(w * xi[:, 0] ** 3) - _tet_monomial(3, 0, 0)) > 1e-5  # degree 2, not 3
    st, w = tri_rule()
    for a in range(5):
        for b in range(5 - a):
            exact = math.factorial(a) * math.factorial(b) / math.factorial(a + b + 2)
            assert abs(np.sum(w * st[:, 0] ** a * st[:, 1] ** b) - exact) < 1e-14
    # shape functions: partition of unity, Kronecker at the nodes
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [.5, 0, 0], [.5, .5, 0], [0, .5, 0],
                      [0, 0, .5], [.5, 0, .5], [0, .5, .5]])
    N, _ = tet_shape(2, nodes)
    assert np.allclose(N, np.eye(10), atol=1e-15)


def _p2_box(div=(2, 2, 2), size=(0.02, 0.02, 0.02)):
    X, T = box_mesh(size, div)
    return quadratic_mesh(X, T)


@pytest.mark.parametrize("law", [Corotational(1e5, 0.45), NeoHookean(1e5, 0.45)])
def test_p2_patch_test_reproduces_a_linear_field(law):
    X, T = _p2_box((3, 2, 2))
    rng = np.random.default_rng(4)
    # curved-free mesh, but with interior nodes moved off the grid (still straight-sided)
    lo, hi = X.min(0), X.max(0)
    bnd = np.flatnonzero(np.any(np.isclose(X, lo) | np.isclose(X, hi), axis=1))
    A = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    b = 1e-3 * rng.standard_normal(3)
    x0 = X @ A.T + b
    fem = build_fem(X, T, law, fixed_nodes=bnd)
    start = X.copy()
    start[bnd] = x0[bnd]
    sol = solve_static(fem, x0=start, solver="splu")
    assert sol.converged
    assert np.abs(sol.x - x0).max() < 1e-10


def test_p2_volume_gradient_pressure_load_and_tangent():
    # closed 6-node surface of a P2 box, nodes perturbed (curved triangles)
    X, T = _p2_box((2, 2, 2))
    fem = build_fem(X, T)
    faces = fem.boundary_faces
    assert faces.shape[1] == 6
    rng = np.random.default_rng(3)
    x = X + 5e-4 * rng.standard_normal(X.shape)
    # outward normals of the solid box: Φ is the box volume (no curvature at rest)
    assert abs(cavity_volume(X, faces) - 0.02**3) < 1e-18
    # the enclosed volume of the perturbed quadratic surface equals the volume of the P2 tets'
    # isoparametric map (det J of degree 3: integrated here by a Duffy-collapsed 5³ Gauss rule)
    g5, w5 = np.polynomial.legendre.leggauss(5)
    g5, w5 = 0.5 * (g5 + 1), 0.5 * w5
    u, v, t = (a.ravel() for a in np.meshgrid(g5, g5, g5, indexing="ij"))
    wq = np.einsum("i,j,k->ijk", w5, w5, w5).ravel() * (1 - u) ** 2 * (1 - v)
    xi = np.column_stack([u, v * (1 - u), t * (1 - u) * (1 - v)])
    _, dN = tet_shape(2, xi)
    vol = sum(np.dot(wq, np.linalg.det(np.einsum("ai,qaj->qij", x[tet], dN))) for tet in T)
    assert abs(cavity_volume(x, faces) - vol) < 1e-12 * vol
    g = cavity_volume_gradient(x, faces, len(X))
    f = pressure_load(x, faces, len(X))
    assert np.abs(g - f).max() < 1e-12 * np.abs(g).max()  # closed surface: load = ∂Φ/∂x
    h = 1e-7
    d = rng.standard_normal(x.size)
    fd = (cavity_volume(x.reshape(-1) + h * d, faces) - cavity_volume(x.reshape(-1) - h * d, faces)) / (2 * h)
    assert abs(fd - g @ d) < 1e-7 * abs(fd)
    K = pressure_load_tangent(x, faces, len(X))
    fdK = (pressure_load(x.reshape(-1) + h * d, faces, len(X)) - pressure_load(x.reshape(-1) - h * d, faces, len(X))) / (2 * h)
    assert np.abs(K @ d - fdK).max() < 1e-6 * np.abs(fdK).max()
    assert abs(K - K.T).max() < 1e-12 * abs(K).max()  # closed surface: Hessian of Φ


def test_contact_patch_consistent_loads_p1_and_p2():
    X, T = box_mesh((0.02, 0.02, 0.02), (4, 4, 4))
    X2, T2 = quadratic_mesh(X, T)
    top = np.array([0.01, 0.01, 0.02])
    for Xm, Tm in ((X, T), (X2, T2)):
        fem = build_fem(Xm, Tm)
        # a patch covering the whole outer surface (centre inside, radius beyond every corner): the
        # consistent loads of a uniform traction: P1 area/3 per corner, P2 zero at corners and
        # area/3 at mid-edge nodes
        H = ContactPatch((0.01, 0.01, 0.01), 0.0175).load_matrix(fem)
        fz = H[:, 2].toarray().ravel()[2::3]
        assert abs(fz.sum() - 1.0) < 1e-12
        faces = fem.boundary_faces
        p = Xm[faces[:, :3]]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        expect = np.zeros(len(Xm))
        if faces.shape[1] == 3:
            np.add.at(expect, faces.reshape(-1), np.repeat(area / 3, 3))
        else:
            np.add.at(expect, faces[:, 3:].reshape(-1), np.repeat(area / 3, 3))
        expect /= area.sum()
        assert np.abs(fz - expect).max() < 1e-12
        # a 4 mm patch: load centred on the point, total exactly 1 N
        H = ContactPatch(top, 0.004).load_matrix(fem)
        w = H[:, 0].toarray().ravel()[0::3]
        assert abs(w.sum() - 1.0) < 1e-12
        assert np.abs((w @ Xm) - top).max() < 1e-4
    with pytest.raises(Exception, match="no outer surface within"):
        ContactPatch((0.01, 0.01, 0.05), 0.004).load_matrix(fem)
    assert ContactPatch.preset("needle", top).radius_m == 1.3e-3
    assert ContactPatch.preset("finger", top).radius_m == 8e-3


def test_probe_on_p2_is_exact_for_quadratic_fields():
    X, T = _p2_box((2, 2, 2))
    fem = build_fem(X, T)
    rng = np.random.default_rng(8)
    pts = 0.02 * rng.uniform(0.05, 0.95, (10, 3))
    P = probe_matrix(fem, pts)
    # a quadratic displacement field is reproduced exactly at any point
    field = lambda y: np.column_stack([y[:, 0] ** 2, y[:, 1] * y[:, 2], y[:, 0] + y[:, 2] ** 2])  # noqa: E731
    x = X + field(X)
    assert np.abs(P @ x - (pts + field(pts))).max() < 1e-14


def test_quadratic_newton_convergence_large_strain_p2():
    X, T = _p2_box((3, 1, 1), (0.03, 0.01, 0.01))
    fem = build_fem(X, T, NeoHookean(1e5, 0.45), fixed_nodes=np.flatnonzero(X[:, 0] < 1e-12))
    tip = np.flatnonzero(X[:, 0] > 0.03 - 1e-12)
    f = np.zeros(fem.n_dof)
    f[3 * tip + 2] = -2.0 / tip.size  # a large bending load: tip moves about half the length
    sol = solve_static(fem, f, solver="splu")
    assert sol.converged and -sol.u[tip, 2].mean() > 0.01
    # from a perturbed equilibrium, plain Newton shows quadratic convergence
    x = sol.x.reshape(-1).copy()
    free = fem.free_dofs
    x[free] += 2e-6 * np.random.default_rng(1).standard_normal(free.size)
    res = []
    for _ in range(4):
        r = (internal_force(fem, x) - f)[free]
        res.append(np.linalg.norm(r))
        x[free] -= scipy.sparse.linalg.spsolve(free_tangent(fem, x).tocsc(), r)
    # r_{k+1} ≈ C r_k²: each step squares the (relative) residual until round-off
    rel = np.array(res) / res[0]
    assert rel[1] < 1e-2 and rel[2] < 10 * rel[1] ** 2 and rel[2] < 1e-6, rel


# --- the phantom with 10-node tets ------------------------------------------------------------------

@pytest.fixture(scope="module")
def p2_model(coarse_p2_model):
    """The default design at 12 mm with 10-node tets (shared, conftest)."""
    return coarse_p2_model


def _capsule_distance(p, a, b):
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


@pytest.mark.slow
def test_p2_phantom_mid_nodes_on_the_cad_and_volumes(p2_model):
    m = p2_model
    d = m.design
    assert m.element_order == 2 and m.tets10.shape == (len(m.tets), 10)
    assert np.array_equal(m.tets10[:, :4], m.tets) and m.tets.max() < m.n_corner_nodes
    segs = {g.name: (g.cavity_segment_mm, g.cavity_radius_mm) for g in d.arm_geometry()}
    segs["urethra"] = (d.urethra.segment_mm, d.urethra.radius_mm)
    for name, ((a, b), r) in segs.items():
        mid = m.nodes[np.unique(m.cavities6[name][:, 3:])] * 1e3
        assert np.abs(_capsule_distance(mid, np.asarray(a), np.asarray(b)) - r).max() < 1e-6, name
        # curved walls: the P2 cavity volume is the design's to 0.1 %, the P1 one errs low by ~6 %
        v2 = cavity_volume(m.nodes, m.cavities6[name]) * 1e9
        v1 = cavity_volume(m.nodes, m.cavities[name]) * 1e9
        design = d.cavity_volumes_mm3()[name]
        assert abs(v2 / design - 1) < 2e-3 and v1 / design - 1 < -0.03, (name, v1, v2)
    # outer faces of the bulb away from the arm junctions (fillets meet it tangentially): mid
    # nodes on the ellipsoid
    ax = np.asarray(d.bulb.semi_axes_mm) * 1e-3
    on = np.abs(((m.nodes / ax) ** 2).sum(1) - 1) < 1e-9
    c = m.nodes[m.outer_faces6[:, :3]].mean(axis=1) * 1e3
    for g in d.arm_geometry():
        t = (c - g.root_mm) @ g.direction
        near = (np.linalg.norm(c - g.root_mm - np.outer(t, g.direction), axis=1) < g.radius_mm + g.fillet_mm + 1.0) \
            & (t > -g.radius_mm)
        on[np.unique(m.outer_faces6[near])] = False
    f6 = m.outer_faces6[np.all(on[m.outer_faces6[:, :3]], axis=1)]
    assert len(f6) > 50 and np.abs(((m.nodes[f6[:, 3:]] / ax) ** 2).sum(-1) - 1).max() < 1e-9
    # the fixed arm ends clamp their mid-edge nodes too
    assert set(np.unique(m.fixed_faces6).tolist()) == set(m.fixed_nodes.tolist())


@pytest.mark.slow
def test_p2_phantom_round_trip_solve_and_vtu(p2_model, tmp_path):
    import meshio

    from softphantom.design import load_model, save_model
    from softphantom.fem import fem_from_phantom, force_actuator, gravity_load
    from softphantom.fem.io import write_deformed_vtu

    m = p2_model
    save_model(m, tmp_path / "m")
    back = load_model(tmp_path / "m")
    assert back == m and back.element_order == 2
    vtu = meshio.read(tmp_path / "m" / "model.vtu")
    assert {c.type for c in vtu.cells} == {"tetra10", "triangle6"}
    msh = meshio.read(tmp_path / "m" / "model.msh")
    t10 = np.vstack([c.data for c in msh.cells if c.type == "tetra10"])
    assert np.array_equal(np.sort(t10, axis=0), np.sort(np.vstack(
        [m.tets10[m.tet_region == r] for r in m.regions.values()]), axis=0))

    fem = fem_from_phantom(m, NeoHookean(142.3e3, 0.45, 1070.0))
    assert fem.order == 2 and fem.n_nodes == len(m.nodes)
    g = gravity_load(fem).reshape(-1, 3)
    assert abs(g[:, 2].sum() + 9.81 * 1070.0 * fem.wq.sum()) < 1e-9  # consistent load: total weight
    fem1 = fem_from_phantom(m, order=1)  # a P1 model on the corner nodes of the same mesh
    assert fem1.n_nodes == m.n_corner_nodes and fem1.order == 1
    H = force_actuator(fem, m.p_ext["on-centre"], radius=4e-3)
    sol = solve_static(fem, H @ np.array([0.0, 1.0, 0.0]))
    assert sol.converged and 0.5e-3 < sol.u[:, 1].max() < 10e-3
    P = probe_matrix(fem, list(m.markers.values()))
    assert np.isfinite(P @ sol.x).all()
    path = write_deformed_vtu(tmp_path / "d.vtu", fem, sol.x, m.tet_region)
    out = meshio.read(path)
    assert out.cells[0].type == "tetra10" and np.isfinite(out.cell_data["von_mises_kPa"][0]).all()


@pytest.mark.slow
def test_simulate_cavity_dv_of_a_p2_model_is_the_curved_volume(p2_model, tmp_path, capsys):
    """`softphantom simulate` on a P2 model: ΔV of every cavity is that of the 6-node (curved)
    triangles on the deformed 10-node mesh, recomputed here with the independent degree-5 rule of
    tests/reference/felupe_bip.py from deformed.vtu (it once used the straight 3-node triangles)."""
    import json
    import sys
    from pathlib import Path

    import meshio

    from softphantom.cli import main
    from softphantom.design import save_model

    sys.path.insert(0, str(Path(__file__).resolve().parent / "reference"))
    from felupe_bip import cavity_volumes

    m = p2_model
    save_model(m, tmp_path / "m")
    rc = main(["simulate", "--model", str(tmp_path / "m"), "--force-N", "0,1,0", "--urethra-kPa", "10",
               "--out", str(tmp_path / "sim")])
    assert rc == 0, capsys.readouterr().out
    dV = json.loads((tmp_path / "sim" / "result.json").read_text())["dV_mm3"]
    vtu = meshio.read(tmp_path / "sim" / "deformed.vtu")
    assert len(vtu.points) == len(m.nodes)
    x = m.nodes + vtu.point_data["displacement_mm"] * 1e-3

    class Mesh:  # what cavity_volumes reads
        cavities = m.cavities6

    v1, v0 = cavity_volumes(Mesh, x), cavity_volumes(Mesh, m.nodes)
    assert set(dV) == set(m.cavities6)
    assert dV["urethra"] > 100.0  # inflated: ~10 % of its volume
    for k in dV:
        ref = (v1[k] - v0[k]) * 1e9
        # vtu displacements are float64 mm; the two rules are exact for these integrands
        assert abs(dV[k] - ref) <= 1e-6 * max(abs(ref), 1.0), (k, dV[k], ref)
    # and that differs from the straight-triangle ΔV the command printed before
    flat = (cavity_volume(x, m.cavities["urethra"]) - cavity_volume(m.nodes, m.cavities["urethra"])) * 1e9
    assert abs(flat - dV["urethra"]) > 0.01 * dV["urethra"]


# --- thick-walled sphere inflation: P2 FE against a hyperelastic shooting reference -------------------

def sphere_shooting_reference(A, B, mu, lam, p):
    """Deformed inner radius of a compressible neo-Hookean thick sphere (radii A < B) under inner
    pressure p: the radial equilibrium ODE dP_r/dR + 2 (P_r − P_θ)/R = 0 in the reference
    configuration, integrated from A with P_r(A) = −p λ_θ(A)² (Cauchy σ_r = −p on the deformed
    wall) and shot on r(A) until P_r(B) = 0. Nominal stresses P_r = μ λ_r + (λ ln J − μ)/λ_r,
    P_θ = μ λ_θ + (λ ln J − μ)/λ_θ, J = λ_r λ_θ²."""

    def Pr(lr, lt):
        return mu * lr + (lam * np.log(lr * lt * lt) - mu) / lr

    def Pt(lr, lt):
        return mu * lt + (lam * np.log(lr * lt * lt) - mu) / lt

    def rhs(R, y):
        r, lr = y
        lt = r / R
        dPr_dlr = mu + (lam * (1 - np.log(lr * lt * lt)) + mu) / lr**2
        dPr_dlt = 2 * lam / (lr * lt)
        return [lr, (-2 * (Pr(lr, lt) - Pt(lr, lt)) / R - dPr_dlt * (lr - lt) / R) / dPr_dlr]

    def miss(ra):
        lt = ra / A
        lr = scipy.optimize.brentq(lambda s: Pr(s, lt) + p * lt * lt, 0.05, 20.0)
        sol = scipy.integrate.solve_ivp(rhs, (A, B), [ra, lr], rtol=1e-11, atol=1e-14)
        return Pr(sol.y[1, -1], sol.y[0, -1] / B)

    return scipy.optimize.brentq(miss, A * 1.0001, A * 3.0, xtol=1e-14)


def p2_shell_octant(a, b, size):
    """Octant of a hollow sphere, 10-node tets (gmsh OCC, order 2, 1 thread): nodes, tets10, the
    inner surface's 6-node triangles oriented into the solid."""
    from softphantom.fem.elements import GMSH_TET10

    gmsh.initialize(["-noenv"], readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        occ = gmsh.model.occ
        shell, _ = occ.cut([(3, occ.addSphere(0, 0, 0, b))], [(3, occ.addSphere(0, 0, 0, a))])
        occ.intersect(shell, [(3, occ.addBox(0, 0, 0, 2 * b, 2 * b, 2 * b))])
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        gmsh.model.mesh.optimize("HighOrder")
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        X = np.asarray(xyz).reshape(-1, 3)
        idx = np.full(int(tags.max()) + 1, -1)
        idx[tags] = np.arange(len(tags))
        _, _, nt = gmsh.model.mesh.getElements(3)
        T = idx[np.asarray(nt[0]).reshape(-1, 10)][:, GMSH_TET10]
        inner = []
        for _, s in gmsh.model.getEntities(2):
            c = np.array(occ.getCenterOfMass(2, s))
            if abs(np.linalg.norm(c) - a) < 0.3 * a and min(c) > 1e-9:  # the curved inner face
                _, _, ft = gmsh.model.mesh.getElements(2, s)
                inner.append(idx[np.asarray(ft[0]).reshape(-1, 6)])
        tri = np.vstack(inner)
    finally:
        gmsh.finalize()
    used = np.unique(T)
    remap = np.full(len(X), -1)
    remap[used] = np.arange(len(used))
    X, T, tri = X[used], remap[T], remap[tri]
    d = np.linalg.det(np.swapaxes(X[T[:, 1:4]] - X[T[:, [0]]], 1, 2))
    T[d < 0] = T[d < 0][:, [0, 1, 3, 2, 4, 8, 7, 6, 5, 9]]
    p = X[tri[:, :3]]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flip = np.einsum("ij,ij->i", n, p.mean(1)) < 0  # into the solid = away from the centre
    tri[flip] = tri[flip][:, [0, 2, 1, 5, 4, 3]]
    return X, T, tri


def test_thick_sphere_inflation_p2_against_shooting_reference():
    A, B, p = 0.01, 0.02, 15e3
    law = NeoHookean(1.0e5, 0.45)
    ra = sphere_shooting_reference(A, B, law.mu_Pa, law.lambda_Pa, p)
    assert 1.1 < ra / A < 1.6  # a large inflation, far from the linear range
    errs = []
    for h in (0.006, 0.0035):
        X, T, tri = p2_shell_octant(A, B, h)
        fixed = np.concatenate([3 * np.flatnonzero(np.abs(X[:, k]) < 1e-12) + k for k in range(3)])
        fem = build_fem(X, T, law, fixed_dofs=fixed)
        sol = solve_static(fem, pressures=[(tri, p)])
        assert sol.converged, sol.status
        inner = np.unique(tri)
        errs.append(np.linalg.norm(sol.x[inner], axis=1).mean() / ra - 1)
    # measured: coarse −0.2 %, finer −0.05 % (see the commit message); the error shrinks
    print("sphere errors", errs)
    assert abs(errs[1]) < abs(errs[0]) and abs(errs[1]) < 2e-3, errs


def cantilever_error(order, nu, n=2):
    """Relative error of a 100×10×10 mm cantilever's mean tip deflection (n elements across, 10n
    along, small tip load, co-rotational law) against Euler–Bernoulli P L³ / (3 E I)."""
    L, h, E, P = 0.1, 0.01, 1.0e6, 1.0e-4
    X, T = box_mesh((L, h, h), (10 * n, n, n))
    if order == 2:
        X, T = quadratic_mesh(X, T)
    fem = build_fem(X, T, Corotational(E, nu), fixed_nodes=np.flatnonzero(X[:, 0] < 1e-12))
    tip = np.flatnonzero(X[:, 0] > L - 1e-12)
    # consistent load of a uniform shear traction on the tip face
    H = ContactPatch((L, h / 2, h / 2), 0.75 * h).load_matrix(fem)
    sol = solve_static(fem, H @ np.array([0.0, 0.0, -P]), solver="splu")
    assert sol.converged
    return -sol.u[tip, 2].mean() / (P * L**3 / (3 * E * h**4 / 12)) - 1.0


def test_p2_locks_much_less_than_p1_at_nu_049():
    e1, e2 = cantilever_error(1, 0.49), cantilever_error(2, 0.49)
    # measured on 2 elements across: P1 −90 %, P2 −6.1 % (ν = 0: −46 %, −1.8 %; the clamp's
    # Poisson constraint stiffens the 3-D beam at ν = 0.49, so part of P2's −6 % is not locking)
    assert e1 < -0.8 and abs(e2) < 0.08 and abs(e2) < abs(e1) / 10, (e1, e2)


@pytest.mark.parametrize("order", [1, 2])
def test_a_load_that_inverts_stops_at_the_level_reached_without_nan(order):
    X, T = box_mesh((0.01, 0.01, 0.01), (2, 2, 2))
    if order == 2:
        X, T = quadratic_mesh(X, T)
    fem = build_fem(X, T, Corotational(1e4, 0.3), fixed_nodes=np.flatnonzero(X[:, 2] < 1e-12))
    top = np.flatnonzero(X[:, 2] > 0.01 - 1e-12)
    f = np.zeros(fem.n_dof)
    f[3 * top + 2] = -20.0 / top.size  # a crushing load: 20 N on a 1 cm² face of a 10 kPa block
    sol = solve_static(fem, f, solver="splu", max_iter=15)
    assert not sol.converged and 0.0 < sol.load_fraction < 1.0
    assert "load fraction" in sol.status and f"reached {sol.load_fraction:.4g}" in sol.status
    assert "inverted" in sol.status, sol.status
    assert np.all(np.isfinite(sol.x)) and np.all(np.isfinite(sol.u)) and np.isfinite(sol.residual_norm)
