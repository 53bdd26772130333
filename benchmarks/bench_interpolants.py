"""The atlas's interpolants against converged solves at held-out loads, on the coarse (12 mm) model.

    .venv/bin/python benchmarks/bench_interpolants.py            # 30 held-out loads each, offline's own sizes
    .venv/bin/python benchmarks/bench_interpolants.py --quick    # the checks `make bench` starts with (~1 min)

1. **Hermite axis.** An atlas with a Hermite f_y axis (3 points, 6 terms) and its Lagrange twin (the
   same grid solves fitted by values alone) at held-out f_y off the grid, the other axes on grid
   points (where every fit is exact): volumes, tracked points and the field. Then the same along a
   displacement-controlled f_x axis over ±1.5 N (the arm pair's step inside), through the atlas's
   own ``coords(force)``.
2. **Reduced-order offline stage.** A small atlas built with ``offline="rom"`` against the one
   built by full solves (force and displacement axes): at off-grid loads within twice the error its
   own checks measured and within 1 % of the volumes' range.

Each comparison has a bound (the figures measured on this model, with margin); a missed bound is
printed and the exit code is 1. ``--quick`` runs them at the sizes they were measured at: 6
held-out loads, 20 ROM comparison loads, the offline stage's small settings (4 Latin-hypercube
snapshots in 2 chains, no step lines, 4 checks). Exactness at grid points, the derivative
identities and the 2n − 1 degree on polynomials are the test suite's (tests/test_atlas_hermite.py,
tests/test_rom.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from softphantom.estimation import AtlasConfig, EstimatorConfig, ForwardModel, build_atlas  # noqa: E402
from softphantom.estimation.atlas.basis import axis_t, to_chebyshev  # noqa: E402
from softphantom.estimation.atlas.map import Atlas  # noqa: E402

CFG = EstimatorConfig(contact="on-centre")
# f_y over a range where the map bends (three Lagrange points miss it), the other axes short
BASE = AtlasConfig(force_min_N=(-0.3, -0.3, -0.3), force_max_N=(0.3, 3.0, 0.3), p_min_kPa=0.0, p_max_kPa=2.0,
                   n_force=(3, 3, 3), n_pressure=2)


def small_config(x_control: str = "force") -> AtlasConfig:
    """The ROM comparison's envelope and grid (tests/shared_models.py's ``atlas_config``): 3 × 4 × 3 × 2
    points, f_x (or the patch displacement) spanning ±0.5 N."""
    return AtlasConfig(force_min_N=(-0.5, -0.3, -0.5), force_max_N=(0.5, 1.2, 0.5), p_min_kPa=-1.0, p_max_kPa=4.0,
                       n_force=(3, 4, 3), n_pressure=2, x_control=x_control)


def build(model, cfg, **kw):
    return build_atlas(model, CFG, cfg, n_workers=1, processes=False, **kw)


def lagrange_twin(at: Atlas) -> Atlas:
    """The Lagrange atlas of the grid solves that made the Hermite atlas ``at``, without solving
    them again: ``at``'s values at its grid points (where the Hermite fit is exact: its solves'
    volumes, points, f_x and field coefficients) fitted as build_atlas fits a grid without
    hermite_axis (on a displacement axis each line through its own points); the POD modes are
    ``at``'s (a build of its own would take them from the values alone)."""
    cfg = dataclasses.replace(at.config, hermite_axis=None)
    assert cfg.cluster_N == at.config.cluster_N  # the grid and its stretch are the Lagrange atlas's
    ax, shape = cfg.axes(), cfg.shape
    grid = np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1)
    grid[..., 0] = at.q_nodes
    lams = grid.reshape(-1, 4)
    tq = np.vectorize(axis_t)(at.q_nodes, ax[0][0], ax[0][-1], cfg.stretch[0])[0]

    def fit(rows):
        return to_chebyshev(np.array(rows).reshape(*shape, -1), shape, tq)

    disp = cfg.x_control == "displacement"
    return Atlas(key="", config=cfg, cV=fit([at.volumes(lam)[0] for lam in lams]),
                 cP=fit([at.points(lam).ravel() for lam in lams]).reshape(*shape, -1, 3),
                 cF=fit([at.modes.T @ (at.nodes(lam).ravel() - at.x_rest) for lam in lams]),
                 cFx=fit([at.forces(lam)[:1] for lam in lams]) if disp else None, q_nodes=at.q_nodes,
                 modes=at.modes, x_rest=at.x_rest, build_s=0.0, solves=at.solves, field_rms_m=at.field_rms_m,
                 solved=at.solved)


