"""The ROM probe: POD of the snapshots (plus the rest static modes), Galerkin and ECSW solves at the held-out
loads against their full solves: MODEL_DIR SNAPSHOTS.pkl [R_MAX] [ECSW_TOL (also the slow ECSW probe)] (docs/estimation.md)."""
import sys, time, pickle
import numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from softphantom.design import load_model
from softphantom.estimation import EstimatorConfig, ForwardModel
from rom import ROM

model = load_model(sys.argv[1])
snap = pickle.load(open(sys.argv[2], "rb"))
r_max = int(sys.argv[3]) if len(sys.argv) > 3 else 80
tol = float(sys.argv[4]) if len(sys.argv) > 4 else 1e-4  # given: also the ECSW model
fwd = ForwardModel(model, EstimatorConfig(contact="on-centre"), exact_sensitivities=False)
train, test = snap["train"], snap["test"]
print(len(train), "train", len(test), "test; full solve CPU-s median", np.median([t[4] for t in train + test]))
X = [t[1] for t in train]
# static modes: K^-1 B at rest (the linear responses) and, where the snapshots carry them, at every
# snapshot (the exact sensitivities each solve gives), per 1 N and per 1 kPa, as extra directions
rest = fwd.rest
scale = np.array([1.0, 1.0, 1.0, 1e3])
extra = [rest.U * scale] + [t[5] * scale for t in train if len(t) > 5]
t0 = time.process_time()
rom = ROM(fwd, X, extra_modes=np.concatenate(extra, axis=1), r_max=r_max)
print(f"POD: r = {rom.r}, sv tail {rom.sv[rom.r - 1] / rom.sv[0]:.1e}, {time.process_time() - t0:.1f} CPU-s")
def evaluate(label):
    errs = []
    t_all = 0.0
    for lam, x, V, P, *_ in test:
        t = time.process_time()
        try:
            q, xr, its = rom.solve(lam)
        except RuntimeError as e:
            print("  fail", np.round(lam, 2), e); continue
        t_all += time.process_time() - t
        Vr = fwd.eq.arm_volumes(xr)
        Pr = fwd.probe @ xr.reshape(-1, 3)
        errs.append((np.abs(Vr - V).max() * 1e9, np.linalg.norm(Pr - P, axis=1).max() * 1e3, its))
    e = np.array(errs)
    print(f"{label}: ROM at {len(e)} test loads: volume err max {e[:, 0].max():.4f} mm3 (median {np.median(e[:, 0]):.4f}), "
          f"points max {e[:, 1].max():.4f} mm (median {np.median(e[:, 1]):.4f}), Newton its {e[:, 2].mean():.1f}, "
          f"{t_all / max(len(e), 1) * 1e3:.0f} CPU-ms a solve")
# the projection error alone (best the basis can do)
pe = [np.linalg.norm((x - fwd.fem.x_rest)[rom.free] - rom.V @ (rom.V.T @ (x - fwd.fem.x_rest)[rom.free]), np.inf) * 1e3 for _, x, *_ in test]
print(f"projection error of test states: max {max(pe):.4f} mm")
def full_reduced(q, lam, need_K=True):
    """Vᵀ r(x) and Vᵀ K(x) V on the full assembly (no hyper-reduction)."""
    from softphantom.fem import free_tangent
    from softphantom.fem.corotational import ElementInversionError
    x = rom.x0 + rom.Vfull @ q
    try:
        r, _ = fwd.eq.residual(x, lam)
    except ElementInversionError:
        return None, None, x
    if not need_K:
        return rom.V.T @ r, None, x
    K = free_tangent(fwd.fem, x, [(fwd.eq._ur_tris, float(lam[3]))] if lam[3] else None)
    return rom.V.T @ r, rom.V.T @ (K @ rom.V), x


def galerkin(lam):
    _, ref = fwd.eq.residual(fwd.fem.x_rest, np.asarray(lam, float))  # the applied load's scale
    return ROM.solve(rom, lam, reduced=full_reduced, ref=ref)


rom.solve = lambda lam, q0=None: galerkin(lam)
evaluate("Galerkin, full assembly")
if len(sys.argv) > 4:
    t0 = time.process_time()
    del rom.solve
    rom.train_ecsw(X, tol=tol)
    print(f"ECSW training {time.process_time() - t0:.1f} CPU-s")
    evaluate(f"ECSW tol {tol:g}")
