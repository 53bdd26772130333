"""The atlas estimator on the coarse mesh with a small envelope and grid: interpolation
against converged forward solves at held-out loads, exactness at the grid, the cache (hash
mismatch, corruption), the out-of-envelope flag, the estimator interface and the CLI option."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.errors import UserError
from softphantom.estimation import (
    AtlasConfig, AtlasEstimator, Estimator, EstimatorConfig, ForwardModel, StateEstimator, build_atlas,
    load_or_build, open_estimator,
)
from softphantom.estimation.atlas.basis import cheb_basis, to_chebyshev
from softphantom.estimation.atlas.catalogue import atlas_key
from softphantom.estimation.atlas.store import FORMAT, AtlasCorrupt, atlas_path, load_atlas, save_atlas
from softphantom.pose import Pose6, rigid_fit
from softphantom.records import BIP_LAYOUT
from softphantom.sensing import Measurement
from shared_models import atlas_config, cached_atlas

CFG = EstimatorConfig(contact="on-centre")
ACFG = atlas_config()  # 3 × 4 × 3 × 2 points, ±0.5 N of f_x (shared: shared_models.cached_atlas)
ACFG_DISP = atlas_config("displacement")


def meas(dV, p=0.0, t=0.0):
    return Measurement(t, 0, t, np.full(5, 51150), 100, np.zeros(4), np.asarray(dV, float), p)


@pytest.fixture(scope="module")
def fwd(coarse_model):
    return ForwardModel(coarse_model, CFG)


@pytest.fixture(scope="module")
def atlas(shared_dir):
    """ACFG's atlas, built once per run (shared_models.cached_atlas)."""
    return cached_atlas(shared_dir)


@pytest.fixture(scope="module")
def atlas_disp(shared_dir):
    return cached_atlas(shared_dir, "displacement")


@pytest.fixture(params=["force", "displacement"])
def any_atlas(request):
    """Each x axis: f_x itself (the default) and the patch displacement."""
    return request.getfixturevalue("atlas" if request.param == "force" else "atlas_disp")


@pytest.fixture(scope="module")
def held_out(fwd):
    """Converged forward solves at seeded random loads strictly inside the envelope."""
    rng = np.random.default_rng(7)
    lo, hi = ACFG.lower, ACFG.upper
    return [fwd.solve(lo + (hi - lo) * rng.uniform(0.1, 0.9, 4)) for _ in range(3)]


def test_chebyshev_tensor_interpolation_is_exact_for_polynomials():
    # a polynomial of degree < n per axis is reproduced exactly between the Lobatto points
    shape = (3, 4, 3, 2)
    axes = [-np.cos(np.pi * np.arange(n) / (n - 1)) for n in shape]
    g = np.meshgrid(*axes, indexing="ij")
    f = (1 + g[0] - 2 * g[0] ** 2) * (g[1] ** 3 - g[1]) + g[2] * g[3] + 0.5 * g[2] ** 2
    c = to_chebyshev(f[..., None], shape)[..., 0]
    x = (0.3, -0.7, 0.45, -0.2)
    b = [cheb_basis(t, n)[0] for t, n in zip(x, shape)]
    val = np.einsum("i,j,k,l,ijkl->", *b, c)
    exact = (1 + x[0] - 2 * x[0] ** 2) * (x[1] ** 3 - x[1]) + x[2] * x[3] + 0.5 * x[2] ** 2
    assert val == pytest.approx(exact, abs=1e-13)
    # derivative of T_k by the recurrence against a central difference
    _, d = cheb_basis(0.37, 6)
    h = 1e-6
    fd = (cheb_basis(0.37 + h, 6)[0] - cheb_basis(0.37 - h, 6)[0]) / (2 * h)
    assert np.allclose(d, fd, atol=1e-8)


def test_lines_through_their_own_first_axis_points_are_interpolated_exactly():
    # a displacement axis's points land near, not at, the Lobatto nodes, each line its own: the fit
    # through each line's points (t0) still reproduces a polynomial of degree < n per axis, and
    # the Lobatto nodes given as t0 are the plain fit
    rng = np.random.default_rng(3)
    shape = (5, 3, 2, 2)
    lob = [-np.cos(np.pi * np.arange(n) / (n - 1)) for n in shape]
    t0 = np.broadcast_to(lob[0].reshape(-1, 1, 1, 1), shape).copy()
    t0[1:-1] += rng.uniform(-0.05, 0.05, (3, *shape[1:]))  # the inner points moved, the faces kept

    def f(a, b, c, d):
        return (a ** 4 - 0.5 * a ** 3 + a) * (1 + b - b * b) + c * d * a ** 2 + 0.3 * d

    g = np.meshgrid(*lob, indexing="ij")
    values = f(t0, g[1], g[2], g[3])[..., None]
    coef = to_chebyshev(values, shape, t0)[..., 0]
    x = (0.21, -0.4, 0.77, -0.3)
    b = [cheb_basis(t, n)[0] for t, n in zip(x, shape)]
    assert np.einsum("i,j,k,l,ijkl->", *b, coef) == pytest.approx(f(*x), abs=1e-12)
    plain = f(np.broadcast_to(lob[0].reshape(-1, 1, 1, 1), shape), g[1], g[2], g[3])[..., None]
    assert np.allclose(to_chebyshev(plain, shape), to_chebyshev(plain, shape, np.broadcast_to(
        lob[0].reshape(-1, 1, 1, 1), shape)), atol=1e-13)


def test_replacing_the_grid_or_first_axis_takes_its_default_stretch():
    big = AtlasConfig()
    assert big.cluster_N[0] > 0 and big.force_cluster_N is None
    assert dataclasses.replace(big, x_control="displacement").cluster_N == AtlasConfig(x_control="displacement").cluster_N
    assert dataclasses.replace(big, n_force=(5, 9, 4)).cluster_N == (0.0, 0.0, 0.0)
    assert dataclasses.replace(big, force_cluster_N=0.05).cluster_N == (0.05, 0.05, 0.05)  # given: kept
    assert AtlasConfig().as_dict() == AtlasConfig(force_cluster_N=AtlasConfig().cluster_N).as_dict()


