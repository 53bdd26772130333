"""An atlas checked against what it was not built from: converged full solves at seeded held-out
loads over its whole envelope (corners and the fold included), compared with the atlas's map and
with its inverse, the estimate a user gets (``softphantom atlas check``; the shipped atlas's CI
check and ``benchmarks/bench_shipped_atlas.py``).

Each load is solved from rest by the forward model's own continuation
(:meth:`~softphantom.estimation.forward.ForwardModel.solve`: force control, not the build's
mixed control along the first axis), then:

- the map: the atlas's volumes and tracked points at the load's coordinates against the solve's;
- the inverse: the estimator given the solved volumes and pressure, started 0.3 N away, against the
  load (force, N), the pose of the markers (mm, deg) and each target (mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softphantom.estimation.atlas.estimator import GOALS  # noqa: F401  (kept with the estimator: its rest check)
from softphantom.estimation.config import EstimatorConfig

COLUMNS = ("dV_mm3", "points_mm", "force_N", "pos_mm", "ang_deg")
START_N = 0.3  # the inverse starts this far (N) from the load: a stream's last estimate is much closer


@dataclass(frozen=True)
class HeldOut:
    """Errors at held-out loads: ``loads`` (n, 4) N, N, N, Pa; ``errors`` (n, len(COLUMNS)) in the
    units of :data:`COLUMNS`; ``targets_mm`` (n, t) each target's error after the inverse, named
    ``target_names``; ``skipped`` loads outside the atlas's solved cells; ``failed`` loads whose full
    solve did not converge (one line each)."""

    loads: np.ndarray
    errors: np.ndarray
    targets_mm: np.ndarray
    target_names: tuple[str, ...]
    skipped: int = 0
    failed: tuple[str, ...] = field(default=())

    def worst(self) -> dict[str, float]:
        """Max error per column and per target (``<target>_mm``)."""
        out = {c: float(self.errors[:, i].max(initial=0.0)) for i, c in enumerate(COLUMNS)}
        out.update({f"{t}_mm": float(self.targets_mm[:, j].max(initial=0.0)) for j, t in enumerate(self.target_names)})
        return out

    def p90(self) -> dict[str, float]:
        """90th percentile per column (0 with no loads)."""
        if not len(self.errors):
            return {c: 0.0 for c in COLUMNS}
        return {c: float(v) for c, v in zip(COLUMNS, np.percentile(self.errors, 90, axis=0))}

    def missed(self, goals: dict[str, float] = GOALS) -> list[str]:
        """The goals the worst errors miss, one phrase each (empty: all met)."""
        w = self.worst()
        return [f"{k} {w[k]:.4g} > {v:g}" for k, v in goals.items() if k in w and w[k] > v]


def held_out_loads(lower, upper, n: int, seed: int = 0, corner_share: float = 0.25) -> np.ndarray:
    """(n, 3 + M) seeded loads over the box ``lower``…``upper`` (N, N, N, Pa…), uniform, except a share
    ``corner_share`` drawn within 5 % of a random corner on every axis (where a polynomial's error
    is largest).

    >>> L = held_out_loads([-1, -1, -1, 0], [1, 3, 1, 4e4], 8, seed=1)
    >>> L.shape, bool(np.all((L >= [-1, -1, -1, 0]) & (L <= [1, 3, 1, 4e4])))
    ((8, 4), True)
    >>> np.array_equal(L, held_out_loads([-1, -1, -1, 0], [1, 3, 1, 4e4], 8, seed=1))
    True
    """
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 1.0, (n, len(lo)))
    corner = rng.uniform(size=n) < corner_share
    ends = rng.integers(0, 2, (n, len(lo)))
    near = np.where(ends == 1, 1.0 - 0.05 * u, 0.05 * u)
    u = np.where(corner[:, None], near, u)
    return lo + (hi - lo) * u


def _solve_near(fwd, at, c, lam):
    """The equilibrium at ``lam`` solved from the atlas's own field there (``at.nodes(c)``): a start
    within the atlas's error, so a few chord iterations instead of a continuation from rest (a
    draft's check); from rest where that fails."""
    from softphantom.errors import SolverError
    from softphantom.estimation.atlas.build import _linearized_at
    from softphantom.fem import ElementInversionError

    try:
        start = _linearized_at(fwd, np.asarray(at.nodes(c), float).ravel(), lam)
        return fwd.solve(lam, start)
    except (SolverError, ElementInversionError, np.linalg.LinAlgError):
        fwd.eq.factorize(fwd.fem.x_rest, np.zeros(len(lam) - 3))
        return fwd.solve(lam)


