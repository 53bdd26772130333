"""The co-rotational FEM on the BIP (coarse mesh): cavities at rest, the 5 N push, urethra pressure.

Signs of the arm cavities under a push along +y at p_ext (on-centre, over a 5 mm patch). The
front arms (±z, at −y) and back arms (±x, at +y) run from the bulb to frame anchors that lie further
out in −y and +y respectively. To first order (small push) the bulb's +y motion stretches the front
arms (the cavity grows: axial strain ε changes a void's volume by ≈ (1 − 2ν) ε > 0) and compresses
the back arms (the cavity shrinks), antisymmetric in the sign of the force: at ±1 N, front +1.4 /
back −2.3 mm³ on the coarse mesh, +2.6 / −3.6 mm³ on the default one. At 5 N the arm ends move
~10 mm sideways and a second-order term, negative for every arm (bending/kinking squeezes the
cavity), adds up: the back pair shrinks by 20–35 mm³ (4–7 % of the cavity), while in the front pair
the first-order growth and the second-order shrinking nearly cancel (−4.5 mm³ coarse, +1.1 mm³ at the
default mesh: its sign is mesh-dependent, so only its small size is asserted). A push off-centre
(+x, +z) adds pitch and yaw moments: the two cavities of the front pair then differ (pitch) and so
do the back pair's (yaw).
"""

import numpy as np
import pytest

from softphantom.fem import (
    cavity_volume,
    fem_from_phantom,
    force_actuator,
    probe_matrix,
    solve_static,
    tet_volumes,
)

ARMS = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")


@pytest.fixture(scope="module")
def bip(coarse_model):
    return coarse_model, fem_from_phantom(coarse_model)


def dV(model, x):
    return {k: cavity_volume(x, t) - cavity_volume(model.nodes, t) for k, t in model.cavities.items()}


def test_cavities_at_rest_are_the_holes_of_the_mesh(bip):
    model, fem = bip
    bnd = {tuple(np.roll(f, -np.argmin(f))) for f in fem.boundary_faces}
    total_air = 0.0
    for name, tri in model.cavities.items():
        # every cavity triangle, reversed, is a boundary face of the tet mesh: the cavity is a
        # closed hole of the solid and Φ > 0 with the air-outward orientation
        rev = tri[:, ::-1]
        assert all(tuple(np.roll(f, -np.argmin(f))) in bnd for f in rev), name
        V = cavity_volume(model.nodes, tri)
        assert V > 0
        total_air += V
    # divergence theorem over the solid: meshed (tet) volume + cavities = volume inside the outer skin
    skin = np.concatenate([model.outer_faces, model.fixed_faces])
    enclosed = cavity_volume(model.nodes, skin)
    assert tet_volumes(fem, model.nodes).sum() + total_air == pytest.approx(enclosed, rel=1e-12)
    assert fem.boundary_faces.shape[0] == skin.shape[0] + sum(len(t) for t in model.cavities.values())


_SOLVED = {}


def push(model, fem, newtons, at="on-centre"):
    key = (id(fem), newtons, at)
    if key not in _SOLVED:  # the same pushes serve several tests
        H = force_actuator(fem, model.p_ext[at], radius=5e-3)  # a 5 mm patch (DESIGN.md §5)
        _SOLVED[key] = solve_static(fem, H @ np.array([0.0, newtons, 0.0]))
    sol = _SOLVED[key]
    assert sol.converged, sol.status
    return sol


def test_push_along_y_moves_bulb_and_cavities_as_predicted(bip):
    model, fem = bip
    bulb = np.unique(fem.tets[model.tet_region == model.regions["bulb"]])
    small = {f: dV(model, push(model, fem, f).x) for f in (1.0, -1.0)}
    for f, sign in ((1.0, 1), (-1.0, -1)):
        for arm in ARMS[:2]:
            assert sign * small[f][arm] > 0.2e-9  # front pair stretched by +y: grows
        for arm in ARMS[2:]:
            assert sign * small[f][arm] < -0.2e-9  # back pair compressed by +y: shrinks
    sol = push(model, fem, 5.0)
    u = sol.u[bulb].mean(axis=0)
    assert u[1] > 5e-3 and abs(u[0]) < 0.05 * u[1] and abs(u[2]) < 0.05 * u[1]
    markers = np.array(list(model.markers.values()))
    moved = probe_matrix(fem, markers) @ sol.x
    assert np.all(moved[:, 1] - markers[:, 1] > 5e-3)
    big = dV(model, sol.x)
    assert all(big[a] < -5e-9 for a in ARMS[2:])  # back pair: compressed and bent, shrinks
    # front pair: still stretched, still grows (the converged NH P2 reference: +21 / +34 mm³ at
    # (1.5, 5.2, 1.5) N; the co-rotational law got this sign wrong, docs/model.md)
    assert all(big[a] > 1e-9 for a in ARMS[:2])
    # magnitude: a few % of the ~0.5 mL cavity at most
    assert all(abs(big[a]) < 0.1 * cavity_volume(model.nodes, model.cavities[a]) for a in ARMS)


def test_off_centre_push_splits_the_pairs(bip):
    model, fem = bip
    on = dV(model, push(model, fem, 5.0).x)
    off = dV(model, push(model, fem, 5.0, "off-centre").x)
    for a, b in (ARMS[:2], ARMS[2:]):
        split_on = abs(on[a] - on[b])  # mesh asymmetry only
        split_off = abs(off[a] - off[b])
        assert split_off > 3 * split_on and split_off > 2e-9, (a, b, split_on, split_off)


def test_urethra_pressure_inflates_bulb_and_pushes_target_out(bip):
    model, fem = bip
    sol = solve_static(fem, pressures={"urethra": 20e3})
    assert sol.converged
    bulb = model.tet_region == model.regions["bulb"]

    def bulb_volume(x):
        return tet_volumes(fem, x)[bulb].sum() + cavity_volume(x, model.cavities["urethra"])

    grow = bulb_volume(sol.x) - bulb_volume(model.nodes)
    d = dV(model, sol.x)
    assert grow > 0 and d["urethra"] > 0
    # the silicone itself expands too: under internal pressure the wall's mean stress is tensile
    # (Lamé: σ_rr + 2σ_θθ = 3 p a³/(b³ − a³) > 0), so the bulb grows by more than the cavity
    assert grow > d["urethra"]
    t0 = model.targets["near_urethra"]
    t1 = (probe_matrix(fem, [t0]) @ sol.x)[0]
    ur = model.nodes[np.unique(model.cavities["urethra"])]
    away = t0 - ur[np.argmin(np.linalg.norm(ur - t0, axis=1))]
    assert np.dot(t1 - t0, away / np.linalg.norm(away)) > 0.2 * np.linalg.norm(t1 - t0) > 0
