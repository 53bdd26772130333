"""Full forward solves at seeded loads for the ROM probe: MODEL_DIR N_TRAIN N_TEST OUT.pkl (16 near-corners of
the box below the fold plus Latin-hypercube loads; each solved from the nearest solved load)."""
import sys, time, pickle
import numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from softphantom.design import load_model
from softphantom.estimation import EstimatorConfig, ForwardModel

model = load_model(sys.argv[1])
n_train, n_test = int(sys.argv[2]), int(sys.argv[3])
fwd = ForwardModel(model, EstimatorConfig(contact="on-centre"))  # exact sensitivities: U at every solve
fem = fwd.fem
print("nodes", fem.n_nodes, "tets", fem.tets.shape, "free", fem.n_free, flush=True)
lo = np.array([-2.0, -1.0, -2.0, -2e3]); hi = np.array([2.0, 4.0, 2.0, 40e3])
rng = np.random.default_rng(3)
def lhs(n):
    u = (rng.permuted(np.tile(np.arange(n), (4, 1)), axis=1).T + rng.uniform(size=(n, 4))) / n
    return lo + (hi - lo) * u
# training: the box's corners-ish (a 2x2x2x2 = 16 corners at 90 %), plus LHS
corners = np.array(np.meshgrid(*[[0.05, 0.95]] * 4, indexing="ij")).reshape(4, -1).T
train = np.concatenate([lo + (hi - lo) * corners, lhs(n_train - 16)])
test = lo + (hi - lo) * rng.uniform(0.05, 0.95, size=(n_test, 4))
scale = hi - lo
solved = [(np.zeros(4), fwd.rest)]
def solve(lam):
    d = [np.max(np.abs((lam - s.lam) / scale)) for _, s in solved]
    start = solved[int(np.argmin(d))][1]
    t = time.process_time()
    lin = fwd.solve(lam, start)
    solved.append((lam, lin))
    return lin, time.process_time() - t
out = {"train": [], "test": []}
for name, loads in (("train", train), ("test", test)):
    order = np.argsort(np.linalg.norm((loads - lo) / scale - 0.0, axis=1)) if name == "train" else range(len(loads))
    for i in order:
        lam = loads[i]
        try:
            lin, cpu = solve(lam)
        except Exception as e:
            print(name, i, lam, "FAILED", e, flush=True); continue
        out[name].append((lam, lin.x.copy(), lin.V.copy(), lin.sub_x.copy(), cpu, lin.U.copy()))
        print(name, i, np.round(lam, 2), f"{cpu:.1f} CPU-s", flush=True)
pickle.dump(out, open(sys.argv[4], "wb"))
