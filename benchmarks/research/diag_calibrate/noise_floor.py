"""What sets the held-out floor of a calibration: the held-out session of a bench_calibrate cache
regenerated from one truth solve with the board's noise and drift switched off one by one, and
each variant's held-out check with the truth's own parameters (the oracle: no calibration can do
better). Usage:

    .venv/bin/python benchmarks/research/diag_calibrate/noise_floor.py CACHE_DIR [--session needle-60s] [--fit-law yeoh] [--workers 2]
        [--variants exact,noise-only] [--levels 3] [--fit-from CACHE_DIR/fit_free_yeoh.npz]

CACHE_DIR is a bench_calibrate cache (its model/ and the held-out session's scenario and
virtual.json); the variants are written next to the session (``<session>-<variant>``). On the
9 mm cache, "exact" leaves 0.028 mm/deg with the truth's parameters, once the held-out check's lag
follows the fitted tube (``calibration.run.held_out_lag``; docs/calibration.md)."""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import bench_calibrate as bc  # noqa: E402

from softphantom.progress import message_handler  # noqa: E402
from softphantom.calibration import FitOptions, SessionSpec, check_held_out  # noqa: E402
from softphantom.design import build_model, load_model  # noqa: E402
from softphantom.virtual.board import BoardConfig  # noqa: E402
from softphantom.virtual.run import VirtualConfig, simulate, write_run  # noqa: E402
from softphantom.virtual.scenario import load_scenario  # noqa: E402
from softphantom.virtual.tracker import TrackerConfig  # noqa: E402
from softphantom.virtual.truth import TruthConfig, solve_truth  # noqa: E402

# (name, board noise in ADC codes, drift range K/min); None: the session's own settings. "quiet"
# still quantizes (un-dithered: ±half a 4.9 Pa code per arm); "exact" writes the transducers'
# pressures themselves (lagged, gains, no offset, no drift) into the recording: no ADC at all.
VARIANTS = (("exact", 0.0, 0.0), ("board", None, None), ("noise-only", None, 0.0), ("quiet", 0.0, 0.0),
            ("drift-only", 0.0, None))


def write_exact(run, rec: Path) -> None:
    """Replace the recording's tared arm pressures by the board's transducer pressures less their
    offsets, at each row's time (what a perfect ADC and a perfect tare would give)."""
    sig = run.signals
    lines = rec.read_text().splitlines(keepends=True)
    head = lines[1].rstrip("\n").split(",")
    cols = [head.index(f"dp_{a}_kPa") for a in bc.ARM_NAMES]
    it = head.index("t_s")
    out = lines[:2]
    for ln in lines[2:]:
        f = ln.rstrip("\n").split(",")
        t = float(f[it])
        for k, c in enumerate(cols):
            f[c] = f"{np.interp(t, sig.t, sig.p_transducer[:, k] - sig.offsets_Pa[k]) / 1e3:.9f}"
        out.append(",".join(f) + "\n")
    rec.write_text("".join(out))


def main() -> None:
    logging.getLogger("softphantom").addHandler(message_handler())  # the library's messages, not its progress
    logging.getLogger("softphantom").setLevel(logging.INFO)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cache", type=Path)
    ap.add_argument("--session", default="needle-60s")
    ap.add_argument("--fit-law", default="yeoh")
    ap.add_argument("--truth-law", default="yeoh")
    ap.add_argument("--truth-order", type=int, default=2)
    ap.add_argument("--truth-mesh-mm", type=float, default=9.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--variants", default="exact,noise-only")
    ap.add_argument("--levels", type=int, default=TruthConfig().levels,
                    help="the truth's keyframes per push ramp (interpolated in load level between them)")
    ap.add_argument("--fit-from", type=Path, default=None,
                    help="also check the parameters of this bench_calibrate dump (fit_<run>.npz)")
    a = ap.parse_args()
    model = load_model(a.cache / "model")
    src = a.cache / a.session
    board = json.loads((src / "virtual.json").read_text())["board"]
    scen = a.cache / "scenarios" / f"{a.session}.toml"
    tm = build_model(bc.truth_design(model.design, a.truth_law, a.truth_order), a.truth_mesh_mm)
    t = time.perf_counter()
    truth = solve_truth(load_scenario(scen), model, TruthConfig(levels=a.levels), truth_mesh=tm)
    print(f"truth of {a.session}: {len(tm.nodes)} nodes, {a.levels} levels a ramp, {time.perf_counter() - t:.0f} s",
          flush=True)
    yeoh = a.fit_law == "yeoh" and a.truth_law == "yeoh"
    checks = [("truth's parameters", bc.oracle_values((bc.YEOH_C20_C10, bc.YEOH_C30_C10) if yeoh else None))]
    if a.fit_from is not None:
        checks.append((a.fit_from.name, bc.dump_values(a.fit_from)))
    for name, noise, drift in VARIANTS:
        if name not in a.variants.split(","):
            continue
        d = src.parent / f"{a.session}-{name}" if a.levels == TruthConfig().levels else \
            src.parent / f"{a.session}-{name}-L{a.levels}"
        bcfg = BoardConfig(seed=board["seed"], tube_length_m=12.0 * bc.TUBE_TRUE, gains=(1, 1, bc.GAIN_TRUE, 1, 1))
        if noise is not None:
            bcfg = dataclasses.replace(bcfg, noise_codes=noise)
        if drift is not None:
            bcfg = dataclasses.replace(bcfg, drift_K_per_min=drift)
        cfg = VirtualConfig(TruthConfig(), bcfg, TrackerConfig(seed=board["seed"]))
        run = simulate(scen, model, cfg, truth=truth)
        write_run(run, d)
        if name == "exact":
            write_exact(run, d / "recording.csv")
        bc.believe_tube(d / "recording.csv")
        drew = json.loads((d / "virtual.json").read_text())["board"]
        print(f"\n== {name}: noise {bcfg.noise_codes} codes, drift {drew['drift_Pa_per_s']} Pa/s "
              f"(the session's: {board['drift_Pa_per_s']} Pa/s)", flush=True)
        for what, values in checks:
            h = check_held_out(a.cache / "model", [SessionSpec(d / "recording.csv", d / "truth.csv", "on-centre")],
                               values, options=FitOptions(law=a.fit_law), n_workers=a.workers)
            bc.print_pose_rmse(f"held-out {name}, nominal → {what}", h)


if __name__ == "__main__":
    main()
