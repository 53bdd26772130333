"""softphantom's hyperelastic FEM against an independent package, FElupe.

A BIP-like case small enough for CI: a silicone block (E = 142 kPa, ν = 0.45) clamped at one end,
with a spherical cavity, pulled and inflated to large strain. Both codes get the same 10-node mesh
(gmsh, order 2, curved cavity) and the same compressible neo-Hookean law
(ψ = μ/2 (I₁ − 3) − μ ln J + λ/2 ln² J); everything else is each code's own: FElupe's element,
quadrature, law and assembly, and the loads and Newton loop of tests/reference/felupe_bip.py,
against softphantom's kernels, actuators and solve_static. Same discretization, so the solutions
must agree to the solvers' tolerance, far inside the issue's 1 %; the full-size default design
against DESIGN.md's table is benchmarks/bench_reference.py.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("felupe")
sys.path.insert(0, str(Path(__file__).resolve().parent / "reference"))

from felupe_bip import (  # noqa: E402
    block_with_cavity,
    cavity_volumes,
    corner_mesh,
    patch_load,
    solve_felupe,
    surface_terms,
)

from softphantom.fem import NeoHookean, build_fem, solve_static  # noqa: E402

LAW = NeoHookean(142.3e3, 0.45)



@pytest.fixture(scope="module")
def block():
    return block_with_cavity(h=0.005)


def test_reference_surface_terms_volume_gradient_and_tangent(block):
    """The reference's own loads: the enclosed volume of the curved cavity, its gradient (the
    follower load per unit pressure) and that load's derivative, by central differences."""
    mesh, _ = block
    rng = np.random.default_rng(3)
    x = mesh.nodes + 2e-4 * rng.standard_normal(mesh.nodes.shape)
    tri = mesh.cavities["cavity"]
    n = len(x)
    v, g, K = surface_terms(x, tri, n)
    sphere = 4 / 3 * np.pi * 0.005**3
    assert abs(cavity_volumes(mesh, mesh.nodes)["cavity"] - sphere) < 0.02 * sphere  # curved P2 wall
    d = rng.standard_normal(x.shape)
    e = 1e-7
    vp, gp, _ = surface_terms(x + e * d, tri, n)
    vm, gm, _ = surface_terms(x - e * d, tri, n)
    assert abs((vp - vm) / (2 * e) - g @ d.reshape(-1)) <= 1e-7 * abs(g @ d.reshape(-1))
    Kd = K @ d.reshape(-1)
    assert np.abs((gp - gm) / (2 * e) - Kd).max() <= 1e-6 * np.abs(Kd).max()
    # closed surface: the pressure stiffness is the Hessian of the volume, symmetric
    assert abs(K - K.T).max() <= 1e-12 * abs(K).max()


def test_reference_patch_load_is_the_whole_force_on_the_patch(block):
    mesh, end = block
    n = len(mesh.nodes)
    centre = np.array([0.04, 0.01, 0.01])
    f = patch_load(mesh.nodes, end, n, centre, [0.3, -1.0, 2.0], 0.004).reshape(-1, 3)
    assert np.allclose(f.sum(0), [0.3, -1.0, 2.0], atol=1e-12)
    loaded = np.flatnonzero(np.abs(f).sum(1) > 0)
    assert np.linalg.norm(mesh.nodes[loaded] - centre, axis=1).max() < 0.004 + 0.005  # within a cell
    with pytest.raises(ValueError):
        patch_load(mesh.nodes, end, n, centre + [0.1, 0, 0], [1.0, 0, 0], 0.004)


@pytest.mark.parametrize("order", [2, 1])
def test_neo_hookean_matches_felupe_under_a_large_end_load(block, order):
    """Same mesh (10-node, or its 4-node corners), same law, the same nodal load: softphantom's
    solution equals FElupe's to the solvers' tolerance."""
    mesh, faces = block
    if order == 1:
        mesh, faces = corner_mesh(mesh), _corner_faces(block)
    n = len(mesh.nodes)
    # 25 kPa dead traction on the far end face: the free end moves ~7 mm (17 % of the length)
    f = 25e3 * surface_terms(mesh.nodes, faces, n, tangent=False)[1]
    ref = solve_felupe(mesh, LAW.mu_Pa, LAW.lambda_Pa, load=f, steps=2)
    fem = build_fem(mesh.nodes, mesh.tets, LAW, mesh.fixed_nodes)
    assert fem.order == order
    sol = solve_static(fem, f)
    assert sol.converged
    u_ref = ref.x - mesh.nodes
    assert np.abs(u_ref).max() > 5e-3  # large deformation, not the linear regime
    assert np.abs(sol.u - u_ref).max() <= 1e-6 * np.abs(u_ref).max()
    v0, v_ref = cavity_volumes(mesh, mesh.nodes)["cavity"], cavity_volumes(mesh, ref.x)["cavity"]
    v_sp = cavity_volumes(mesh, sol.x)["cavity"]
    assert abs(v_ref - v0) > 0.01 * v0
    assert abs((v_sp - v0) - (v_ref - v0)) <= 1e-6 * abs(v_ref - v0)


def _corner_faces(block):
    mesh, end = block
    used = np.unique(mesh.tets[:, :4])
    remap = np.full(len(mesh.nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    return remap[end[:, :3]]
