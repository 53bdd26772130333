"""Usage: known_vs_rate.py BENCH_CACHE_DIR [fit_free.npz]. Known-load residuals (fitted force − known) at the keyframes against the load's rate there:
a pressure clock error dt shows as residual ≈ −dt · df/dt. Prints the regression dt per session."""
import sys, numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from softphantom.evaluation.files import read_table
D = Path(sys.argv[1]); f = np.load(D / (sys.argv[2] if len(sys.argv) > 2 else "fit_free.npz"))
ng = int(f["n_global"]); K = len(f["t"]); forces = f["z"][ng:].reshape(K, 3)
for s, d in enumerate([D / "bench-on-centre-30s", D / "bench-off-centre-30s"]):
    c = dict(read_table(d / "truth.csv").columns)
    sel = f["session"] == s; t = f["t"][sel]
    F = np.stack([c[f"force_{x}_N"] for x in "xyz"], 1)
    dF = np.gradient(F, c["t_s"], axis=0)
    rate = np.stack([np.interp(t, c["t_s"], dF[:, i]) for i in range(3)], 1)
    res = forces[sel] - f["known"][sel]
    dt = -(res.ravel() @ rate.ravel()) / (rate.ravel() @ rate.ravel())
    left = res + dt * rate
    print(f"{d.name}: fitted−known RMS {np.sqrt(np.mean(res**2)):.4f} N; as −dt·df/dt with dt = {dt * 1e3:+.1f} ms "
          f"leaves {np.sqrt(np.mean(left**2)):.4f} N; |df/dt| at keyframes up to {np.abs(rate).max():.2f} N/s, "
          f"{int(np.sum(np.linalg.norm(rate, axis=1) > 0.3))}/{sel.sum()} keyframes on a ramp")