def _rows(model, config: EstimatorConfig, atlas, loads: np.ndarray, seed: int, from_atlas: bool = False):
    """Errors at ``loads`` (a Dask task: its own forward model and estimator); ``from_atlas``: each
    full solve started from the atlas's field (:func:`_solve_near`)."""
    from softphantom.errors import SolverError
    from softphantom.estimation.atlas.estimator import AtlasEstimator
    from softphantom.pose import pose_of_markers

    est = AtlasEstimator(model, config, atlas)
    fwd, at = est.forward, est.atlas
    nm = fwd.n_markers
    rng = np.random.default_rng(seed)
    rows, targets, used, skipped, failed = [], [], [], 0, []
    for lam in np.asarray(loads, float):
        p = lam[3] if len(lam) == 4 else lam[3:]  # a stack's: every pressure
        c = at.coords(lam[:3], p)
        if not at.solved_at(c):
            skipped += 1
            continue
        try:
            lin = _solve_near(fwd, at, c, lam) if from_atlas else fwd.solve(lam)
        except SolverError as exc:
            failed.append(f"load {np.round(lam[:3], 3).tolist()} N, {lam[3] * 1e-3:.2f} kPa: {exc}")
            continue
        V, _ = at.volumes(c)
        start = at.coords(lam[:3] + rng.normal(0.0, START_N / np.sqrt(3.0), 3), p)
        lam_e = est.invert(lin.V, p, start=start)[0]
        truth = pose_of_markers(est.rest_markers, lin.sub_x[:nm]).to_mm_deg()
        d = pose_of_markers(est.rest_markers, at.points(lam_e)[:nm]).to_mm_deg() - truth
        rows.append([np.abs(V - lin.V).max() * 1e9, np.abs(at.points(c) - lin.sub_x).max() * 1e3,
                     np.linalg.norm(at.forces(lam_e) - lam[:3]), np.abs(d[:3]).max(), np.abs(d[3:]).max()])
        targets.append(np.linalg.norm(at.points(lam_e)[nm:] - lin.sub_x[nm:], axis=1) * 1e3)
        used.append(lam)
    t = len(fwd.target_names)
    return (np.reshape(used, (-1, loads.shape[1])), np.reshape(rows, (-1, len(COLUMNS))), np.reshape(targets, (-1, t)),
            skipped, failed, tuple(fwd.target_names))


def check_held_out(model, config: EstimatorConfig, atlas, loads, *, seed: int = 0, client=None,
                   chunks: int | None = None, from_atlas: bool = False) -> HeldOut:
    """:class:`HeldOut` errors of ``atlas`` (an :class:`~softphantom.estimation.atlas.map.Atlas` or
    its pieces, or an :class:`~softphantom.estimation.atlas.map.AtlasStack`) for ``model`` at ``loads``
    (n, 3 + M) N, N, N, Pa…. On ``client`` (Dask) the loads are split into ``chunks`` tasks
    (default: 2 per worker), each building its own estimator; else here. ``from_atlas``: each full
    solve starts from the atlas's own field at the load, not from rest (a draft's quick check: the
    same equilibrium where it is unique, at the cost of a grid point instead of a continuation)."""
    loads = np.atleast_2d(np.asarray(loads, float))
    if client is None:
        parts = [_rows(model, config, atlas, loads, seed, from_atlas)]
    else:
        from softphantom.errors import UserError
        from softphantom.parallel import map_tasks

        k = chunks or max(1, 2 * len(client.scheduler_info().get("workers", {})))
        groups = [g for g in np.array_split(loads, min(k, len(loads))) if len(g)]
        m, a = client.scatter([model, atlas], broadcast=True)
        res = map_tasks(client, _rows, [(m, config, a, g, seed + i, from_atlas) for i, g in enumerate(groups)],
                        label="held-out loads")
        bad = [r.error for r in res if not r.ok]
        if bad:
            raise UserError(f"held-out check: {len(bad)} of {len(res)} tasks failed; first: {bad[0]}")
        parts = [r.value for r in res]
    return HeldOut(loads=np.vstack([p[0] for p in parts]), errors=np.vstack([p[1] for p in parts]),
                   targets_mm=np.vstack([p[2] for p in parts]), target_names=parts[0][5],
                   skipped=sum(p[3] for p in parts), failed=tuple(f for p in parts for f in p[4]))


DRAFT_LOADS = 12  # held-out loads a draft atlas is checked at (atlas build --draft)


