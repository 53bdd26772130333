"""Every registered material law (softphantom.fem.laws.REGISTRY) against the contract the FEM and
the calibration rely on: its stress is the derivative of its energy and its tangent that of its
stress (central differences), both objective (a rotation of the deformed body rotates P and leaves
W; a rigid motion of the mesh gives zero force, a rotated one rotated forces), linear elasticity
with its own μ, λ at small strain, W linear in the parameter row (stiffness factors), its ratios
where its row says, and its design-file form round-trips. A new law gets these checks by being
registered. Plus: the compiled element loops' disk cache is keyed on the law files."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softphantom.fem import build_fem, internal_force
from softphantom.fem import _numba, kernels
from softphantom.fem.laws import BY_NAME, REGISTRY
from softphantom.fem.meshes import box_mesh
from test_fem_laws import random_F


def example(cls):
    """A law of each class at E = 100 kPa, ν = 0.45, with non-zero ratios where it has them."""
    law = cls.from_small_strain(1.0e5, 0.45, 1000.0)
    return law.with_ratios([0.05] * len(law.ratios)) if law.ratios else law


LAWS = {c.name: example(c) for c in REGISTRY}


def test_registry_ids_and_names():
    assert [c.law_id for c in REGISTRY] == list(range(len(REGISTRY)))
    assert [c.name for c in REGISTRY][:3] == ["corotational", "neo-hookean", "yeoh"]  # atlases hash the ids
    assert BY_NAME == {c.name: c for c in REGISTRY}


@pytest.mark.parametrize("name", list(LAWS))
def test_stress_is_the_energy_gradient_and_tangent_the_stress_gradient(name):
    law = LAWS[name]
    h = 1e-6
    for F in random_F(np.random.default_rng(5), 12):
        W, P, D = law.evaluate(F)
        assert W == pytest.approx(law.energy(F), rel=1e-14)
        np.testing.assert_array_equal(P, law.gradient(F))
        np.testing.assert_array_equal(D, law.hessian(F))
        P_fd, D_fd = np.zeros((3, 3)), np.zeros((9, 9))
        for k in range(9):
            E = np.zeros(9)
            E[k] = h
            E = E.reshape(3, 3)
            P_fd.flat[k] = (law.energy(F + E) - law.energy(F - E)) / (2 * h)
            D_fd[:, k] = ((law.gradient(F + E) - law.gradient(F - E)) / (2 * h)).reshape(-1)
        assert np.abs(P - P_fd).max() < 1e-6 * law.mu_Pa
        assert np.abs(D - D_fd).max() < 1e-5 * law.mu_Pa
        assert np.abs(D - D.T).max() < 1e-9 * law.mu_Pa


@pytest.mark.parametrize("name", list(LAWS))
def test_objectivity_of_the_point_function(name):
    law = LAWS[name]
    Qs = Rotation.random(4, random_state=3).as_matrix()
    for F in random_F(np.random.default_rng(6), 6):
        W, P, _ = law.evaluate(F, 1)
        sigma = P @ F.T / np.linalg.det(F)
        for Q in Qs:
            Wq, Pq, _ = law.evaluate(Q @ F, 1)
            assert Wq == pytest.approx(W, rel=1e-10, abs=1e-10 * law.mu_Pa)
            np.testing.assert_allclose(Pq, Q @ P, atol=1e-9 * law.mu_Pa)
            np.testing.assert_allclose(Pq @ (Q @ F).T / np.linalg.det(F), Q @ sigma @ Q.T, atol=1e-9 * law.mu_Pa)


@pytest.mark.parametrize("name", list(LAWS))
def test_rigid_motion_gives_zero_force_and_rotated_forces(name):
    X, T = box_mesh((0.02, 0.01, 0.01), (4, 2, 2))
    fem = build_fem(X, T, LAWS[name])
    Q = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    x = X + 1e-3 * np.sin(200 * X[:, [1, 2, 0]])  # a deformed state, strains ~0.2
    f = internal_force(fem, x).reshape(-1, 3)
    assert np.abs(f).max() > 0
    assert np.abs(internal_force(fem, X @ Q.T + [0.01, -0.02, 0.5])).max() < 1e-9 * np.abs(f).max()
    fq = internal_force(fem, x @ Q.T + 0.3).reshape(-1, 3)
    np.testing.assert_allclose(fq, f @ Q.T, atol=1e-9 * np.abs(f).max())


@pytest.mark.parametrize("name", list(LAWS))
def test_small_strain_limit_is_linear_elasticity_with_its_moduli(name):
    law = LAWS[name]
    W, P, D = law.evaluate(np.eye(3))
    d = np.eye(3)
    C = (law.mu_Pa * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))
         + law.lambda_Pa * np.einsum("ij,kl->ijkl", d, d)).reshape(9, 9)
    assert abs(W) < 1e-9 * law.mu_Pa and np.abs(P).max() < 1e-9 * law.mu_Pa
    np.testing.assert_allclose(D, C, atol=1e-6 * law.mu_Pa)
    assert law.E_Pa == pytest.approx(law.mu_Pa * (3 * law.lambda_Pa + 2 * law.mu_Pa) / (law.lambda_Pa + law.mu_Pa))


@pytest.mark.parametrize("name", list(LAWS))
def test_energy_is_linear_in_the_parameter_row_and_ratios_sit_in_their_columns(name):
    law = LAWS[name]
    F = random_F(np.random.default_rng(8), 1)[0]
    W1 = kernels.point(law.law_id, law.params(), F, 0)[0]
    W3 = kernels.point(law.law_id, 3.0 * law.params(), F, 0)[0]
    assert W3 == pytest.approx(3.0 * W1, rel=1e-12)
    assert law.scaled(3.0).energy(F) == pytest.approx(3.0 * W1, rel=1e-12)
    for k, r in enumerate(law.ratios):
        v = list(law.ratio_values())
        v[k] = 0.07
        row = law.with_ratios(v).params()
        assert row[r.column] == pytest.approx(0.07 * row[r.of_column], rel=1e-14)
        assert law.with_ratios(v).ratio_values()[k] == pytest.approx(0.07, rel=1e-14)
    assert type(law).feasible_ratios(law.ratio_values(), [True] * len(law.ratios)) == pytest.approx(law.ratio_values())


@pytest.mark.parametrize("name", list(LAWS))
def test_design_form_round_trips(name):
    law = LAWS[name]
    back = type(law).from_design(dict(law.design_values()), "materials.x")
    for f in law.field_names():
        assert getattr(back, f) == pytest.approx(getattr(law, f), rel=1e-14)
    required = [k for k, req in type(law).design_keys() if req]
    assert required and all(k in dict(law.design_values()) for k in required)


def test_element_loop_cache_is_keyed_on_the_law_files(tmp_path, monkeypatch):
    # numba keys a cached function on its own file only: a law edit would leave the loops that
    # inline it stale. The loops' source stamp carries every law file's contents.
    if not kernels.HAVE_NUMBA:
        pytest.skip("numba not installed")
    locator = kernels.point_loop_kernel._cache._impl.locator
    stamp = locator.get_source_stamp()
    assert stamp[1] == _numba.laws_stamp()
    copy = tmp_path / "laws"
    copy.mkdir()
    for p in _numba.LAWS_DIR.glob("*.py"):
        (copy / p.name).write_bytes(p.read_bytes())
    monkeypatch.setattr(_numba, "LAWS_DIR", copy)
    assert locator.get_source_stamp() == stamp
    (copy / "yeoh.py").write_text((copy / "yeoh.py").read_text() + "\n# edited\n")
    assert locator.get_source_stamp() != stamp


def test_an_unregistered_law_is_refused_not_run_as_another():
    # the kernels dispatch on the registry's position: a law outside it would run as the last one
    from dataclasses import dataclass

    from softphantom.errors import UserError
    from softphantom.fem.laws import NeoHookean

    @dataclass(frozen=True)
    class Unregistered(NeoHookean):
        name = "unregistered"
        law_id = -1

    X, T = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    with pytest.raises(UserError, match="Unregistered is not in softphantom.fem.laws.REGISTRY"):
        build_fem(X, T, Unregistered(1e5, 0.4))