class Checks:
    """Named bounds: each printed with its figures; ``failed`` lists the missed ones."""

    def __init__(self):
        self.failed: list[str] = []

    def __call__(self, name: str, ok: bool, figures: str) -> None:
        print(f"  {'ok    ' if ok else 'MISSED'} {name}: {figures}", flush=True)
        if not ok:
            self.failed.append(name)


def hermite_force_axis(model, fwd, n_held: int, check: Checks) -> None:
    """Held-out f_y off the grid, the other axes on grid points: the f_y interpolation's error."""
    rng = np.random.default_rng(11)
    ax = BASE.axes()
    h3_atlas = build(model, dataclasses.replace(BASE, hermite_axis=1))
    held = [fwd.solve(np.array([ax[0][rng.integers(3)], f_y, ax[2][rng.integers(3)], ax[3][rng.integers(2)]]))
            for f_y in rng.uniform(-0.2, 2.9, n_held)]

    def errors(at):
        return np.array([max(np.abs(at.volumes(h.lam)[0] - h.V).max() for h in held),
                         max(np.abs(at.points(h.lam) - h.sub_x).max() for h in held),
                         max(np.abs(at.nodes(h.lam) - h.x.reshape(-1, 3)).max() for h in held)])

    h3, l3 = errors(h3_atlas), errors(lagrange_twin(h3_atlas))
    # measured (H3 / L3; a 5-point Lagrange build, 90 solves, gave L5): volumes 0.0009 / 0.067 mm³
    # (L5 0.0007), points 0.0007 / 0.054 mm (0.0005); the field 0.025 / 0.058 mm (0.023), where the
    # POD truncation (FIELD_RTOL) bounds all three
    fig = (f"H3 / L3 volumes {h3[0] * 1e9:.4f} / {l3[0] * 1e9:.4f} mm³, points {h3[1] * 1e3:.4f} / "
           f"{l3[1] * 1e3:.4f} mm, field {h3[2] * 1e3:.4f} / {l3[2] * 1e3:.4f} mm")
    check(f"Hermite f_y axis: volumes and points within 5 % of its Lagrange twin's error ({n_held} loads)",
          bool(np.all(h3[:2] <= 0.05 * l3[:2])), fig)
    check("Hermite f_y axis: the field within half its Lagrange twin's error", bool(h3[2] <= 0.5 * l3[2]), fig)


def hermite_displacement_axis(model, fwd, n_held: int, check: Checks) -> None:
    """Along the patch displacement q over ±1.5 N of f_x, held-out f_x on grid points of the other
    axes, through the atlas's own coords(force)."""
    base = dataclasses.replace(BASE, force_min_N=(-1.5, -0.3, -0.3), force_max_N=(1.5, 1.5, 0.3),
                               x_control="displacement")
    rng = np.random.default_rng(7)
    ax = base.axes()
    held = [fwd.solve(np.array([f_x, ax[1][rng.integers(3)], ax[2][rng.integers(3)], ax[3][rng.integers(2)]]))
            for f_x in rng.uniform(-1.4, 1.4, n_held)]

    def errors(at):
        lams = [at.coords(h.lam[:3], h.lam[3]) for h in held]
        back = max(np.abs(at.forces(lam) - h.lam[:3]).max() for lam, h in zip(lams, held))
        check("displacement axis: coords(force) inverts forces() to 1e-9 N", bool(back <= 1e-9), f"{back:.1e} N")
        return np.array([max(np.abs(at.volumes(lam)[0] - h.V).max() for lam, h in zip(lams, held)),
                         max(np.abs(at.points(lam) - h.sub_x).max() for lam, h in zip(lams, held))])

    at = build(model, dataclasses.replace(base, hermite_axis=0))
    h3, l3 = errors(at), errors(lagrange_twin(at))
    # measured: volumes 0.011 / 0.20 mm³, points 0.007 / 0.31 mm (H3 / L3); a 5-point Lagrange
    # build (90 more solves) gave 0.018 mm³ and 0.026 mm, also above H3's
    check(f"Hermite displacement axis: within 10 % of its Lagrange twin's error ({n_held} loads)",
          bool(np.all(h3 <= 0.1 * l3)), f"H3 / L3 volumes {h3[0] * 1e9:.4f} / {l3[0] * 1e9:.4f} mm³, points "
                                          f"{h3[1] * 1e3:.4f} / {l3[1] * 1e3:.4f} mm")