def draft_error_text(held: dict) -> str:
    """One line of a draft atlas's measured error (``provenance["held_out"]``, :func:`check_draft`).

    >>> draft_error_text({"loads": 12, "worst": {"force_N": 0.031, "pos_mm": 0.042, "ang_deg": 0.21,
    ...                   "near_urethra_mm": 0.03}})
    'held-out error at 12 loads: 0.031 N, 0.042 mm, 0.21°, near_urethra 0.03 mm (goals of a full atlas: 0.05 N, 0.05 mm, 0.1°, 0.02 mm)'
    """
    w = held.get("worst", {})
    near = f", near_urethra {w['near_urethra_mm']:.2g} mm" if "near_urethra_mm" in w else ""
    return (f"held-out error at {held.get('loads', 0)} loads: {w.get('force_N', float('nan')):.2g} N, "
            f"{w.get('pos_mm', float('nan')):.2g} mm, {w.get('ang_deg', float('nan')):.2g}°{near} (goals of a full "
            f"atlas: {GOALS['force_N']:g} N, {GOALS['pos_mm']:g} mm, {GOALS['ang_deg']:g}°, "
            f"{GOALS['near_urethra_mm']:g} mm)")


def check_draft(model, config: EstimatorConfig, atlas, *, n: int = DRAFT_LOADS, seed: int = 0, client=None) -> dict:
    """A draft atlas's held-out error: :func:`check_held_out` at ``n`` seeded loads over its
    envelope, each full solve started from the atlas's field (``from_atlas``); returns what its
    file keeps (``provenance["held_out"]``: loads, worst and 90th percentile per column and target)."""
    c = atlas.config
    further = (np.array(c.further_min_kPa) * 1e3, np.array(c.further_max_kPa) * 1e3)
    L = held_out_loads(np.r_[c.lower, further[0]], np.r_[c.upper, further[1]], n, seed)
    res = check_held_out(model, config, atlas, L, seed=seed, client=client, from_atlas=True)
    return {"loads": int(len(res.loads)), "skipped": int(res.skipped), "failed": len(res.failed), "seed": int(seed),
            "worst": {k: round(v, 5) for k, v in res.worst().items()},
            "p90": {k: round(v, 5) for k, v in res.p90().items()}}


def draft_held_out(atlas) -> dict | None:
    """A draft atlas's held-out error as its files keep it (:func:`measure_draft`), else None (also
    for an atlas's config, not built yet)."""
    from softphantom.estimation.atlas.map import pieces_of

    return (getattr(pieces_of(atlas)[0], "provenance", None) or {}).get("held_out")


def measure_draft(model, config: EstimatorConfig, found, model_dir, scheduler: str | None = None,
                  n_workers: int | None = None) -> dict:
    """A draft atlas's held-out error (:func:`check_draft`) of ``found`` (a catalogue
    :class:`~softphantom.estimation.atlas.catalogue.Found`): measured once on Dask and kept in each
    of its files in ``model_dir`` (``provenance["held_out"]``), read from there after; returned."""
    from dataclasses import replace

    from softphantom.estimation.atlas.store import atlas_path, save_atlas
    from softphantom.parallel import dask_client

    from softphantom.estimation.atlas.map import pieces_of

    at = found.atlas
    pieces = pieces_of(at)
    held = draft_held_out(at)
    if held is None:
        with dask_client(scheduler, n_workers) as client:
            held = check_draft(model, config, at, client=client)
        for piece in pieces:
            save_atlas(replace(piece, provenance={**(piece.provenance or {}), "held_out": held}),
                       atlas_path(model_dir, piece.key))
    return held


def find_or_build_measured(model, config: EstimatorConfig, acfg=None, **kw):
    """:func:`~softphantom.estimation.atlas.catalogue.find_or_build` with ``draft``: a draft it
    builds (no full atlas anywhere) gets its held-out error measured (:func:`measure_draft`) before
    it is returned, as ``estimate --draft`` and ``demo --draft`` promise."""
    from softphantom.estimation.atlas.catalogue import find_or_build

    found = find_or_build(model, config, acfg, draft=True, **kw)
    at, model_dir = found.atlas, kw.get("model_dir")
    if at.draft and model_dir is not None and draft_held_out(at) is None:
        measure_draft(model, config, found, model_dir, kw.get("scheduler"), kw.get("n_workers"))
        found = find_or_build(model, config, acfg, draft=True, **kw)  # as saved, its error with it
    return found
