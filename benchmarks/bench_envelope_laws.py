"""Each law over the atlas's envelope (docs/model.md): converged solves from rest
at the default atlas envelope's corners, on-centre and off-centre contact, with and without the
urethra at 40 kPa, on the default design at its mesh (6 mm P1), per law; optionally the
neo-Hookean P2 12 mm model at a few corners as the reference of another element.

    .venv/bin/python benchmarks/bench_envelope_laws.py [--laws corotational neo-hookean] [--p2-reference]

Prints the arm-cavity volume changes (mm³), iterations and CPU seconds per solve; a failed solve
prints the solver's one-line reason.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import time

import numpy as np

from softphantom.design import BIPDesign, build_model
from softphantom.design.params import MaterialSpec
from softphantom.errors import SolverError
from softphantom.estimation import AtlasConfig, EstimatorConfig
from softphantom.estimation.forward import ForwardModel


def corners() -> list[tuple[float, float, float, float]]:
    cfg = AtlasConfig()
    lo, hi = cfg.force_min_N, cfg.force_max_N
    pts = [(fx, hi[1], fz, 0.0) for fx, fz in itertools.product((lo[0], hi[0]), (lo[2], hi[2]))]
    p = cfg.p_max_kPa * 1e3
    return pts + [(0.0, lo[1], 0.0, 0.0), (0.0, 0.0, 0.0, p), (hi[0], hi[1], hi[2], p), (lo[0], hi[1], lo[2], p)]


def with_law(design: BIPDesign, law: str, order: int = 1) -> BIPDesign:
    mats = tuple(MaterialSpec(m.name, law, m.values) for m in design.materials)
    return dataclasses.replace(design, materials=mats, mesh=dataclasses.replace(design.mesh, element_order=order))


def solve_all(model, label: str, points, contacts) -> None:
    for contact in contacts:
        fwd = ForwardModel(model, EstimatorConfig(contact=contact))
        for p in points:
            t = time.process_time()
            try:
                lin = fwd.solve(p)
                msg = f"arm dV mm3 {np.round(lin.V * 1e9, 2)}, {lin.iterations} it"
            except SolverError as exc:
                msg = f"FAILED: {str(exc)[:160]}"
            print(f"{label} {contact:10s} F_N {p[:3]} p_kPa {p[3] / 1e3:g}: {msg} "
                  f"({time.process_time() - t:.1f} CPU-s)", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--laws", nargs="+", default=["corotational", "neo-hookean"])
    ap.add_argument("--p2-reference", action="store_true", help="also NH P2 12 mm at the on-centre push corners")
    a = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.1f}")
    d = BIPDesign()
    for law in a.laws:
        solve_all(build_model(with_law(d, law)), f"{law:13s} P1 6 mm ", corners(), ("on-centre", "off-centre"))
    if a.p2_reference:
        m = build_model(with_law(d, "neo-hookean", 2), 12.0)
        solve_all(m, "neo-hookean   P2 12 mm", [c for c in corners()[:4]], ("on-centre",))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
