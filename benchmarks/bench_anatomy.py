"""Anatomy import on label maps as public zonal data sets publish them: wall time to a valid,
meshed, solvable design.

Run: ``.venv/bin/python benchmarks/bench_anatomy.py [--volumes-mL 30,47,60] [--template both|default|linear]``

Each map is ``zonal_label_map`` of tests/label_maps.py: an ellipsoidal gland tilted 10°,
a transition zone (label 2) inside a peripheral zone (label 1), no urethra label, 0.625 × 0.625 ×
3.6 mm voxels over a 200 × 200 × 90 mm field of view (the size of a prostate MRI's label map),
written as NIfTI. One ``softphantom design --anatomy MAP --gland-labels 1,2`` per map and
template (the CLI's default design, and the linear template ``bip_default.toml``), run as a user
runs it, in a subprocess: its wall time (the import, the meshing and the design's observability
check, i.e. its solves at rest and, for 4-node tets, over the load envelope), then a
``simulate`` of a 1 N push on-centre of the design it wrote (the design solves under load). The
goal (the further-organs issue): <= 2 min from the map to a solvable design, no hand edits.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _results import ROOT, write_table

SPACING_MM = (0.625, 0.625, 3.6)
FOV_MM = (200.0, 200.0, 90.0)
TEMPLATES = {"default": [], "linear": ["--config", str(ROOT / "softphantom" / "data" / "bip_default.toml")]}


def _run(argv: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    """(wall s, CPU s of the child tree, the process) of ``softphantom ARGV``."""
    before = os.times()
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "softphantom", *argv], capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = os.times()
    return wall, (after.children_user - before.children_user) + (after.children_system - before.children_system), r


def main() -> None:
    import nibabel as nib

    sys.path.insert(0, str(ROOT / "tests"))
    from label_maps import zonal_label_map  # the tests' synthetic zonal map

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volumes-mL", default="30,47,60")
    ap.add_argument("--template", choices=("both", *TEMPLATES), default="both")
    args = ap.parse_args()
    volumes = [float(v) for v in args.volumes_mL.split(",")]
    templates = list(TEMPLATES) if args.template == "both" else [args.template]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for vol in volumes:
            data, affine, _, _ = zonal_label_map(vol, tilt_deg=10.0, spacing_mm=SPACING_MM, fov_mm=FOV_MM)
            path = tmp / f"zones_{vol:g}mL.nii.gz"
            nib.save(nib.Nifti1Image(data, affine), str(path))
            for name in templates:
                out = tmp / f"{name}_{vol:g}"
                wall, cpu, r = _run(["design", "--anatomy", str(path), "--gland-labels", "1,2", "--no-png",
                                     "--out", str(out), *TEMPLATES[name]])
                if r.returncode != 0:
                    print(f"{vol:g} mL, {name}: design exit {r.returncode}: {r.stderr.strip()}", flush=True)
                    rows.append([f"{vol:g}", name, "refused", "", "", "", "", "", r.stderr.strip()[:80]])
                    continue
                npz = np.load(out / "model.npz", allow_pickle=False)
                nodes, order = len(npz["nodes"]), 2 if "tets10" in npz.files else 1
                swall, scpu, s = _run(["simulate", "--model", str(out), "--force-N", "0,1,0", "--out",
                                       str(tmp / f"sim_{name}_{vol:g}")])
                solved = "yes" if s.returncode == 0 else f"no (exit {s.returncode})"
                total = wall + swall
                print(f"{vol:g} mL, {name} (P{order}, {nodes} nodes): design {wall:.1f} s wall / {cpu:.1f} CPU-s, "
                      f"simulate 1 N {swall:.1f} s ({solved}); {total:.1f} s in all", flush=True)
                rows.append([f"{vol:g}", name, f"P{order}", f"{nodes:,}".replace(",", " "), f"{wall:.1f}",
                             f"{cpu:.1f}", f"{swall:.1f}", f"{total:.1f}", solved])
    print(json.dumps(rows))
    write_table("anatomy", ["gland mL", "template", "elements", "nodes", "design s", "design CPU-s",
                            "simulate 1 N s", "total s", "solved"], rows, right=(0, 3, 4, 5, 6, 7),
                caption=f"Zonal label maps (labels 1, 2; no urethra), {' × '.join(f'{s:g}' for s in SPACING_MM)} mm "
                        f"voxels, {' × '.join(f'{s:g}' for s in FOV_MM)} mm field of view, tilted 10°; "
                        f"`design --anatomy MAP --gland-labels 1,2` then `simulate --force-N 0,1,0`, each a "
                        f"subprocess. Goal: <= 120 s to a solvable design.")


if __name__ == "__main__":
    main()