@pytest.mark.slow
def test_atlas_is_exact_at_grid_points(any_atlas, fwd):
    atlas = any_atlas
    ax = ACFG.axes()
    for i in range(3):
        lam = np.array([atlas.q_nodes[i, 3, 2, 1], ax[1][3], ax[2][2], ax[3][1]])
        f = atlas.forces(lam)  # on a displacement axis the f_x the build found for this point
        lin = fwd.solve(np.r_[f, lam[3]])
        V, _ = atlas.volumes(lam)
        assert np.allclose(V, lin.V, atol=1e-9 * 1e-6, rtol=1e-6)  # 1e-6 mm³ or 1 ppm: solver tolerance
        assert np.allclose(atlas.points(lam), lin.sub_x, atol=1e-9)
        if i in (0, 2):  # the faces are the envelope's f_x faces on either axis
            assert lam[0] == ax[0][i] and f[0] == pytest.approx(ax[0][i], abs=1e-12)


@pytest.mark.slow
def test_displacement_axis_points_sit_at_their_patch_displacement(atlas_disp, fwd):
    """On a displacement axis the middle point of a line is solved where the patch's
    x-displacement (work-conjugate to f_x) is halfway between the faces', and its coordinate q is
    where it is — a property of the equilibria, checked on independent solves at the faces and at
    the f_x the build found."""
    from softphantom.estimation.atlas.build import NODE_TOL, x_patch

    h = x_patch(fwd)
    ax = ACFG.axes()
    lo, hi = ax[0][0], ax[0][-1]
    for j, k in [(0, 0), (3, 1), (2, 2)]:
        u = []
        for i in range(3):
            lam = np.array([atlas_disp.q_nodes[i, j, k, 0], ax[1][j], ax[2][k], ax[3][0]])
            lin = fwd.solve(np.r_[atlas_disp.forces(lam), lam[3]])
            u.append(h @ (lin.x - fwd.fem.x_rest))
        assert u[0] < u[1] < u[2]  # ū_x increases with f_x (a stable path)
        q = lo + (hi - lo) * (u[1] - u[0]) / (u[2] - u[0])
        assert q == pytest.approx(atlas_disp.q_nodes[1, j, k, 0], abs=1e-6)
        assert abs(q - ax[0][1]) <= NODE_TOL * (ax[0][1] - lo) + 1e-9
        # the mixed-control solve (f_x an unknown of the chord iterations) lands on the node itself
        assert abs(q - ax[0][1]) <= 1e-4 * (ax[0][1] - lo)


@pytest.mark.slow
def test_atlas_matches_converged_solves_at_held_out_loads(any_atlas, held_out, fwd):
    atlas = any_atlas
    for lin in held_out:
        lam = atlas.coords(lin.lam[:3], lin.lam[3])
        assert np.allclose(atlas.forces(lam), lin.lam[:3], atol=1e-9)  # coords inverts forces
        V, J = atlas.volumes(lam)
        span = np.max(np.abs(lin.V))
        assert np.max(np.abs(V - lin.V)) < 0.01 * span  # 1 % of the volume change
        J = atlas.by_force(lam, J)  # the Jacobian too (per N and Pa)
        assert np.allclose(J, lin.W, rtol=0.05, atol=0.05 * np.abs(lin.W).max())
        # points and the full field (POD) within 3 % of the largest displacement (measured: 1 %)
        move = np.max(np.abs(lin.x - fwd.fem.x_rest))
        assert np.max(np.abs(atlas.points(lam) - lin.sub_x)) < 0.03 * move
        assert np.max(np.abs(atlas.nodes(lam) - lin.x.reshape(-1, 3))) < 0.03 * move


@pytest.mark.slow
def test_atlas_estimator_inverts_the_converged_volumes(coarse_model, any_atlas, held_out, fwd):
    atlas = any_atlas
    est = AtlasEstimator(coarse_model, CFG, atlas)
    for lin in held_out:
        est.reset()
        e = est.step(meas(lin.V, lin.lam[3]))
        assert e.status == "ok" and e.in_envelope and e.qp_status == "optimal"
        assert np.linalg.norm(e.force - lin.lam[:3]) < 0.02  # N
        assert np.allclose(est.lam, np.r_[e.force, lin.lam[3]])
        truth = Pose6.from_transform(rigid_fit(est.rest_markers, lin.sub_x[: fwd.n_markers])).to_mm_deg()
        d = e.pose.to_mm_deg() - truth
        assert np.max(np.abs(d[:3])) < 0.01 and np.max(np.abs(d[3:])) < 0.05  # mm, deg
        assert np.allclose(est.node_positions(), atlas.nodes(est.coords))
        assert np.allclose(atlas.forces(est.coords), e.force)


@pytest.mark.slow
def test_out_of_envelope_is_flagged_and_clamped(coarse_model, atlas, fwd):
    est = AtlasEstimator(coarse_model, CFG, atlas)
    outside = fwd.solve([0.0, 2.0, 0.0, 0.0])  # beyond the envelope's f_y ≤ 1.2 N
    e = est.step(meas(outside.V))
    assert not e.in_envelope and e.status == "ok"
    assert e.force[1] == pytest.approx(1.2)
    e = est.step(meas(np.zeros(4), p=9e3))  # pressure above the envelope's 4 kPa
    assert not e.in_envelope and e.p_urethra == 9e3
    assert est.step(meas(np.zeros(4))).in_envelope
    bad = est.step(meas([np.nan, 0, 0, 0]))
    assert bad.status.startswith("rejected:nan")


