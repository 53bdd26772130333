"""Usage: law_form.py BENCH_CACHE_DIR WORK_DIR. Which parameters can represent another law's arm ΔV?
On the nominal mesh (BENCH_CACHE_DIR/model, neo-Hookean), bulb × 1.3, six pushes (3 N along +y and
(±0.6, 2.5, ∓0.6) N, on- and off-centre): solves under the design's law (exact scale and force
sensitivities), under the Yeoh preset and under Yeoh with C20 = C30 = 0 (the decoupled form, same
small-strain μ and K), and with λ × 1.2 in the arms and in the bulb (finite differences: ν's
direction). Then the Yeoh − neo-Hookean difference (ΔV as pressure at 1 Pa, markers at 0.2 mm, the
forces free at 0.02 N) fitted by linear least squares with the stiffness scales alone, + ln λ per
group, + per-arm gains: the cost left and the parameters it takes (docs/calibration.md)."""
import dataclasses, sys, time
import numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[3])); sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench_calibrate import with_law
from softphantom.design import load_model, save_model
from softphantom.calibration import forward as fw
from softphantom.fem import cavity_volume, solve_static

SCALES = {"bulb": 1.3, "arms": 1.0}
PA_PER_M3, SIG_P, SIG_M, SIG_F = 101325 / 14.1e-6, 1.0, 0.2e-3, 0.02  # ≈ 7.2 Pa per mm³ (V_T 14.1 cm³)


def lam_solve(model_dir, contact, f, group, factor, x0):
    base = fw._base(model_dir, contact, 4e-3)
    fem = fw.scaled_fem(base.fem, fw._tet_scale(base, SCALES))
    prm, lam, sel = np.array(fem.params, float), np.array(fem.lam, float), base.group_tets[group]
    prm[sel, 1] *= factor
    lam[sel] *= factor
    sol = solve_static(dataclasses.replace(fem, params=prm, lam=lam), base.H @ np.asarray(f, float), x0=x0, tol=1e-9,
                       solver=base.solver)
    assert sol.converged, sol.status
    x = sol.x.reshape(-1)
    return np.array([cavity_volume(x, fem.cavities[a]) for a in fw.ARM_NAMES]) - base.V0, np.asarray(base.P @ x.reshape(-1, 3))


def solve_all(D, W):
    m = load_model(D / "model")
    dirs = {}
    for name, kw in (("yeoh", {}), ("yeoh00", {"shape": (0.0, 0.0)})):
        dirs[name] = W / name
        if not (dirs[name] / "model.npz").is_file():
            save_model(dataclasses.replace(m, design=with_law(m.design, "yeoh", m.element_order, **kw)), dirs[name])
    rows, h = [], 1.2
    for contact in ("on-centre", "off-centre"):
        c = tuple(float(v) for v in m.p_ext[contact])
        for f in ([0.0, 3.0, 0.0], [0.6, 2.5, -0.6], [-0.6, 2.5, 0.6]):
            t = time.perf_counter()
            s = fw.solve_keyframe(str(D / "model"), c, 4e-3, SCALES, np.array(f), 0.0)
            r = dict(nh_dV=s.dV, nh_M=s.markers, dV_df=s.dV_df, dV_dlnc=s.dV_dlnc, dM_df=s.dM_df, dM_dlnc=s.dM_dlnc)
            for nm, d in dirs.items():
                q = fw.solve_keyframe(str(d), c, 4e-3, SCALES, np.array(f), 0.0, x0=s.x)
                r[nm + "_dV"], r[nm + "_M"] = q.dV, q.markers
            for g in ("arms", "bulb"):
                dv, M = lam_solve(str(D / "model"), c, f, g, h, s.x)
                r[f"dV_dlnlam_{g}"], r[f"dM_dlnlam_{g}"] = (dv - s.dV) / np.log(h), (M - s.markers) / np.log(h)
            rows.append(r)
            print(contact, f, f"{time.perf_counter() - t:.0f} s; ΔV ratio per arm yeoh/nh", (r["yeoh_dV"] / s.dV).round(4),
                  "yeoh00/nh", (r["yeoh00_dV"] / s.dV).round(4), flush=True)
    return rows


def fit(rows, target, cols):
    n, G = len(rows), len(cols)
    A, b = [], []
    for k, r in enumerate(rows):
        for what, sig, d in (("dV", SIG_P / PA_PER_M3, r[target + "_dV"] - r["nh_dV"]),
                             ("M", SIG_M, (r[target + "_M"] - r["nh_M"]).reshape(-1))):
            pre = "dV" if what == "dV" else "dM"
            J = np.zeros((d.size, G + 3 * n))
            J[:, G + 3 * k:G + 3 * k + 3] = r[f"{pre}_df"].reshape(-1, 3) / sig
            for j, c in enumerate(cols):
                if c in ("c_bulb", "c_arms"):
                    J[:, j] = r[f"{pre}_dlnc"][..., ("c_bulb", "c_arms").index(c)].reshape(-1) / sig
                elif c.startswith("lam_"):
                    J[:, j] = r[f"{pre}_dlnlam_" + c[4:]].reshape(-1) / sig
                elif what == "dV":  # gain of arm i: scales its pressure
                    i = int(c[-1])
                    J[i, j] = r["nh_dV"][i] / sig
            A.append(J)
            b.append(d / sig)
        Jf = np.zeros((3, G + 3 * n))
        Jf[:, G + 3 * k:G + 3 * k + 3] = np.eye(3) / SIG_F
        A.append(Jf)
        b.append(np.zeros(3))
    A, b = np.vstack(A), np.concatenate(b)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    res = b - A @ x
    return 0.5 * b @ b, 0.5 * res @ res, {c: round(float(v), 4) for c, v in zip(cols, x[:G])}


def main():
    D, W = Path(sys.argv[1]), Path(sys.argv[2])
    W.mkdir(parents=True, exist_ok=True)
    rows = solve_all(D, W)
    gains = ["gain0", "gain1", "gain2", "gain3"]
    for target in ("yeoh", "yeoh00"):
        for cols in (["c_bulb", "c_arms"], ["c_bulb", "c_arms", "lam_arms"], ["c_bulb", "c_arms", "lam_arms", "lam_bulb"],
                     ["c_bulb", "c_arms"] + gains, ["c_bulb", "c_arms", "lam_arms", "lam_bulb"] + gains):
            c0, c1, x = fit(rows, target, cols)
            print(f"{target} − nh, fitted by {' '.join(cols)}: cost {c0:.0f} → {c1:.1f}; (ln factors, gain − 1) {x}")


if __name__ == "__main__":
    main()