def rom_against_full(model, x_control: str, n_loads: int, quick: bool, check: Checks) -> None:
    """The reduced-order build of :func:`small_config` against the full one at off-grid loads."""
    from softphantom.estimation.atlas.store import describe, load_atlas, save_atlas

    base = small_config(x_control)
    full = build(model, base)
    red = build(model, dataclasses.replace(base, offline="rom"))
    off = red.provenance["offline"]
    if quick:
        check(f"ROM ({x_control} axis): the quick settings' 4 checks and 20 snapshots",
              off["checks"] == 4 and off["snapshots"] == 20 and off["check_max_dV_mm3"] >= 0,
              f"{off['checks']} checks, {off['snapshots']} snapshots")
    check(f"ROM ({x_control} axis): another key, every grid point solved", red.key != full.key and red.solved.all(),
          f"{red.solved.mean():.0%} solved")
    with tempfile.TemporaryDirectory() as tmp:
        back = load_atlas(save_atlas(red, os.path.join(tmp, "rom.npz")), red.key)
        said = dict(describe(back))["offline"]
    check(f"ROM ({x_control} axis): `atlas info` states the checks' error",
          f"volumes within {off['check_max_dV_mm3']:.3f} mm³" in said, said)
    rng = np.random.default_rng(5)
    lo, hi = base.lower, base.upper
    worst = 0.0
    for _ in range(n_loads):
        lam = lo + (hi - lo) * rng.uniform(0.05, 0.95, 4)
        if not red.solved_at(red.coords(lam[:3], lam[3])):
            continue
        worst = max(worst, float(np.max(np.abs(red.volumes(red.coords(lam[:3], lam[3]))[0]
                                                - full.volumes(full.coords(lam[:3], lam[3]))[0]))))
    vol_range = float(np.ptp([full.volumes(lo + (hi - lo) * u)[0] for u in rng.uniform(size=(10, 4))]))
    # measured on this model, either axis: 0.0099 mm³ off-grid, checks 0.011 mm³, range 5.8 mm³
    check(f"ROM ({x_control} axis): off-grid within twice its checks' error and 1 % of the range ({n_loads} loads)",
          worst <= 2 * off["check_max_dV_mm3"] * 1e-9 and worst <= 0.01 * vol_range,
          f"off-grid {worst * 1e9:.4f} mm³, checks {off['check_max_dV_mm3']:.4f} mm³ ({off['checks']} solves, "
          f"{off['snapshots']} snapshots), range {vol_range * 1e9:.2f} mm³")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the sizes the bounds were measured at (~1 min)")
    ap.add_argument("--held-out", type=int, default=None, help="held-out loads per Hermite comparison (quick 6, else 30)")
    ap.add_argument("--rom-loads", type=int, default=None, help="off-grid loads per ROM comparison (quick 20, else 100)")
    a = ap.parse_args(argv)
    n_held = a.held_out or (6 if a.quick else 30)
    n_rom = a.rom_loads or (20 if a.quick else 100)

    from softphantom.design import BIPDesign, build_model
    from softphantom.estimation import offline

    t0 = time.perf_counter()
    model = build_model(BIPDesign(), 12.0, isolate=False)
    print(f"coarse model: {len(model.nodes)} nodes ({time.perf_counter() - t0:.0f} s)", flush=True)
    fwd = ForwardModel(model, CFG)
    check = Checks()
    hermite_force_axis(model, fwd, n_held, check)
    hermite_displacement_axis(model, fwd, n_held, check)
    if a.quick:
        offline.N_LHS, offline.STEP_FX_N, offline.N_CHAINS, offline.N_CHECK = 4, (), 2, 4
    with tempfile.TemporaryDirectory() as tmp:
        offline.SNAPSHOT_CACHE = os.path.join(tmp, "snapshots")  # the two axes' builds share their snapshots
        for x_control in ("force", "displacement"):
            rom_against_full(model, x_control, n_rom, a.quick, check)
    print(f"{'all bounds met' if not check.failed else f'{len(check.failed)} missed'} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 1 if check.failed else 0


if __name__ == "__main__":
    sys.exit(main())