@pytest.mark.slow
def messages(caplog) -> list[str]:
    """The log messages of the atlas build (not its progress records), at WARNING with the level."""
    from softphantom.progress import is_progress

    return [(f"warning: {r.getMessage()}" if r.levelno >= logging.WARNING else r.getMessage())
            for r in caplog.records if r.name.startswith("softphantom.estimation") and not is_progress(r)]


def test_cache_round_trip_mismatch_and_corruption(coarse_model, atlas, fwd, tmp_path, monkeypatch, caplog):
    path = atlas_path(tmp_path, atlas.key)
    save_atlas(atlas, path)
    back = load_atlas(path, atlas.key)
    assert np.array_equal(back.cV, atlas.cV) and back.config.as_dict() == ACFG.as_dict()
    assert back.config.force_cluster_N == ACFG.cluster_N  # the file keeps the stretch it was built with
    # another contact patch, law parameter or envelope → another key; the file is refused in one line
    other = ForwardModel(coarse_model, EstimatorConfig(contact="off-centre"))
    assert atlas_key(other.model, other.config, ACFG) != atlas.key
    assert atlas_key(fwd.model, fwd.config, dataclasses.replace(ACFG, force_max_N=(0.5, 1.3, 0.5))) != atlas.key
    assert atlas_key(fwd.model, fwd.config, dataclasses.replace(ACFG, p_min_kPa=-1, p_max_kPa=4)) == atlas.key  # ints: one key
    assert atlas_key(fwd.model, fwd.config, dataclasses.replace(ACFG, force_cluster_N=ACFG.cluster_N)) == atlas.key  # the default, given
    assert atlas_key(fwd.model, fwd.config, dataclasses.replace(ACFG, force_cluster_N=(0.1, 0.0, 0.0))) != atlas.key
    with pytest.raises(UserError, match="built for another model") as exc:
        load_atlas(path, atlas_key(other.model, other.config, ACFG))
    assert "\n" not in str(exc.value)
    # the cached file is used as is
    built = []
    monkeypatch.setattr("softphantom.estimation.atlas.build.build_atlas", lambda *a, **k: built.append(1) or atlas)
    caplog.set_level(logging.INFO, logger="softphantom")
    assert load_or_build(coarse_model, CFG, ACFG, cache_dir=tmp_path, fwd=fwd).key == atlas.key
    assert not built and any(str(path) in m for m in messages(caplog))
    # one flipped byte in the data → corrupt: one line naming the file, never used, nothing overwritten
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(AtlasCorrupt):
        load_atlas(path)
    with pytest.raises(AtlasCorrupt, match="atlas build --model .* --rebuild") as exc:
        load_or_build(coarse_model, CFG, ACFG, cache_dir=tmp_path, fwd=fwd)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)
    assert not built and path.read_bytes() == bytes(raw)
    # asked to rebuild: built and rewritten intact
    load_or_build(coarse_model, CFG, ACFG, cache_dir=tmp_path, fwd=fwd, rebuild=True)
    assert built == [1] and any(m.startswith("warning: ") and "rebuilding" in m for m in messages(caplog))
    assert np.array_equal(load_atlas(path, atlas.key).cV, atlas.cV)  # rewritten intact
    path.write_bytes(b"not an npz")
    with pytest.raises(AtlasCorrupt, match="not a readable atlas file"):
        load_atlas(path)
    # the atlas/ directory given instead of the model's: one line says so before the build
    caplog.clear()
    load_or_build(coarse_model, CFG, ACFG, cache_dir=path.parent, fwd=fwd)
    assert built == [1, 1] and sum("warning" in m and "model directory" in m for m in messages(caplog)) == 1


def test_the_file_stores_the_field_compact_and_reads_format_4(atlas, tmp_path):
    """The field (live view, report) is stored as float16 modes scaled per mode and float32
    coefficients: within 1e-3 of the largest displacement, the volumes and tracked points exact; a
    file of the previous layout (float64 arrays, format 4) still reads, digest checked."""
    import io
    import json

    from softphantom.estimation.atlas import store

    # the fixture was loaded from a file (its modes quantized already): orthonormal float64 modes
    modes = np.linalg.qr(np.random.default_rng(0).normal(size=atlas.modes.shape))[0]
    atlas = dataclasses.replace(atlas, modes=modes)
    path = save_atlas(atlas, tmp_path / "a.npz")
    back = load_atlas(path, atlas.key)
    assert back.modes.dtype == np.float32 and np.array_equal(back.cV, atlas.cV) and np.array_equal(back.cP, atlas.cP)
    lo, hi = ACFG.lower, ACFG.upper
    for t in np.random.default_rng(1).uniform(size=(5, 4)):
        lam = lo + t * (hi - lo)
        u = atlas.nodes(lam) - atlas.x_rest.reshape(-1, 3)
        err = np.abs(back.nodes(lam) - atlas.nodes(lam)).max()
        assert 0 < err <= 1e-3 * np.abs(u).max(), (err, np.abs(u).max())
        assert np.array_equal(back.volumes(lam)[0], atlas.volumes(lam)[0])
    raw = sum(getattr(atlas, k).nbytes for k in store.ARRAYS)
    assert path.stat().st_size < 0.5 * raw
    # format 4: every array as built, the digest over them in ARRAYS order
    arrays = {k: getattr(atlas, k) for k in store.ARRAYS}
    meta = {"format": 4, "key": atlas.key, "config": atlas.config.as_dict(), "build_s": 1.0, "solves": atlas.solves,
            "field_rms_m": atlas.field_rms_m, "digest": store._digest(arrays, store.ARRAYS), "provenance": {}}
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
    old = tmp_path / "v4.npz"
    old.write_bytes(buf.getvalue())
    assert np.array_equal(load_atlas(old, atlas.key).modes, atlas.modes)
    arrays["cV"] = arrays["cV"] * 1.001
    np.savez(buf := io.BytesIO(), meta=np.array(json.dumps(meta)), **arrays)
    old.write_bytes(buf.getvalue())
    with pytest.raises(AtlasCorrupt, match="do not match the digest"):
        load_atlas(old)


