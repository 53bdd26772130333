"""The atlas estimator's compiled per-sample step against its references: the
kernel evaluation against numpy tensor contractions and finite differences, the kernel rigid fit
against ``pose.rigid_fit``, and the step against the pre-kernel step (every Gauss–Newton step by
the QP solver) on an atlas of a known non-linear map — no forward solves, so it runs in seconds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from softphantom.estimation import AtlasConfig, AtlasEstimator, EstimatorConfig, ForwardModel
from softphantom.estimation.atlas import kernels as ak
from softphantom.estimation.atlas.basis import to_chebyshev
from softphantom.estimation.atlas.map import Atlas
from softphantom.estimation.atlas.catalogue import atlas_key
from softphantom.pose import matrix_from_ypr, rigid_fit, ypr_from_matrix
from softphantom.sensing import Measurement

CFG = EstimatorConfig(contact="on-centre")
ACFG = AtlasConfig(force_min_N=(-1.0, -0.5, -1.0), force_max_N=(1.0, 5.0, 1.0), p_min_kPa=-2.0, p_max_kPa=4.0,
                   n_force=(5, 7, 4), n_pressure=3, force_cluster_N=(0.0, 0.0, 0.0), x_control="force")
# the same with f_x stretched (points clustered about 0, the default's layout): every test runs on both
ACFG_STRETCHED = dataclasses.replace(ACFG, force_cluster_N=(0.3, 0.0, 0.0))
RNG = np.random.default_rng(11)
A = np.array([[1.0, 0.3, -0.2], [0.2, 1.3, 0.1], [-0.4, 0.1, 0.9], [0.3, -0.9, 0.4]]) * 1e-9  # m³/N
A_P = np.array([2.0, 1.5, 1.0, 2.5]) * 1e-12  # m³/Pa


def meas(dV, p=0.0, t=0.0):
    return Measurement(t, 0, t, np.full(5, 51150), 100, np.zeros(4), np.asarray(dV, float), p)


def volumes_map(lam):
    """A smooth non-linear map (N, Pa → m³): linear part A, a stiffening and a cross term."""
    f, p = lam[..., :3], lam[..., 3:]
    lin = f @ A.T + p * A_P
    quad = 0.04e-9 * np.stack([f[..., 1] ** 2, f[..., 0] * f[..., 1], np.sin(f[..., 2]), f[..., 1] * f[..., 2]], -1)
    return lin - quad


@pytest.fixture(scope="module")
def fwd(coarse_model):
    return ForwardModel(coarse_model, CFG)


@pytest.fixture(scope="module")
def atlas(fwd):
    return make_atlas(fwd, ACFG)


@pytest.fixture(scope="module", params=[ACFG, ACFG_STRETCHED], ids=["affine", "stretched"])
def atlas_any(fwd, request):
    return make_atlas(fwd, request.param)


def make_atlas(fwd, acfg):
    """The atlas of ``volumes_map`` (points: the rest tracked points moved linearly plus a twist)."""
    shape = acfg.shape
    g = np.stack(np.meshgrid(*acfg.axes(), indexing="ij"), axis=-1)  # (n1..n4, 4)
    rest = fwd.rest.sub_x
    Bp = RNG.normal(size=(rest.shape[0], 3, 4)) * np.array([1e-4, 1e-4, 1e-4, 1e-8])
    P = rest + np.einsum("kaj,...j->...ka", Bp, g) + 1e-5 * np.sin(g[..., 1])[..., None, None] * rest[:, ::-1]
    r = 3
    modes = np.linalg.qr(RNG.normal(size=(fwd.fem.n_dof, r)))[0] * 1e-3
    coef = np.stack([g[..., 0] * g[..., 1], g[..., 2], np.cos(g[..., 1])], -1)
    return Atlas(key=atlas_key(fwd.model, fwd.config, acfg), config=acfg, cV=to_chebyshev(volumes_map(g), shape),
                 cP=to_chebyshev(P.reshape(*shape, -1), shape).reshape(*shape, -1, 3),
                 cF=to_chebyshev(coef, shape), modes=modes, x_rest=fwd.fem.x_rest.copy(), build_s=0.0,
                 solves=int(np.prod(shape)), field_rms_m=0.0, solved=np.ones(shape, bool))


def test_kernel_evaluation_equals_the_tensor_contraction_and_its_derivative(atlas_any):
    atlas = atlas_any
    lo, hi = ACFG.lower, ACFG.upper
    for lam in lo + (hi - lo) * RNG.uniform(-0.05, 1.05, (20, 4)):  # a little outside the box too
        V, J = atlas.volumes(lam)
        Vr, Jr = atlas.volumes_reference(lam)
        assert np.allclose(V, Vr, rtol=0, atol=1e-12 * np.abs(Vr).max())
        assert np.allclose(J, Jr, rtol=0, atol=1e-12 * np.abs(Jr).max())
        # the Jacobian is the derivative of the kernel's own value (central differences)
        for j, h in enumerate((1e-5, 1e-5, 1e-5, 1e-2)):
            e = np.eye(4)[j] * h
            fd = (atlas.volumes(lam + e)[0] - atlas.volumes(lam - e)[0]) / (2 * h)
            assert np.allclose(J[:, j], fd, rtol=1e-6, atol=1e-7 * np.abs(J[:, j]).max())
        assert np.allclose(atlas.points(lam), atlas.value_reference(atlas.cP, lam), rtol=0, atol=1e-15)
        field = atlas.x_rest + atlas.modes @ atlas.value_reference(atlas.cF, lam)
        assert np.allclose(atlas.nodes(lam), field.reshape(-1, 3), rtol=0, atol=1e-15)
    # and the polynomial is the map it was fitted to, at the grid points
    g = np.array([a[1] for a in atlas.config.axes()])
    assert np.allclose(atlas.volumes(g)[0], volumes_map(g), rtol=1e-12, atol=0)


def test_kernel_pose_equals_pose_rigid_fit():
    """``points_pose`` on constant points (only the T_0 coefficient): the rigid fit and its Euler
    angles as ``pose.rigid_fit`` and ``ypr_from_matrix``, also for a mirror image and at gimbal lock."""
    P = RNG.normal(size=(5, 3)) * 0.03
    cp = P.mean(axis=0)
    shape = np.array([2, 3, 2, 2])
    box = (np.full(4, -1.0), np.full(4, 1.0), np.array([0.3, 0.0, 0.0, 0.0]), RNG.uniform(-1, 1, 4))
    for k in range(10):
        ang = RNG.normal(size=3) * (0.3 if k else 3.0)  # one large rotation
        R0 = matrix_from_ypr(ang)
        if k == 2:
            R0 = matrix_from_ypr([0.4, np.pi / 2, 0.3])  # gimbal lock: pitch 90°
        Q = P @ R0.T + RNG.normal(size=3) * 0.01 + RNG.normal(size=P.shape) * (1e-4 if k != 2 else 0.0)
        if k == 1:
            Q = P * [1, 1, -1]  # a mirror image: the reflection guard must keep det R = +1
        CP = np.zeros((24, 15))
        CP[0] = Q.ravel()
        pts, t, ypr = np.empty(15), np.empty(3), np.empty(3)
        ak.points_pose(CP, shape, *box, P - cp, cp, pts, t, ypr)
        ref = rigid_fit(P, Q)
        assert np.allclose(pts, Q.ravel(), rtol=0, atol=1e-15)
        assert np.allclose(t, ref.t, atol=1e-14)
        assert np.allclose(matrix_from_ypr(ypr), ref.R, atol=1e-12)
        assert np.allclose(ypr, ypr_from_matrix(ref.R), atol=1e-12)  # rad


def ramp():
    """Samples of a 4.5 N push along +y with sideways wobble and pressure, one beyond the f_x face
    (a bound in the way), one with the pressure above the envelope."""
    out = []
    for k, fy in enumerate(np.r_[np.linspace(0, 4.5, 60), np.linspace(4.5, 0.2, 20)]):
        lam = np.array([0.2 * np.sin(k / 9), fy, -0.1 * np.cos(k / 13), 1e3 * np.sin(k / 7)])
        if k == 30:
            lam[0] = 1.6  # beyond f_x ≤ 1 N
        if k == 50:
            lam[3] = 6e3  # above 4 kPa
        out.append(meas(volumes_map(lam), lam[3], k / 77.0))
    return out


def test_step_equals_the_reference_step(coarse_model, atlas_any):
    atlas = atlas_any
    fast, ref = AtlasEstimator(coarse_model, CFG, atlas), AtlasEstimator(coarse_model, CFG, atlas)
    flags = []
    for m in ramp():
        a, b = fast.step(m), ref.step_reference(m)
        assert a.status == b.status == "ok"
        assert (a.qp_status, a.in_envelope, a.extra["gn_iterations"]) == (b.qp_status, b.in_envelope,
                                                                          b.extra["gn_iterations"])
        assert np.allclose(a.force, b.force, rtol=0, atol=1e-9)  # N
        assert np.allclose(a.pose.to_mm_deg(), b.pose.to_mm_deg(), rtol=0, atol=1e-9)  # mm, deg
        for name in fast.target_names:
            assert np.allclose(a.target_shift[name], b.target_shift[name], rtol=0, atol=1e-12)
        assert np.allclose(a.volume_pred, b.volume_pred, rtol=0, atol=1e-18)  # 1e-9 mm³
        assert a.cond_W == pytest.approx(b.cond_W, rel=1e-9)
        assert a.extra["qp_residual_m3"] == pytest.approx(b.extra["qp_residual_m3"], rel=1e-6, abs=1e-21)
        flags.append(a.in_envelope)
    assert flags.count(False) == 2  # the two samples outside the envelope, and only those
    assert np.allclose(fast.node_positions(), ref.node_positions(), rtol=0, atol=1e-15)


def test_warm_start_gives_the_cold_start_answer(coarse_model, atlas):
    est = AtlasEstimator(coarse_model, CFG, atlas)
    lam = np.array([0.3, 2.5, -0.4, 1.5e3])
    warm = est.invert(volumes_map(lam), lam[3], start=lam + [0.02, -0.03, 0.01, 0])
    cold = est.invert(volumes_map(lam), lam[3], start=np.zeros(4))
    assert warm[1] == cold[1] == "optimal" and warm[2] and cold[2]
    assert np.allclose(warm[0], cold[0], rtol=0, atol=1e-8)  # N: the same minimum
    assert np.allclose(warm[0], lam, rtol=0, atol=1e-4)  # the map, to the polynomial's interpolation error
    assert warm[5] < cold[5]  # fewer Gauss–Newton iterations from nearby


def test_qp_solver_only_where_a_bound_is_active(coarse_model, atlas, monkeypatch):
    import softphantom.estimation.atlas.estimator as atlas_mod

    calls = []
    real = atlas_mod.solve_volume_qp
    monkeypatch.setattr(atlas_mod, "solve_volume_qp", lambda *a: calls.append(a[-1]) or real(*a))
    lam = np.array([0.3, 2.5, -0.4, 1.5e3])
    for solver in ("daqp", "quadprog"):
        est = AtlasEstimator(coarse_model, EstimatorConfig(contact="on-centre", qp_solver=solver), atlas)
        assert est.invert(volumes_map(lam), lam[3])[1] == "optimal" and not calls  # inside: no QP
        out = np.array([0.3, 5.8, -0.4, 1.5e3])  # beyond f_y ≤ 5 N: the bound holds f_y
        got = est.invert(volumes_map(out), out[3])
        ref = est.invert_reference(volumes_map(out), out[3])
        assert calls and set(calls) == {solver}  # the configured solver took the bounded steps
        assert got[0][1] == pytest.approx(5.0) and not got[2]  # clamped, flagged
        assert np.allclose(got[0], ref[0], rtol=0, atol=1e-9) and got[1] == ref[1] and got[5] == ref[5]
        calls.clear()


def _fit_and_eval(values, acfg, lams):
    """The atlas polynomial of grid ``values`` (shape + ()) at ``lams`` (k, 4) by the kernel."""
    shape = np.array(acfg.shape, dtype=np.int64)
    C = np.ascontiguousarray(to_chebyshev(values[..., None], acfg.shape).reshape(-1, 1))
    out = np.empty(1)
    res = []
    for lam in lams:
        ak.eval_value(C, shape, acfg.lower, acfg.upper, acfg.stretch, np.asarray(lam, float), out)
        res.append(out[0])
    return np.array(res)


def test_interpolant_reproduces_polynomials_of_its_degree_in_each_axis_variable():
    """Exact for a tensor polynomial of degree n_a − 1 in each axis's variable: the load itself on
    an affine axis, asinh(f / w) on a stretched one (the analytic check of ``axis_t`` and
    ``cheb_points``: the grid is Chebyshev–Lobatto in that variable)."""
    acfg = dataclasses.replace(ACFG, force_cluster_N=(0.2, 0.0, 0.5))
    rng = np.random.default_rng(5)
    coef = rng.normal(size=acfg.shape)  # monomial coefficients in the axis variables u_a

    def u(lam):  # the variables in which the map is a polynomial: asinh(f/w) where stretched
        w = acfg.stretch
        return np.where(w > 0, np.arcsinh(lam / np.where(w > 0, w, 1.0)), lam * np.array([1, 1, 1, 1e-3]))

    def poly(lam):
        x = u(lam)
        out = coef
        for a in range(4):
            out = np.tensordot(x[a] ** np.arange(acfg.shape[a]), out, axes=([0], [0]))
        return float(out)

    grid = np.stack(np.meshgrid(*acfg.axes(), indexing="ij"), axis=-1)
    values = np.vectorize(lambda *l: poly(np.array(l)))(*np.moveaxis(grid, -1, 0))
    lams = acfg.lower + (acfg.upper - acfg.lower) * rng.uniform(0, 1, (30, 4))
    want = np.array([poly(lam) for lam in lams])
    assert np.allclose(_fit_and_eval(values, acfg, lams), want, rtol=0, atol=1e-9 * np.abs(values).max())
    # a polynomial in the load itself of the same degree is not reproduced on the stretched axis
    lin = np.vectorize(lambda *l: l[0] ** 3)(*np.moveaxis(grid, -1, 0))
    assert np.abs(_fit_and_eval(lin, acfg, lams) - lams[:, 0] ** 3).max() > 1e-4


def test_stretched_axis_follows_a_sharp_step_about_zero_force():
    """Why f_x is stretched by default: a tanh step 0.05 N wide near f_x = 0 (the default design's
    arms 2 and 3 at pushes above ≈ 3.5 N) with 9 points on ±1.5 N — the affine Chebyshev grid misses
    it by 90 % of the half-jump, the grid stretched with w = 0.05 N by ≈ 10 %."""
    lams = np.zeros((601, 4))
    lams[:, 0] = np.linspace(-1.5, 1.5, 601)
    err = {}
    for w in (0.0, 0.05):
        acfg = dataclasses.replace(ACFG, force_min_N=(-1.5, -0.5, -1.0), force_max_N=(1.5, 5.0, 1.0),
                                   n_force=(9, 3, 3), n_pressure=2, force_cluster_N=(w, 0.0, 0.0))
        fx = acfg.axes()[0]
        values = np.broadcast_to(np.tanh((fx - 0.01) / 0.05)[:, None, None, None], acfg.shape).copy()
        err[w] = np.abs(_fit_and_eval(values, acfg, lams) - np.tanh((lams[:, 0] - 0.01) / 0.05)).max()
    assert err[0.0] > 0.8 and err[0.05] < 0.12


def test_the_estimator_reads_only_the_atlas_public_interface():
    """``AtlasEstimator`` uses the atlas through its public names (``Atlas.kernel``, ``points``, …):
    no ``obj._name`` on anything but itself."""
    import ast
    import inspect

    import softphantom.estimation.atlas.estimator as mod

    private = [f"{ast.unparse(n.value)}.{n.attr}" for n in ast.walk(ast.parse(inspect.getsource(mod)))
               if isinstance(n, ast.Attribute) and n.attr.startswith("_") and not n.attr.startswith("__")
               and not (isinstance(n.value, ast.Name) and n.value.id == "self")]
    assert not private, private


@pytest.mark.skipif(not ak.HAVE_NUMBA, reason="numba kernels")
def test_the_step_kernels_keep_the_gil():
    """A kernel that released the GIL would hand it, at every call of a step, to any busy Python thread
    of the process (a Dask client's event loop, a progress display) for up to the 5 ms switch
    interval: the demo's step p99 of several ms (``bench_estimate.py``'s busy-thread row)."""
    kernels = [f for f in vars(ak).values() if hasattr(f, "targetoptions")]
    assert {"gn_run", "gn_update", "points_pose", "force_chain", "cond_force", "eval_vj3"} <= {f.__name__ for f in kernels}
    assert [f.__name__ for f in kernels if f.targetoptions.get("nogil")] == []
