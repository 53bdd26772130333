"""Usage: law_vs_mesh.py BENCH_CACHE_DIR OUT_MODEL_DIR. Same mesh (the nominal NH P2 12 mm), the two laws: arm ΔV under the same loads (bulb × 1.3).
Separates the law's share of the front arms' ΔV deficit from the mesh's."""
import dataclasses, sys, numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[3])); sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench_calibrate import with_law
from softphantom.design import load_model, save_model
from softphantom.calibration.forward import solve_keyframe
D = Path(sys.argv[1]); out = Path(sys.argv[2])
m = load_model(D / "model")
if not (out / "model.npz").is_file():
    save_model(dataclasses.replace(m, design=with_law(m.design, "yeoh", m.element_order)), out)
arms = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
scales = {"bulb": 1.3, "arms": 1.0}
for contact in ("on-centre", "off-centre"):
    c = tuple(m.p_ext[contact])
    for f in ([0.0, 3.0, 0.0], [0.6, 2.5, -0.6], [-0.6, 2.5, 0.6]):
        r = {}
        for name, d in (("nh", D / "model"), ("yeoh", out)):
            r[name] = solve_keyframe(str(d), c, 4e-3, scales, np.array(f), 0.0).dV
        print(contact, f, "yeoh/nh ΔV per arm:", " ".join(f"{a} {y / n:.4f}" for a, y, n in zip(arms, r["yeoh"], r["nh"])),
              "| nh ΔV mm³", (r["nh"] * 1e9).round(2), flush=True)