def _rewrite_meta(path, **changes) -> None:
    """Rewrite an atlas file's metadata (its arrays, and so their digest, unchanged)."""
    import io
    import json

    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays.pop("meta")))
    for k, v in changes.items():
        if isinstance(v, dict):
            meta[k].update(v)
        else:
            meta[k] = v
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
    path.write_bytes(buf.getvalue())


@pytest.mark.slow
def test_atlas_files_are_verified_described_and_installed(coarse_model, atlas, tmp_path, capsys):
    from softphantom.design import save_model

    model_dir = save_model(coarse_model, tmp_path / "model")
    path = save_atlas(atlas, atlas_path(model_dir, atlas.key))
    assert main(["atlas", "verify", "--model", str(model_dir)]) == 0
    assert "ok" in capsys.readouterr().out
    assert main(["atlas", "info", "--model", str(model_dir)]) == 0
    out = capsys.readouterr().out
    assert "3 × 4 × 3 × 2 points" in out and "on-centre" in out and atlas.key in out
    # `atlas build` finds it (no solve: the cached file is loaded and named)
    build = ["atlas", "build", "--model", str(model_dir), "--atlas-grid", "3,4,3,2", "--atlas-x-axis", "force",
             "--envelope", "-0.5:0.5,-0.3:1.2,-0.5:0.5,-1:4", "--atlas-f-y-split-N", ""]
    assert main(build) == 0
    out = capsys.readouterr().out
    # the build's log line, then where the atlas came from
    assert f"atlas: {path} (model directory)" in out and out.splitlines()[-1] == f"{path} (model directory)"
    assert main(["-q", *build]) == 0
    assert capsys.readouterr().out.splitlines() == [f"{path} (model directory)"]  # quiet: no log line
    # installed into another copy of the same model: found under its key; again: already there
    twin = save_model(coarse_model, tmp_path / "twin")
    assert main(["atlas", "add", str(path), "--model", str(twin)]) == 0
    assert atlas_path(twin, atlas.key).read_bytes() == path.read_bytes()
    assert main(["atlas", "add", str(path), "--model", str(twin)]) == 0
    assert "already present" in capsys.readouterr().out
    # another mesh (every node moved 10 µm): refused in one line, nothing written
    other = save_model(dataclasses.replace(coarse_model, nodes=coarse_model.nodes + 1e-5), tmp_path / "other")
    assert main(["atlas", "add", str(path), "--model", str(other)]) == 2
    err = capsys.readouterr().err
    assert "built for another model" in err and str(path) in err and len(err.strip().splitlines()) == 1
    assert not (other / "atlas").exists()
    # another version's file format, a tampered file and a truncated one: exit 2, the file named
    bad = {}
    for name, spoil in (("format", lambda p: _rewrite_meta(p, format=3)),
                        ("tampered", lambda p: _rewrite_meta(p, provenance={"tol": 1e-6})),
                        ("flipped", lambda p: p.write_bytes(p.read_bytes()[:-2000] + bytes(
                            b ^ 0xFF for b in p.read_bytes()[-2000:-1000]) + p.read_bytes()[-1000:])),
                        ("truncated", lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]))):
        p = tmp_path / f"{name}.npz"
        p.write_bytes(path.read_bytes())
        spoil(p)
        before = p.read_bytes()
        assert main(["atlas", "verify", str(p), "--model", str(model_dir)]) == 2
        bad[name] = capsys.readouterr().err.strip()
        assert str(p) in bad[name] and len(bad[name].splitlines()) == 1 and p.read_bytes() == before
    assert "format 3" in bad["format"] and f"reads formats 4, {FORMAT}" in bad["format"]
    assert "another model" in bad["tampered"]
    assert "digest" in bad["flipped"] or "not a readable" in bad["flipped"]
    assert "truncated" in bad["truncated"]


def test_a_model_directory_is_no_misplaced_atlas_cache(coarse_model, atlas, fwd, tmp_path, monkeypatch, caplog):
    """A directory just made by ``design`` holds model.npz (the model's own file): building its first
    atlas says nothing about "atlas files"; a directory holding an atlas file (named by its key) does."""
    from softphantom.design import save_model

    monkeypatch.setattr("softphantom.estimation.atlas.build.build_atlas", lambda *a, **k: atlas)
    save_model(coarse_model, tmp_path / "model")
    assert (tmp_path / "model" / "model.npz").is_file()
    caplog.set_level(logging.INFO, logger="softphantom")
    load_or_build(coarse_model, CFG, ACFG, cache_dir=tmp_path / "model", fwd=fwd)
    assert messages(caplog) and not any("warning" in m for m in messages(caplog)), messages(caplog)
    assert atlas_path(tmp_path / "model", atlas.key).is_file()
    caplog.clear()  # the atlas/ directory itself given as the cache: warned once
    load_or_build(coarse_model, CFG, ACFG, cache_dir=tmp_path / "model" / "atlas", fwd=fwd)
    assert sum("warning" in m and "holds atlas files" in m for m in messages(caplog)) == 1


@pytest.mark.slow
def test_both_estimators_implement_the_interface(coarse_model, atlas):
    a = open_estimator("atlas", coarse_model, CFG, atlas=atlas)
    r = open_estimator("refresh", coarse_model, CFG)
    for est in (a, r):
        assert isinstance(est, StateEstimator)
        e = est.step(meas(np.zeros(4)))
        assert e.status == "ok" and np.allclose(e.force, 0, atol=0.01)  # N; the atlas: interpolation error
        assert est.node_positions().shape == (len(coarse_model.nodes), 3)
        est.close()
    assert isinstance(r, Estimator) and a.kind == "atlas" and r.kind == "refresh"
    with pytest.raises(UserError, match="--estimator must be atlas or refresh"):
        open_estimator("sync", coarse_model, CFG)


