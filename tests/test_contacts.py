"""Named contact points (``[contacts]`` of the design file): validated on the bulb's surface, carried
by the model after ``on-centre`` and ``off-centre``, pushed on by the FEM, the scenarios and every
command that takes a contact point; any other name is refused in one line listing the model's."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.design import BIPDesign, build_model, load_model, save_model
from softphantom.design.geometry import project_to_ellipsoid
from softphantom.design.params import design_from_dict, design_to_dict, load_design, save_design
from softphantom.errors import DesignError, UserError

AXES = BIPDesign().bulb.semi_axes_mm
# on the front, below and to the left of the off-centre point, clear of the arms and markers
LOBE = tuple(float(v) for v in project_to_ellipsoid((0.6, -1.0, -0.4), AXES))
MIRROR = (-LOBE[0], LOBE[1], LOBE[2])  # its mirror image: no contact point near it
NAMES = ["on-centre", "off-centre", "front-lobe"]
UNKNOWN = "back-lobe"
REFUSAL = f"{UNKNOWN}: not a contact point of this model (on-centre, off-centre, front-lobe)"


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err and err.startswith("error: "), err
    return err


def test_the_bip_has_no_named_contacts_and_its_file_is_unchanged():
    d = BIPDesign()
    assert d.contacts == () and d.contact_names == ("on-centre", "off-centre")
    assert "contacts" not in design_to_dict(d)
    p = d.p_ext_mm()
    assert list(p) == ["on-centre", "off-centre"]
    np.testing.assert_array_equal(p["on-centre"], [0.0, -AXES[1], 0.0])  # where −y leaves the ellipsoid


def test_a_named_contact_validates_and_round_trips_through_toml(tmp_path):
    d = design_from_dict({"contacts": {"front-lobe": list(LOBE)}})
    assert d.contact_names == tuple(NAMES)
    p = d.p_ext_mm()
    assert list(p) == NAMES
    np.testing.assert_array_equal(p["front-lobe"], LOBE)
    # the derived two are the BIP's
    for k, v in BIPDesign().p_ext_mm().items():
        np.testing.assert_array_equal(p[k], v)
    path = save_design(d, tmp_path / "d.toml")
    assert "[contacts]" in path.read_text()
    back = load_design(path)
    assert back == d and list(back.p_ext_mm()) == NAMES


@pytest.mark.parametrize("contacts, message", [
    ({"front-lobe": [0.0, -20.0, 0.0]}, "contacts.front-lobe = [0.0, -20.0, 0.0] is 5 mm off the bulb surface"),
    ({"on-centre": list(LOBE)}, "contacts.on-centre: reserved"),
    ({"off-centre": list(LOBE)}, "contacts.off-centre: reserved"),
    ({"1st": list(LOBE)}, "contacts.1st: a contact's name must start with a letter"),
    ({"a,b": list(LOBE)}, "contacts.a,b: a contact's name"),
    ({"top": list(project_to_ellipsoid((0.0, -0.6, 1.0), AXES))}, "contacts.top lies under arms.front_zpos"),
    ({"front-lobe": [1.0, 2.0]}, "contacts.front-lobe: expected 3 numbers"),
    (3, "contacts: expected a table of name = [x, y, z]"),
])
def test_a_bad_contact_is_one_line_naming_it(contacts, message):
    with pytest.raises(DesignError) as e:
        design_from_dict({"contacts": contacts})
    assert str(e.value).startswith(message) and "\n" not in str(e.value), str(e.value)


def test_two_contacts_of_one_name_are_refused():
    # a TOML table cannot repeat a key; the pairs a program passes can
    with pytest.raises(DesignError, match=r"^contacts\.front-lobe: two contact points have this name$"):
        BIPDesign(contacts=(("front-lobe", LOBE), ("front-lobe", MIRROR)))


@pytest.fixture(scope="module")
def model():
    """The BIP with ``front-lobe``, linear at 12 mm, its contact points refined (to 4 mm within 5 mm)."""
    d = BIPDesign(contacts={"front-lobe": LOBE},
                  mesh=dataclasses.replace(BIPDesign().mesh, contact_size_mm=2.0, contact_zone_mm=5.0))
    return build_model(d, 12.0, isolate=False)


@pytest.fixture(scope="module")
def model_dir(model, tmp_path_factory):
    return save_model(model, tmp_path_factory.mktemp("contacts") / "model")


def test_the_model_carries_the_contact_and_refines_the_mesh_there(model, model_dir):
    assert list(model.p_ext) == NAMES
    np.testing.assert_allclose(model.p_ext["front-lobe"], np.asarray(LOBE) * 1e-3, rtol=0, atol=1e-15)
    assert load_model(model_dir) == model  # model.npz keeps it, in order
    # outer-surface edges within 5 mm of the point, against those at its mirror image (the mesh is
    # otherwise symmetric in x there: on-centre and off-centre are 16 and 25 mm away)
    X = model.nodes * 1e3
    f = model.outer_faces
    e = np.vstack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    mid = 0.5 * (X[e[:, 0]] + X[e[:, 1]])
    near = {k: length[np.linalg.norm(mid - np.asarray(q), axis=1) < 5.0]
            for k, q in (("lobe", LOBE), ("mirror", MIRROR))}
    assert near["lobe"].size > 2 * near["mirror"].size > 0
    assert near["lobe"].mean() < 0.6 * near["mirror"].mean(), {k: v.mean() for k, v in near.items()}


def test_a_push_at_the_contact_is_held_by_the_fixed_arm_ends(model):
    from softphantom.fem import fem_from_phantom, force_actuator, internal_force, solve_static

    fem = fem_from_phantom(model)
    F = np.array([0.5, 2.0, -0.3])
    H = force_actuator(fem, model.p_ext["front-lobe"], radius=4e-3)
    f_ext = H @ F
    # the load sits at the point: its centre on the mesh lies within a mm of it
    w = np.asarray(H[:, 1].todense()).reshape(-1, 3)[:, 1]
    centre = w @ fem.nodes / w.sum()
    assert np.linalg.norm(centre - model.p_ext["front-lobe"]) < 1e-3
    sol = solve_static(fem, f_ext)
    assert sol.converged
    fixed = np.setdiff1d(np.arange(fem.n_dof), fem.free_dofs)
    assert np.abs(f_ext[fixed]).max() == 0.0  # the patch is on the bulb, away from the clamped ends
    reaction = np.zeros(3)  # what the frame exerts on the arm ends, from the deformed body's forces
    np.add.at(reaction, fixed % 3, (internal_force(fem, sol.x) - f_ext)[fixed])
    np.testing.assert_allclose(reaction, -F, rtol=0, atol=1e-6 * np.linalg.norm(F))
    u = sol.u[np.argmin(np.linalg.norm(fem.nodes - model.p_ext["front-lobe"], axis=1))]
    assert u @ F > 0.9 * np.linalg.norm(u) * np.linalg.norm(F)  # the point moves with the push (0.96)


def _push_at(point: str):
    from softphantom.virtual.scenario import scenario_from_dict

    return scenario_from_dict({"name": "lobe", "duration_s": 4.0, "push": [
        {"point": point, "start_s": 1.5, "rise_s": 1.0, "force_N": [0.3, 2.0, -0.2]}]}, "lobe.toml")


def test_a_scenario_pushes_at_any_of_the_models_contacts(model):
    from softphantom.virtual import ScenarioError, solve_truth

    sc = _push_at("front-lobe")
    assert sc.check_points(model.p_ext) is sc
    with pytest.raises(ScenarioError) as e:
        _push_at(UNKNOWN).check_points(model.p_ext)
    assert str(e.value) == f"lobe.toml: push.point {REFUSAL}"
    # the truth refuses it before meshing the truth model (which takes seconds)
    with pytest.raises(ScenarioError, match=f"^lobe\\.toml: push\\.point {UNKNOWN}: not a contact point"):
        solve_truth(_push_at(UNKNOWN), model)


def test_simulate_pushes_at_the_named_contact(model, model_dir, tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--model", str(model_dir), "--force-N", "0,1,0", "--at", "front-lobe",
                 "--out", str(out)]) == 0, capsys.readouterr().err
    assert json.loads((out / "result.json").read_text())["at_mm"] == pytest.approx(list(LOBE), abs=1e-12)


def test_every_command_refuses_another_name_in_one_line(model_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    m = str(model_dir)
    (tmp_path / "r.csv").write_text("")
    for args, option in [
        (["simulate", "--model", m, "--at", UNKNOWN, "--out", "o"], "--at"),
        (["atlas", "build", "--model", m, "--at", UNKNOWN], "--at"),
        (["atlas", "check", "--model", m, "--at", UNKNOWN], "--at"),
        (["estimate", "--model", m, "--source", "replay:r.csv", "--out", "e.csv", "--at", UNKNOWN], "--at"),
        (["acquire", "--port", "loop://", "--out", "a.csv", "--model", m, "--at", UNKNOWN], "--at"),
        (["calibrate", "--model", m, "--recording", "r.csv", "--truth", "t.csv", "--out", "o",
          "--contact", UNKNOWN], "--contact"),
        (["calibrate", "--model", m, "--recording", "r.csv", "--truth", "t.csv", "--out", "o",
          "--holdout-recording", "h.csv", "--holdout-truth", "ht.csv", "--holdout-contact", UNKNOWN],
         "--holdout-contact"),
        (["live", "--model", m, "--source", "virtual:push-on-centre", "--at", UNKNOWN, "--http-port", "0",
          "--no-stream"], "--at"),
    ]:
        assert main(args) == 2, args
        err = _one_line(capsys)
        assert err.startswith(f"error: {option} {REFUSAL}"), err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"], args  # nothing written
    # the forms that are not names keep working: coordinates, and the BIP's names without a model
    assert main(["acquire", "--port", "loop://", "--out", "a.csv", "--at", "front-lobe"]) == 2
    assert _one_line(capsys) == ("error: --at front-lobe: not a contact point of the default design (on-centre, "
                                 "off-centre); --model for a design's [contacts]")


def test_check_contact_names_the_option_and_lists_the_names():
    from softphantom.design.params import check_contact

    assert check_contact("front-lobe", NAMES) == "front-lobe"
    with pytest.raises(UserError, match=r"^--contact x: not a contact point of this model \(on-centre, "
                                        r"off-centre, front-lobe\); or X,Y,Z_mm$"):
        check_contact("x", NAMES, "--contact", hint="or X,Y,Z_mm")


def test_a_replay_made_at_a_contact_the_model_lacks_is_refused(model_dir, tmp_path, capsys):
    from softphantom.sensing.chain import default_chain, nominal_tare, simulate_raw, to_measurement
    from softphantom.sensing.recording import Recorder

    chain = default_chain()
    tare = nominal_tare(chain)
    rec = tmp_path / "r.csv"
    with Recorder(rec, {"tare": tare.to_dict(), "chain": chain.summary(), "contact": UNKNOWN},
                  layout=chain.layout) as r:
        for k in range(3):
            r.write(to_measurement(k / 77.0, k, k / 77.0, simulate_raw(np.zeros(5), 100, np.random.default_rng(k)),
                                   100, chain, tare))
    out = tmp_path / "e.csv"
    assert main(["estimate", "--model", str(model_dir), "--source", f"replay:{rec}", "--out", str(out)]) == 2
    assert _one_line(capsys) == (f"error: replay:{rec}: recording_contact {REFUSAL}; --at gives another")
    assert not out.exists()
