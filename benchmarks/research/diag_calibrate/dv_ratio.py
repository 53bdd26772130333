"""Model ΔV (fitted scales, fitted forces) against the truth's ΔV per arm at the keyframes; and
the fitted forces against the known loads. Usage: dv_ratio.py CACHE_DIR [fit_free.npz]"""
import sys, numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from softphantom.evaluation.files import read_table
D = Path(sys.argv[1]); f = np.load(D / (sys.argv[2] if len(sys.argv) > 2 else "fit_free.npz"))
arms = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
dirs = [D / "bench-on-centre-30s", D / "bench-off-centre-30s"]
ng = int(f["n_global"]); K = len(f["t"]); forces = f["z"][ng:].reshape(K, 3)
for s, d in enumerate(dirs):
    tab = read_table(d / "truth.csv"); c = dict(tab.columns)
    sel = f["session"] == s; t = f["t"][sel]
    dv_t = np.stack([np.interp(t, c["t_s"], c[f"dV_{a}_mm3"]) for a in arms], 1) * 1e-9
    dv_m = f["dV"][sel]
    big = np.abs(dv_t) > 0.2 * np.abs(dv_t).max(0)
    print(d.name)
    for i, a in enumerate(arms):
        b = big[:, i]
        # least-squares ratio model/truth over keyframes with a sizeable ΔV
        r = (dv_m[b, i] @ dv_t[b, i]) / (dv_t[b, i] @ dv_t[b, i])
        print(f"  {a:11s} model/truth ΔV {r:.4f}  (n={b.sum()}, |ΔV| up to {np.abs(dv_t[:, i]).max() * 1e9:.1f} mm³)")
    ft = np.stack([np.interp(t, c["t_s"], c[f"force_{x}_N"]) for x in "xyz"], 1)
    print("  fitted force − truth force RMS (N) x y z:", np.sqrt(np.mean((forces[sel] - ft) ** 2, 0)).round(4),
          " fitted − known:", np.sqrt(np.mean((forces[sel] - f["known"][sel]) ** 2, 0)).round(4))