@pytest.mark.slow
def test_cli_estimate_atlas_option(coarse_model, atlas, tmp_path, capsys):
    from softphantom.design import save_model
    from softphantom.evaluation.files import read_table
    from softphantom.sensing.chain import default_chain, nominal_tare, simulate_raw, to_measurement
    from softphantom.sensing.pneumatics import boyle_dp
    from softphantom.sensing.recording import Recorder

    d = tmp_path / "model"
    save_model(coarse_model, d)
    rec = tmp_path / "rec.csv"
    chain, rng = default_chain(), np.random.default_rng(1)
    tare = nominal_tare(chain)
    def record(path, scale):
        with Recorder(path, {"tare": tare.to_dict(), "chain": chain.summary(), "contact": "on-centre"},
                      layout=chain.layout) as r:
            for k in range(12):  # a push along +y: ~0.3 N at scale 1
                dV = np.array([0.2, 0.15, -0.9, -0.85]) * 1e-9 * scale * k / 11
                raw = simulate_raw(np.r_[boyle_dp(dV, chain.v_total_m3, tare.p0_Pa), 0.0], 100, rng)
                r.write(to_measurement(k / 77.0, k, k / 77.0, raw, 100, chain, tare))

    record(rec, 1.0)
    out = tmp_path / "est.csv"
    # the options give the fixture's envelope and grid: the CLI finds the atlas saved under its key
    save_atlas(atlas, atlas_path(d, atlas.key))
    args = ["estimate", "--model", str(d), "--source", f"replay:{rec}", "--out", str(out),
            "--atlas-grid", "3,4,3,2", "--envelope", "-0.5:0.5,-0.3:1.2,-0.5:0.5,-1:4"]
    assert main(args) == 0
    assert "atlas: " + str(atlas_path(d, atlas.key)) in capsys.readouterr().out.replace("\n", "")
    tab = read_table(out)
    assert tab.meta["estimator"] == "atlas" and len(tab.columns["t_s"]) == 12
    assert np.all(tab.columns["in_envelope"] == 1) and tab.columns["force_y_N"][-1] > 0.1
    assert "warning" not in capsys.readouterr().out
    # a push beyond the envelope's f_y face (1.2 N): clamped, flagged per row, and one warning line
    # with the fraction of clamped estimates
    record(big := tmp_path / "big.csv", 8.0)
    assert main(["estimate", "--model", str(d), "--source", f"replay:{big}", "--out", str(tmp_path / "big_est.csv"),
                 *args[7:]]) == 0
    flags = read_table(tmp_path / "big_est.csv").columns["in_envelope"]
    # (a hand-made recording without its tube: the lag compensation's own warning says it is off)
    out_lines = [ln for ln in capsys.readouterr().out.splitlines() if "warning" in ln and "lag compensation" not in ln]
    k = int(np.sum(flags == 0))
    assert 0 < k < 12 and len(out_lines) == 1
    assert f"{k} of 12 estimates ({k / 12:.0%})" in out_lines[0] and "--envelope" in out_lines[0]
    assert main(args[:-4] + ["--estimator", "nope"]) == 2
    assert "--estimator must be atlas or refresh" in capsys.readouterr().err
    assert main(args[:-2] + ["--envelope", "1:0,0:1,0:1,0:1"]) == 2


def test_unreachable_grid_points_are_filled_and_flagged(coarse_model, fwd, monkeypatch, caplog):
    """A corner of the envelope that does not converge: the build goes on, does not try the points
    beyond the failure, fills them (exactly, for a map linear in the loads) and flags estimates
    there as outside the envelope; one log line per plane with failures."""
    from types import SimpleNamespace

    from softphantom.errors import SolverError

    rng = np.random.default_rng(5)
    A = rng.normal(size=(4, 4)) * np.array([1e-9, 1e-9, 1e-9, 1e-12])  # m³ per N, m³ per Pa
    B = rng.normal(size=(fwd.fem.n_dof, 4)) * np.array([1e-4, 1e-4, 1e-4, 1e-7])
    tried = []

    def bad(lam):
        return lam[0] > 0.1 and lam[1] > 0.5

    class Linear:  # stands in for the FEM: a map linear in the loads, failing in one corner
        def __init__(self, model, config, **kw):
            self.probe, self.fem = fwd.probe, fwd.fem
            self.eq = SimpleNamespace(keep=lambda: None, restore=lambda kept: None,  # no factor to keep
                                      arm_names=fwd.eq.arm_names)

        def solve(self, lam, start=None, factor_at_solution=False, via_tol=None):
            lam = np.asarray(lam, float)
            tried.append(lam)
            if bad(lam):
                raise SolverError("line search failed at load fraction 0.8\n(detail on a second line)")
            x = fwd.fem.x_rest + B @ lam
            return SimpleNamespace(V=A @ lam, x=x, sub_x=(fwd.probe @ x.reshape(-1, 3)), lam=lam)

    monkeypatch.setattr("softphantom.estimation.atlas.solves.ForwardModel", Linear)  # where a build task makes its forward model
    caplog.set_level(logging.INFO, logger="softphantom")
    at = build_atlas(coarse_model, CFG, ACFG, n_workers=1, processes=False, fwd=fwd)
    lines = [s for s in messages(caplog) if "parallel efficiency" not in s]  # the build's summary aside
    g = np.stack(np.meshgrid(*ACFG.axes(), indexing="ij"), axis=-1)
    fails = (g[..., 0] > 0.1) & (g[..., 1] > 0.5)
    assert np.array_equal(~at.solved, fails) and at.unsolved == fails.sum() > 0
    assert at.solves == at.solved.size - at.unsolved
    # only the first failing point of each line outwards was tried (f_y rows at f_x = 0.5 N)
    n_tried_bad = sum(bad(lam) for lam in tried)
    assert 0 < n_tried_bad < fails.sum()
    assert len(lines) == len({(i, l) for i, _, _, l in np.argwhere(fails)})
    assert all("\n" not in s and "unreachable" in s for s in lines)
    # its planes' progress: one record as each plane task ends, done of total, for the CLI's bar
    steps = [r.progress for r in caplog.records if hasattr(r, "progress")]
    n_planes = ACFG.shape[0] * (1 if ACFG.linear_pressure else ACFG.shape[3])
    label = f"atlas: {n_planes} tasks, {ACFG.n_solves} grid points"
    assert [(s.task, s.done, s.total) for s in steps] == [(label, k, n_planes) for k in range(n_planes + 1)]
    assert all(s.what.startswith("ETA ") for s in steps[1:-1])  # the time left, once a task has ended
    # the fill is exact for a linear map: the polynomial reproduces it everywhere
    lam = np.array([0.4, 1.0, 0.2, 2e3])
    assert np.allclose(at.volumes(lam)[0], A @ lam, rtol=1e-9, atol=1e-18)
    assert at.solved_at(lam) is False and at.solved_at([-0.3, 0.2, 0.0, 0.0]) is True
    # solved_at against the cell rule written out: all 16 corners of the cell holding lam solved
    rng = np.random.default_rng(5)
    axes = ACFG.axes()
    lo, hi = ACFG.lower, ACFG.upper
    draws = list(lo + (hi - lo) * rng.uniform(-0.05, 1.05, (300, 4))) + list(g.reshape(-1, 4)[::7])
    ends = np.array([[a[0], a[-1]] for a in axes])
    slack = 1e-9 * (1 + np.abs(ends))  # the grid's ends are the box's to round-off
    for x in draws:
        if np.any(x < ends[:, 0] - slack[:, 0]) or np.any(x > ends[:, 1] + slack[:, 1]):
            want = False
        else:
            i = [min(max(int(np.searchsorted(a, v)) - 1, 0), len(a) - 2) for v, a in zip(x, axes)]
            want = bool(at.solved[i[0]:i[0] + 2, i[1]:i[1] + 2, i[2]:i[2] + 2, i[3]:i[3] + 2].all())
        assert at.solved_at(x) is want, x
    monkeypatch.undo()
    est = AtlasEstimator(coarse_model, CFG, at)
    assert not est.step(meas(A @ lam, lam[3])).in_envelope
    inside = np.array([-0.3, 0.2, 0.1, 1e3])
    e = est.step(meas(A @ inside, inside[3]))
    assert e.in_envelope and np.allclose(e.force, inside[:3], atol=1e-6)


def test_an_atlas_in_pieces_along_f_y_follows_a_kink_one_polynomial_cannot(coarse_model, fwd, monkeypatch, tmp_path):
    """``AtlasConfig.f_y_splits_N``: a map with a kink in f_y (a stand-in for the quadratic model's
    fold) is reproduced exactly by pieces split at the kink, each a cubic in f_y, and not by one
    polynomial over the range; the estimator inverts loads on either side and across the shared face;
    each piece is cached as the plain atlas of its range."""
    from types import SimpleNamespace

    from softphantom.estimation.atlas.map import AtlasPatches

    rng = np.random.default_rng(11)
    A = rng.normal(size=(4, 4)) * np.array([1e-9, 1e-9, 1e-9, 1e-12])  # m³ per N, m³ per Pa
    B = rng.normal(size=(fwd.fem.n_dof, 4)) * np.array([1e-4, 1e-4, 1e-4, 1e-7])
    split = 0.5
    kink = np.array([0.2, -0.1, 3.0, -2.0]) * 1e-9  # m³/N²: the back pair parts above the split

    def volumes(lam):
        return A @ lam + kink * max(lam[1] - split, 0.0) ** 2

    class Kinked:  # stands in for the FEM: linear in the loads but for a kink at f_y = split
        def __init__(self, model, config, **kw):
            self.probe, self.fem = fwd.probe, fwd.fem
            self.eq = SimpleNamespace(keep=lambda: None, restore=lambda kept: None, arm_names=fwd.eq.arm_names)

        def solve(self, lam, start=None, factor_at_solution=False, via_tol=None):
            lam = np.asarray(lam, float)
            x = fwd.fem.x_rest + B @ lam
            return SimpleNamespace(V=volumes(lam), x=x, sub_x=(fwd.probe @ x.reshape(-1, 3)), lam=lam)

    cfg4 = dataclasses.replace(ACFG, n_force=(3, 4, 3))
    pieces = dataclasses.replace(cfg4, f_y_splits_N=(split,))
    assert [c.force_max_N[1] for c in pieces.patches()] == [split, ACFG.force_max_N[1]]
    assert pieces.n_solves == 2 * cfg4.n_solves and "f_y_splits_N" not in cfg4.as_dict()  # old keys kept
    monkeypatch.setattr("softphantom.estimation.atlas.solves.ForwardModel", Kinked)  # where a build task makes its forward model
    kw = dict(n_workers=1, processes=False, fwd=fwd)
    one = build_atlas(coarse_model, CFG, cfg4, **kw)
    at = build_atlas(coarse_model, CFG, pieces, **kw)
    monkeypatch.undo()
    assert isinstance(at, AtlasPatches) and len(at.patches) == 2 and at.solves == pieces.n_solves
    # each piece is the plain atlas of its range: the cache finds it under that atlas's key
    for piece in at.patches:
        save_atlas(piece, atlas_path(tmp_path, atlas_key(fwd.model, fwd.config, piece.config)))
    cached = load_or_build(coarse_model, CFG, pieces, cache_dir=tmp_path, fwd=fwd)
    assert isinstance(cached, AtlasPatches) and cached.key == at.key
    lo, hi = ACFG.lower, ACFG.upper
    loads = lo + (hi - lo) * rng.uniform(0.02, 0.98, (40, 4))
    err_pieces = max(np.abs(at.volumes(x)[0] - volumes(x)).max() for x in loads)
    err_one = max(np.abs(one.volumes(x)[0] - volumes(x)).max() for x in loads)
    scale = np.abs(kink).max() * (hi[1] - split) ** 2
    assert err_pieces < 1e-9 * scale and err_one > 1e-3 * scale, (err_pieces, err_one, scale)
    # the face belongs to the piece below; both pieces agree there
    face = np.array([0.1, split, -0.2, 1e3])
    assert at.index(split) == 0 and np.allclose(at.patches[1].volumes(face)[0], at.volumes(face)[0], rtol=1e-9)
    # the estimator: from rest (below), across the face and back
    est = AtlasEstimator(coarse_model, CFG, at)
    for lam in ([0.2, 0.1, 0.1, 0.0], [0.2, 1.0, -0.3, 2e3], [-0.3, 0.9, 0.2, 1e3], [0.1, -0.2, 0.0, 0.0]):
        lam = np.array(lam)
        e = est.step(meas(volumes(lam), lam[3]))
        assert e.in_envelope and np.allclose(e.force, lam[:3], atol=1e-6), (lam, e.force)
    with pytest.raises(UserError, match="f_y_splits_N"):
        dataclasses.replace(ACFG, f_y_splits_N=(1.2,))


@pytest.mark.parametrize("order", [1, 2])
def test_the_default_atlas_follows_the_elements_order(order, monkeypatch):
    """With no atlas asked for, ``load_or_build`` builds :func:`default_atlas_config` of the forward
    model's element order: on the quadratic model the displacement axis in pieces along f_y, built
    together (one graph of tasks), in the order of f_y."""
    from types import SimpleNamespace

    from softphantom.estimation.atlas import build as atlas_mod
    from softphantom.estimation.atlas import catalogue
    from softphantom.estimation.atlas import config as atlas_config

    class Built(Exception):
        pass

    def build(model, cfg, acfg, **kw):
        raise Built(acfg, kw.get("pieces"))

    monkeypatch.setattr(catalogue, "piece_keys", lambda model, cfg, acfg: ("key",) * len(acfg.pieces()))
    monkeypatch.setattr(atlas_mod, "build_atlas", build)
    with pytest.raises(Built) as got:
        load_or_build(SimpleNamespace(element_order=order, layout=BIP_LAYOUT), CFG, None)
    acfg, pieces = got.value.args
    if order == 1:
        assert acfg == atlas_config.AtlasConfig() and pieces == (0,)
    else:
        assert (acfg.x_control, acfg.shape, acfg.f_y_splits_N) == ("displacement", (11, 6, 5, 3), (3.3,))
        assert pieces == (0, 1)
        assert [(c.force_min_N[1], c.force_max_N[1]) for c in acfg.patches()] == [
            (-1.0, atlas_config.P2_F_Y_SPLITS_N[0]), (atlas_config.P2_F_Y_SPLITS_N[0], 5.2)]


def test_a_uniform_stiffness_scale_is_the_atlas_with_the_loads_scaled(coarse_model, atlas, fwd, tmp_path,
                                                                      monkeypatch):
    """Every modulus times s (a calibration's uniform stiffness scale): the model's state under
    loads λ is the uncalibrated one's under λ/s (checked by two full solves), so the scaled atlas
    needs no build; the calibration carries it over (verified against the calibrated model, found
    by the estimators), and says which build an uneven scale needs."""
    from softphantom.calibration.output import calibrated_design, carry_atlases
    from softphantom.design import save_model
    from softphantom.estimation.atlas.config import model_atlas_config
    from softphantom.estimation.atlas.catalogue import verify_atlas

    s = 1.3
    model_s = dataclasses.replace(coarse_model, design=calibrated_design(coarse_model.design, {"bulb": s, "arms": s}))
    fwd_s = ForwardModel(model_s, CFG)
    lam = s * np.array([0.2, 0.8, -0.3, 2.0e3])
    a, b = fwd_s.solve(lam), fwd.solve(lam / s)
    assert np.allclose(a.V, b.V, rtol=1e-6, atol=1e-14) and np.abs(a.x - b.x).max() < 1e-9
    assert abs(a.V - fwd.solve(lam).V).max() > 0.1 * abs(a.V).max()  # not vacuous: the stiffness matters
    sc = atlas.scaled(s, atlas_key(fwd_s.model, fwd_s.config, ACFG.scaled(s)))
    assert np.allclose(sc.volumes(lam)[0], atlas.volumes(lam / s)[0], rtol=1e-12, atol=0)
    assert np.allclose(sc.points(lam), atlas.points(lam / s), rtol=0, atol=1e-15)
    assert abs(sc.volumes(lam)[0] - a.V).max() <= 1.01 * abs(atlas.volumes(lam / s)[0] - b.V).max() + 1e-16

    base = save_model(coarse_model, tmp_path / "base")
    save_atlas(atlas, atlas_path(base, atlas.key))
    out = tmp_path / "calibrated"
    save_model(model_s, out)
    note = carry_atlases(base, model_s, out, {"bulb": s, "arms": s}, law_changed=False)
    assert "carried over with the loads scaled by 1.3" in note
    (f,) = sorted((out / "atlas").glob("*.npz"))
    assert verify_atlas(f, model_s).key == sc.key
    monkeypatch.setattr("softphantom.estimation.atlas.build.build_atlas", lambda *a, **k: pytest.fail("built"))
    got = load_or_build(model_s, CFG, ACFG.scaled(s), cache_dir=out, fwd=fwd_s)
    assert got.key == sc.key and model_atlas_config(1, out) == model_atlas_config(1).scaled(s)
    # bulb and arms scaled differently: nothing carried, the build named
    out2 = tmp_path / "uneven"
    save_model(model_s, out2)
    note = carry_atlases(base, model_s, out2, {"bulb": s, "arms": 1.1}, law_changed=False, shown="cal/")
    assert "unevenly" in note and "softphantom atlas build --model cal/" in note and not (out2 / "atlas").exists()
    # its times from the build's cost model (estimate_build), the full grid's and the draft's
    from softphantom.estimation.atlas.build import duration_text, estimate_build

    full = estimate_build(1, len(model_s.nodes), model_atlas_config(1, out2))
    assert f"about {duration_text(full.wall_s)} on this machine's {full.workers} cores" in note
    assert f"{duration_text(full.critical_path_s)} on a cluster of {full.tasks} workers" in note and "--draft" in note


def test_a_shipped_atlas_is_found_by_its_key_for_any_copy_of_its_model(coarse_model, atlas, fwd, tmp_path,
                                                                        monkeypatch, capsys):
    """The package's atlases (listed in ``data/models/*/atlas.json``) are found by key: a model
    directory that ``design`` wrote with the same mesh loads the shipped file, builds nothing and
    writes nothing; ``atlas verify --model`` checks it; a damaged shipped file is refused naming it."""
    import json

    from softphantom.design import save_model
    from softphantom.estimation.atlas.build import AtlasMissing

    shipped = save_model(coarse_model, tmp_path / "pkg" / "coarse")
    path = save_atlas(atlas, atlas_path(shipped, atlas.key))
    # shipped: listed in the shipped model's manifest
    (shipped / "atlas.json").write_text(json.dumps({"pieces": [{"contact": "on-centre", "key": atlas.key[:32]}]}))
    monkeypatch.setattr("softphantom.design.model.SHIPPED_MODELS", tmp_path / "pkg")
    user = save_model(coarse_model, tmp_path / "user")
    got = load_or_build(coarse_model, CFG, ACFG, cache_dir=user, fwd=fwd, max_build_s=0.0)  # a build: AtlasMissing
    assert got.key == atlas.key and np.array_equal(got.cV, atlas.cV)
    assert not (user / "atlas").exists()
    assert main(["atlas", "verify", "--model", str(user)]) == 0
    assert f"ok  {path}" in capsys.readouterr().out
    with pytest.raises(AtlasMissing):  # another mesh: not found
        other = dataclasses.replace(coarse_model, nodes=coarse_model.nodes + 1e-5)
        load_or_build(other, CFG, ACFG, cache_dir=save_model(other, tmp_path / "other"), max_build_s=0.0)
    # a calibration's uniform stiffness scale carries the shipped atlas over, as it does a model's own
    from softphantom.calibration.output import calibrated_design, carry_atlases

    model_s = dataclasses.replace(coarse_model, design=calibrated_design(coarse_model.design, {"bulb": 1.2, "arms": 1.2}))
    out = save_model(model_s, tmp_path / "calibrated")
    assert "1 atlas file(s)" in carry_atlases(user, model_s, out, {"bulb": 1.2, "arms": 1.2}, law_changed=False)
    path.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(AtlasCorrupt, match=str(path)):
        load_or_build(coarse_model, CFG, ACFG, cache_dir=user, fwd=fwd, max_build_s=0.0)


def test_atlas_check_solves_held_out_loads_and_exits_1_on_a_missed_goal(coarse_model, atlas, tmp_path, monkeypatch,
                                                                          capsys):
    """``atlas check``: seeded held-out full solves against the atlas's map and inverse; the map's
    error at its own grid points is nil (the check compares like with like), a missed goal exits 1
    naming it, a model without an atlas exits 2 with the build's command."""
    from softphantom.design import save_model
    from softphantom.estimation.atlas.check import check_held_out, held_out_loads

    grid = np.array(np.meshgrid(*ACFG.axes(), indexing="ij")).reshape(4, -1).T
    at_grid = check_held_out(coarse_model, CFG, atlas, grid[[1, 17, 40]])
    assert at_grid.worst()["dV_mm3"] < 1e-6 and at_grid.worst()["points_mm"] < 1e-6
    loads = held_out_loads(ACFG.lower, ACFG.upper, 3, seed=4)
    held = check_held_out(coarse_model, CFG, atlas, loads, seed=4)
    assert len(held.loads) + held.skipped == 3 and not held.failed and held.worst()["dV_mm3"] > 1e-6
    model_dir = save_model(coarse_model, tmp_path / "model")
    assert main(["atlas", "check", "--model", str(model_dir), "--workers", "0"]) == 2  # no atlas yet
    assert "softphantom atlas build --model" in capsys.readouterr().err
    save_atlas(atlas, atlas_path(model_dir, atlas.key))
    monkeypatch.setattr("softphantom.estimation.atlas.catalogue.model_atlas_config", lambda order, d: ACFG)
    argv = ["atlas", "check", "--model", str(model_dir), "--workers", "0", "--loads", "3", "--seed", "4"]
    assert main([*argv, "--max-force-N", "10", "--max-pos-mm", "10", "--max-ang-deg", "10",
                 "--max-near-urethra-mm", "10"]) == 0
    out = capsys.readouterr().out
    assert f"{'map: arm volumes':24s} {held.worst()['dV_mm3']:.4f}" in out and "all goals met" in out
    assert main([*argv, "--max-force-N", "1e-9"]) == 1
    assert "atlas check: force_N" in capsys.readouterr().err
