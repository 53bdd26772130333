"""The demo pipeline (``softphantom demo``, what ``make demo`` runs): the scenarios on the virtual
phantom → estimate → evaluate → one report per scenario, an index page and a summary.

The estimator is the model's own atlas, per contact point the scenarios use: for the default
design the one shipped with the package (loaded in seconds), for another model the one built into
its directory (``softphantom atlas build``); a missing one that would take longer than
:data:`~softphantom.estimation.atlas.build.MAX_BUILD_ON_THE_FLY_S` to build is refused before any
solve, in one line naming the command. With ``grid`` (``--atlas-grid``), a small atlas over the
scenarios' own loads is built for the demo instead (:func:`scenario_atlas`, :func:`shared_atlases`:
for a model without its atlas, e.g. a coarse test model).

The truths are solved on Dask (:mod:`softphantom.parallel`: a local cluster by default, an
existing scheduler by its address), one at a time in scenario order, while the demo's own atlases,
if any, are built on the same cluster; each scenario is estimated and evaluated in this process as
soon as its truth is ready.
"""

from __future__ import annotations

import html
import json
import logging
import queue
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from softphantom.estimation import AtlasConfig, EstimatorConfig, estimate_stream, load_or_build, open_estimator
from softphantom.progress import Step, forward_progress, report

# The demo's own atlas per scenario (with --atlas-grid): the box of the scenario's peak loads (its
# pushes; the pressure its inflation reached) and zero, each face widened by MARGIN_N + MARGIN_REL ×
# the peak on that side of that axis (the estimator's model differs from the truth's, so its
# forces do too: in the demo the estimates passed the truth's peaks by ≤ 0.62 N along the push,
# ≤ 0.2 N sideways), the pressure by MARGIN_KPA only: it is measured, not estimated (a 20 % margin
# put the inflation atlas's top planes at 51 kPa, beyond what the estimator's model reaches).
# Margins are per axis: one margin for all axes from the largest force would make the sideways
# range 3.1 N for ±0.6 N of load. Pushes vary the force (the pressure stays near 0: 2 points), an
# inflation the pressure.
MARGIN_N = 0.5
MARGIN_REL = 0.2
MARGIN_KPA = 2.0
PUSH_GRID = (5, 5, 5, 2)
INFLATE_GRID = (3, 3, 3, 5)
# the demo's default scenarios: the bundled ones at the contact whose atlas ships (on-centre)
DEMO_SCENARIOS = ("needle-insertion", "push-on-centre", "push-off-centre", "urethra-inflation")
# a design's generated pushes (design_scenarios): their force (N) and tilt off the surface normal (deg)
PUSH_N = 2.5
PUSH_TILT_DEG = 15.0
INFLATE_KPA = 20.0  # and their inflations' gauge pressure
TRUTH_TOPIC = "softphantom-demo-truth"  # the Dask event topic of the truth solves' progress

log = logging.getLogger(__name__)


def contact_of(scenario) -> str:
    """The contact point the estimator assumes for a scenario: its pushes' one point, else on-centre."""
    points = {e.point for e in scenario.events if e.kind == "push"}
    return points.pop() if len(points) == 1 else "on-centre"


def demo_contacts(points) -> tuple[str, ...]:
    """Of a design's contact ``points`` (its ``p_ext_mm()``), those its demo pushes at: its named
    ones, else ``on-centre`` (``off-centre`` is the BIP paper's second point, pushed only when asked for)."""
    named = tuple(n for n in points if n not in ("on-centre", "off-centre"))
    return named or ("on-centre",)


def design_scenarios(design, push_N: float = PUSH_N, inflate_kPa: float = INFLATE_KPA) -> list:
    """The demo of a design without scenario files: at each of :func:`demo_contacts`, three pushes
    of ``push_N`` (N) into the body, along the inward surface normal and tilted ``PUSH_TILT_DEG``
    either way (as the paper's manual pushes, Fig. 9); then, for each actuated internal cavity, three
    inflations to ``inflate_kPa`` (a breathing-like cycle for an actuator, a lesion's balloon swelling;
    a measured cavity is read during the pushes, never inflated).

    >>> from softphantom.design import default_design
    >>> [sc.name for sc in design_scenarios(default_design())]
    ['push-on-centre', 'inflate-urethra']
    >>> [round(float(np.linalg.norm(e.force_N)), 3) for e in design_scenarios(default_design())[0].events]
    [2.5, 2.5, 2.5]
    >>> design_scenarios(default_design())[0].events[0].force_N  # the front (-y) surface's inward normal
    (0.0, 2.5, 0.0)
    >>> sc = design_scenarios(default_design())[1]
    >>> sc.name, [(e.kind, e.cavity, e.p_kPa) for e in sc.events][0]
    ('inflate-urethra', ('inflate', 'urethra', 20.0))
    """
    from softphantom.virtual.scenario import scenario_from_dict

    if not 0.0 < push_N <= 20.0:
        raise ValueError(f"push_N must be in (0, 20] N, got {push_N:g}")
    out = []
    points = design.p_ext_mm()  # on a surface body, ray casts and a bisection: once
    for c in demo_contacts(points):
        n = -np.asarray(design.bulb.normal(points[c]), float)
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        t = np.radians(PUSH_TILT_DEG)
        dirs = (n, np.cos(t) * n + np.sin(t) * (a + b) / np.sqrt(2), np.cos(t) * n - np.sin(t) * (a - b) / np.sqrt(2))
        pushes = [{"point": c, "start_s": 2.0 + 3.5 * i, "rise_s": 1.1, "hold_s": 0.7, "fall_s": 1.1,
                   "force_N": [round(float(v), 6) + 0.0 for v in push_N * d]} for i, d in enumerate(dirs)]
        out.append(scenario_from_dict({
            "name": f"push-{c}", "duration_s": 13.0, "rest_s": 1.5, "push": pushes,
            "description": f"{design.name}: three pushes of {push_N:g} N at {c}, along the inward normal and "
                           f"tilted {PUSH_TILT_DEG:g}° either way"}, source=f"{design.name} (generated)"))
    if not 0.0 < inflate_kPa <= 250.0:
        raise ValueError(f"inflate_kPa must be in (0, 250] kPa, got {inflate_kPa:g}")
    for c in design.pressure_names:  # a measured cavity is read, never inflated
        cycles = [{"cavity": c, "p_kPa": inflate_kPa, "start_s": 2.0 + 3.5 * i, "rise_s": 1.1, "hold_s": 0.7,
                   "fall_s": 1.1} for i in range(3)]
        out.append(scenario_from_dict({
            "name": f"inflate-{c}", "duration_s": 13.0, "rest_s": 1.5, "inflate": cycles,
            "description": f"{design.name}: three inflations of {c} to {inflate_kPa:g} kPa"},
            source=f"{design.name} (generated)"))
    return out


def push_only(sc) -> str | None:
    """The contact point of a scenario that only pushes, at one point; else None."""
    points = {e.point for e in sc.events if e.kind == "push"}
    return points.pop() if len(points) == 1 and all(e.kind == "push" for e in sc.events) else None


def atlas_box(forces, p_kPa: float, grid=None, further_kPa=()) -> AtlasConfig:
    """The atlas over the box of ``forces`` (N, each (3,)) and zero, widened by the margins above;
    the pressure from −MARGIN_KPA to ``p_kPa`` + MARGIN_KPA; ``grid`` the points per axis (default:
    ``PUSH_GRID`` for a push, every pressure 0, else ``INFLATE_GRID``). ``further_kPa``: the peaks
    of the further actuated cavities (a design of M ≥ 2): a stack whose levels span each the same
    way, ``grid``'s pressure points for a cavity that inflates; one that stays at rest (its measured
    pressure is noise about 0) gets one level at 0, and p_1 at rest its tangent line: so each
    scenario's atlas costs what it would for one cavity.

    >>> c = atlas_box([(0.0, 0.0, 0.0)], 0.0, further_kPa=(20.0,))
    >>> c.shape, c.linear_pressure, c.further_max_kPa, c.n_further, c.n_solves
    ((3, 3, 3, 2), True, (22.0,), (5,), 135)
    >>> c = atlas_box([(0.0, 0.0, 0.0)], 20.0, further_kPa=(0.0,))
    >>> c.shape, c.further_min_kPa, c.further_max_kPa, c.n_further, c.n_solves
    ((3, 3, 3, 5), (-2.0,), (2.0,), (1,), 135)
    """
    F = np.array([np.zeros(3)] + [np.asarray(f, float) for f in forces])
    lo, hi = F.min(0), F.max(0)
    further = tuple(float(v) for v in further_kPa)
    inflating = p_kPa != 0.0 or any(further)
    n = grid or (INFLATE_GRID if inflating else PUSH_GRID)
    n_p = 2 if further and p_kPa == 0.0 else n[3]
    stack = dict(further_min_kPa=(-MARGIN_KPA,) * len(further), further_max_kPa=tuple(v + MARGIN_KPA for v in further),
                 n_further=tuple(n[3] if v else 1 for v in further)) if further else {}
    # a push's pressure stays near 0 (the middle of its range): the pressure axis is the tangent
    # line there, one plane of solves instead of two (AtlasConfig.linear_pressure)
    return AtlasConfig(force_min_N=tuple(lo - MARGIN_N + MARGIN_REL * lo),
                       force_max_N=tuple(hi + MARGIN_N + MARGIN_REL * hi), p_min_kPa=-MARGIN_KPA,
                       p_max_kPa=p_kPa + MARGIN_KPA, n_force=n[:3], n_pressure=n_p,
                       linear_pressure=p_kPa == 0.0 and n_p == 2,
                       x_control="force", **stack)


def scenario_atlas(truth, grid: tuple[int, int, int, int] | None = None, cavities=()) -> AtlasConfig:
    """The :class:`~softphantom.estimation.atlas.config.AtlasConfig` the demo builds for one
    scenario from its solved ``truth`` (see ``MARGIN_N`` above); ``grid`` overrides the points per
    axis; ``cavities``: the model's actuated ones, whose peaks set a stack's levels (M ≥ 2).

    >>> from types import SimpleNamespace as E
    >>> push = E(events=[E(force=(0.4, 3.0, 0.3), p_Pa=0.0), E(force=(-0.5, 2.8, -0.4), p_Pa=0.0)])
    >>> a = scenario_atlas(push)
    >>> [round(v, 2) for v in a.force_min_N], [round(v, 2) for v in a.force_max_N], a.shape
    ([-1.1, -0.5, -0.98], [0.98, 4.1, 0.86], (5, 5, 5, 2))
    >>> a = scenario_atlas(E(events=[E(force=(0.0, 0.0, 0.0), p_Pa=30e3)]))
    >>> a.force_max_N, a.p_min_kPa, a.p_max_kPa, a.shape
    ((0.5, 0.5, 0.5), -2.0, 32.0, (3, 3, 3, 5))
    """
    groups = getattr(truth, "groups", ())  # two events at once: their loads add
    forces = [e.force for e in (*truth.events, *groups)]

    def peak_kPa(c):  # the largest pressure of cavity c (None: of any) over the events and groups
        ev = [e.p_Pa for e in truth.events if c is None or getattr(e, "cavity", None) == c]
        gr = [max(g.pressures_Pa.values(), default=0.0) if c is None else g.pressures_Pa.get(c, 0.0) for g in groups]
        return max([0.0] + ev + gr) * 1e-3

    if len(cavities) < 2:
        return atlas_box(forces, peak_kPa(None), grid)
    return atlas_box(forces, peak_kPa(cavities[0]), grid, tuple(peak_kPa(c) for c in cavities[1:]))


def shared_atlases(scs, grid: tuple[int, int, int, int] | None = None,
                   n_cavities: int = 1) -> dict[str, AtlasConfig]:
    """One atlas per contact point for the scenarios that only push there (their peak forces are
    the scenario's own, known before any solve): the box of all of them, so the needle insertion
    and the on-centre pushes share one build; ``grid`` the points per axis (default ``PUSH_GRID``);
    for ``n_cavities`` ≥ 2 actuated cavities a stack of one level of each further one, at 0.
    {contact: AtlasConfig}.

    >>> from types import SimpleNamespace as E
    >>> needle = E(events=[E(kind="push", point="on-centre", force_N=(0.15, 2.5, -0.2))])
    >>> pushes = E(events=[E(kind="push", point="on-centre", force_N=(-0.6, 2.6, -0.5))])
    >>> inflate = E(events=[E(kind="inflate", point="on-centre", force_N=(0.0, 0.0, 0.0))])
    >>> a = shared_atlases([needle, pushes, inflate])
    >>> c = a["on-centre"]  # each face: 0.5 N + 0.2 × the peak on that side (f_y: 2.6 + 0.5 + 0.52)
    >>> list(a), [round(v, 2) for v in c.force_min_N], [round(v, 2) for v in c.force_max_N], c.shape
    (['on-centre'], [-1.22, -0.5, -1.1], [0.68, 3.62, 0.5], (5, 5, 5, 2))
    >>> c.linear_pressure, c.cluster_N  # one plane of solves at 0 kPa; affine points
    (True, (0.0, 0.0, 0.0))
    """
    by: dict[str, list] = {}
    for sc in scs:
        if (c := push_only(sc)) is not None:
            by.setdefault(c, []).extend(e.force_N for e in sc.events)
            # two pushes at once: their sum
            by[c].extend(np.add(sc.events[i].force_N, sc.events[j].force_N) for i, j in getattr(sc, "groups", ()))
    return {c: atlas_box(f, 0.0, grid, (0.0,) * (n_cavities - 1)) for c, f in by.items()}


def in_envelope_fraction(path: Path) -> float:
    """Fraction of the estimates inside the atlas's envelope (the CSV's in_envelope column)."""
    from softphantom.evaluation.files import read_table

    col = read_table(path).columns["in_envelope"]
    return float(col.mean()) if len(col) else float("nan")


def run_scenario(sc, model, out: Path, cfg, truth, estimator: str = "atlas", grid=None, atlas=None,
                 scheduler: str | None = None, shown: Path | None = None, clinical: bool = True) -> dict:
    """One scenario end to end from its solved ``truth``, into ``out``/<name>; returns its summary
    row (JSON-able). ``shown``: where ``out`` ends up (the demo writes into a staging directory and
    renames it), for the paths the report names (default ``out``). ``estimator``: atlas (``atlas``, an AtlasConfig, default the scenario's envelope
    (:func:`scenario_atlas`); loaded from or built into out/model/atlas, on ``scheduler`` if
    given) or refresh (sync); ``grid`` the atlas's points per axis (None or (): by kind). Its progress
    is reported (tasks ``<scenario>: estimate``, ``<scenario>: evaluate``)."""
    from softphantom.evaluation import evaluate, read_estimate, read_truth, write_report
    from softphantom.evaluation.report import tube_advance_ms
    from softphantom.tracking import estimate_lag
    from softphantom.virtual import run_summary, simulate, write_run

    d = out / sc.name
    run = simulate(sc, model, cfg, truth=truth)
    paths = write_run(run, d)
    est_path = d / "estimate.csv"
    if est_path.exists():
        est_path.unlink()
    src = run.source()
    n_frames = int(run.board().rate_Hz * sc.duration_s)
    t1 = time.perf_counter()
    task = f"{sc.name}: estimate"
    report(log, task, 0, n_frames)
    ecfg = EstimatorConfig(contact=contact_of(sc), mode="sync")
    if estimator != "atlas":
        atlas = None
    elif atlas is None:
        atlas = scenario_atlas(truth, grid, model.layout.actuated)
    from softphantom.estimation.lag import compensated, lag_compensation
    from softphantom.virtual.run import host_bench

    # the host's tube model, as `estimate` has it from a recording: on by default where the lag matters
    lag, lag_meta, _ = lag_compensation(None, host_bench(model, run.config.board))
    # a progress record at each tenth and at most every 0.2 s between: one a sample cost 25-30 µs and
    # handed the GIL to the progress bar's refresh thread (the kidney's stream: 1.3 kHz against
    # 5.4 kHz on free cores, 560-700 Hz against 720-800 Hz beside two busy workers)
    last = [0.0, 0]  # when, which tenth

    def progress(e, n: int) -> None:
        now, tenth = time.perf_counter(), 10 * n // max(n_frames, 1)
        if tenth > last[1] or now - last[0] >= 0.2:
            last[:] = [now, tenth]
            report(log, task, n, n_frames)

    with open_estimator(estimator, model, ecfg, cache_dir=out / "model", atlas=atlas, scheduler=scheduler) as est:
        c0 = time.thread_time()
        stats = estimate_stream(src, compensated(est, lag), est_path, progress,
                                live=False, metadata={"model": "../model", "scenario": sc.name, "contact": ecfg.contact,
                                                      "source": f"virtual:{sc.name}",
                                                      "contact_radius_mm": ecfg.contact_radius_m * 1e3, **lag_meta})
        cpu = time.thread_time() - c0
    # the rate in wall time is the share of the cores this process got (the cluster's workers solve
    # the next truths meanwhile); in its own CPU time, what the stream costs
    stats["rate_cpu_Hz"] = stats["estimates"] / cpu if cpu > 0 else float("nan")
    report(log, task, n_frames, n_frames)
    t_est = time.perf_counter() - t1
    t2 = time.perf_counter()
    task = f"{sc.name}: evaluate"
    report(log, task, 0, None, "report")
    tru = read_truth(paths["truth"])
    estimate = read_estimate(est_path)
    advance = tube_advance_ms(estimate, tru)  # from the files where they are now (recording.csv beside it)
    if shown is not None:  # the report names the files where the user will find them
        tru, estimate = (replace(x, source=str(shown / Path(x.source).relative_to(out))) for x in (tru, estimate))
    ev = evaluate(tru, estimate)
    page, rows = write_report(d / "report", tru, estimate, ev, snapshot=paths["snapshot"], tube_advance=advance,
                              title=f"{sc.name} — {sc.description}", clinical=clinical)
    # the tracker path: Motive CSV → reader → rest-window registration → lag against the exact truth
    trk = read_truth(paths["tracker"])
    lag = estimate_lag(tru.t, tru.mm_deg(), trk.t, trk.mm_deg(), max_lag_s=1.0)
    t_eval = time.perf_counter() - t2
    report(log, task, 1, 1, "report")
    rs = run_summary(run)
    return {
        "scenario": sc.name, "report": str(page),
        "rmse": {s.name: s.rmse for s in ev.dof}, "units": {s.name: s.unit for s in ev.dof},
        "peak_truth": {s.name: s.peak_truth for s in ev.dof},
        "force_rmse_N": {s.name: s.rmse for s in ev.force},
        "force_peak_N": {s.name: s.peak_truth for s in ev.force},
        "target_rmse_mm": {s.name: s.rmse for s in ev.targets},
        "lag_ms": ev.lag_ms, "lag_source": ev.lag_source,
        "table_i": [{"dof": r.ref.dof, "observed": r.observed, "unit": r.ref.unit, "flag": r.flag,
                     "study": r.ref.study} for r in rows],
        "tracker_clock_offset_ms": {"injected": rs["tracker"]["clock_offset_s"] * 1e3, "recovered": lag.lag_ms},
        "estimate": {k: stats[k] for k in ("estimates", "rejected", "rate_Hz", "rate_cpu_Hz", "step_ms_p50",
                                           "step_ms_p99")},
        "estimator": estimator,
        "atlas": None if atlas is None else _atlas_row(atlas, est_path),
        "truth": rs["truth"], "seconds": {"truth_solve": truth.solve_s, "estimate": t_est, "evaluate": t_eval},
    }


def _atlas_row(atlas, est_path: Path) -> dict:
    """The summary's atlas entry: its envelope, grid, pieces and the share of estimates inside it;
    for a draft atlas, ``draft`` and its held-out error (``held_out``) as its file keeps it."""
    atlas = getattr(atlas, "atlas", atlas)  # the catalogue's Found: its atlas
    c = getattr(atlas, "config", atlas)  # a built atlas (or its pieces), or the config of one to build
    stack = {"further_min_kPa": c.further_min_kPa, "further_max_kPa": c.further_max_kPa,
             "levels": len(c.levels())} if c.stacked else {}
    draft = {}
    if getattr(c, "draft", False):
        from softphantom.estimation.atlas.check import draft_held_out

        draft = {"draft": True, "held_out": draft_held_out(atlas)}
    return {"force_min_N": c.force_min_N, "force_max_N": c.force_max_N, "p_min_kPa": c.p_min_kPa,
            "p_max_kPa": c.p_max_kPa, "grid": c.shape, "pieces": len(c.patches()), **stack, **draft,
            "in_envelope_fraction": in_envelope_fraction(est_path)}


def _solve_truth(sc, model, truth_cfg, truth_mesh):
    """A Dask task: the truth of ``sc``, its progress as events on :data:`TRUTH_TOPIC` (reported
    again on the client, :func:`run_all`)."""
    from distributed import get_worker

    from softphantom.virtual import solve_truth

    worker = get_worker()

    def sink(step: Step) -> None:
        worker.log_event(TRUTH_TOPIC, (step.task, step.done, step.total, step.what))

    with forward_progress(sink):
        return solve_truth(sc, model, truth_cfg, truth_mesh=truth_mesh)


def _truth_lane(client, order, model, truth_cfg, truth_mesh, ready: queue.Queue, stop: threading.Event,
                together: bool = False) -> None:
    """Solve the truths in ``order``, one at a time (the other workers build the demo's atlases
    meanwhile) or, ``together``, all at once on the cluster's workers; each put on ``ready`` as
    (name, Truth | the exception) when done, in ``order``."""
    submit = lambda sc: client.submit(_solve_truth, sc, model, truth_cfg, truth_mesh, pure=False)  # noqa: E731
    futures = [submit(sc) for sc in order] if together else None
    for i, sc in enumerate(order):
        if stop.is_set():
            return
        try:
            ready.put((sc.name, (futures[i] if together else submit(sc)).result()))
        except Exception as exc:  # noqa: BLE001 - re-raised in the main thread
            ready.put((sc.name, exc))
            return


def model_atlases(scs, model, atlas_dir: Path | None, scheduler: str | None = None,
                  draft: bool = False) -> dict[str, object]:
    """The model's own atlas (:func:`~softphantom.estimation.atlas.config.default_atlas_config`) at
    each contact point the scenarios use ({contact: :class:`~softphantom.estimation.atlas.catalogue.Found`}),
    by the catalogue's order: ``atlas_dir`` (the model directory), the package's shipped files, else
    built there if that takes under ``MAX_BUILD_ON_THE_FLY_S``; else
    :class:`~softphantom.estimation.atlas.build.AtlasMissing`, one line naming the command (with
    ``draft``, the model's draft atlas is built there instead)."""
    from softphantom.estimation.atlas.build import MAX_BUILD_ON_THE_FLY_S
    from softphantom.estimation.atlas.catalogue import find_or_build
    from softphantom.estimation.atlas.check import find_or_build_measured

    find = find_or_build_measured if draft else find_or_build
    found = {}
    for c in dict.fromkeys(contact_of(sc) for sc in scs):
        found[c] = f = find(model, EstimatorConfig(contact=c, mode="sync"), None, model_dir=atlas_dir,
                            scheduler=scheduler, max_build_s=MAX_BUILD_ON_THE_FLY_S)
        log.info(f"{c}: {f.describe()}")
    return found


def run_all(scs, model, out: Path, cfg, truth_mesh, estimator: str = "atlas", grid=None, *,
            scheduler: str | None = None, n_workers: int | None = None, shown: Path | None = None,
            atlas_dir: Path | None = None, atlases: dict | None = None, clinical: bool = True) -> list[dict]:
    """Every scenario of ``scs`` end to end into ``out`` (:func:`run_scenario`), its progress
    reported here (the truths' too, from the workers): truths solved on Dask (together, or one at a
    time while the demo's own atlases build), each scenario then estimated and evaluated here as
    soon as its truth is ready. The estimator: the
    model's own atlas (``atlases`` as :func:`model_atlases` gives them, else found here from
    ``atlas_dir``, default ``out``/model, before any solve); with ``grid`` (points per axis, or ``()``:
    each scenario's kind's, ``PUSH_GRID`` or ``INFLATE_GRID``), the demo's atlases instead (the push scenarios' shared ones,
    :func:`shared_atlases`, built on the same cluster while the truths are solved; an inflation's
    from its truth: those scenarios are solved first). Rows in the order of ``scs``. ``shown``:
    where ``out`` ends up, ``clinical`` whether the reports compare with the paper's Table I
    (:func:`run_scenario`)."""
    from softphantom.parallel import dask_client

    own = grid is None and estimator == "atlas"
    n_cavities = len(model.layout.actuated)
    shared = shared_atlases(scs, grid, n_cavities) if estimator == "atlas" and not own else {}
    order = sorted(scs, key=lambda sc: push_only(sc) in shared)  # stable: the others first
    rows: dict[str, dict] = {}
    truths: dict[str, object] = {}
    ready: queue.Queue = queue.Queue()
    stop = threading.Event()
    # the truth solves and builds are background work beside the estimator's real-time loop here
    with dask_client(scheduler, n_workers, background=True) as client:
        address = client.scheduler.address
        if own:
            with_contact = atlases or model_atlases(scs, model, atlas_dir or out / "model", address)
        truth_steps = {f"{sc.name}: truth": Step(f"{sc.name}: truth", 0, None, "queued") for sc in order}

        def progress(event) -> None:
            step = Step(*event[1])
            if step.task in truth_steps:
                truth_steps[step.task] = step
                report(log, step.task, step.done, step.total, step.what)

        for step in truth_steps.values():
            report(log, step.task, step.done, step.total, step.what)
        client.subscribe_topic(TRUTH_TOPIC, progress)
        lane = threading.Thread(target=_truth_lane, args=(client, order, model, cfg.truth, truth_mesh, ready, stop,
                                                          not shared), daemon=True)
        lane.start()
        try:
            for contact, acfg in shared.items():
                task = f"atlas at {contact}"
                report(log, task, 0, None, f"{acfg.n_solves} forward solves")
                load_or_build(model, EstimatorConfig(contact=contact, mode="sync"), acfg, cache_dir=out / "model",
                              scheduler=address)
                report(log, task, 1, 1, "built")
            for sc in order:
                while sc.name not in truths:
                    name, truth = ready.get()
                    if isinstance(truth, BaseException):
                        raise truth
                    truths[name] = truth
                    last = truth_steps[f"{name}: truth"]
                    report(log, last.task, last.done, last.total, f"solved in {truth.solve_s:.0f} s")
                atlas = with_contact[contact_of(sc)] if own else shared.get(push_only(sc))
                rows[sc.name] = run_scenario(sc, model, out, cfg, truths.pop(sc.name), estimator, grid,
                                             atlas=atlas, scheduler=address, shown=shown, clinical=clinical)
        finally:
            stop.set()
            client.unsubscribe_topic(TRUTH_TOPIC)
    lane.join(5)
    return [rows[sc.name] for sc in scs]


def write_summary(out: Path, work: Path, rows: list[dict], wall_s: float) -> Path:
    """The demo's summary.json and index page into ``work`` (the index's links relative to
    ``out``, where ``work`` ends up); the index's path."""
    (work / "summary.json").write_text(json.dumps({"wall_s": wall_s, "scenarios": rows}, indent=2, default=float)
                                       + "\n")
    items = "".join(
        f"<li><a href='{html.escape(str(Path(r['report']).relative_to(out)))}'>{html.escape(r['scenario'])}</a>: "
        f"lag {r['lag_ms']:.0f} ms; RMSE " + ", ".join(f"{k} {v:.2f} {r['units'][k]}" for k, v in r["rmse"].items())
        + "</li>" for r in rows)
    p = work / "index.html"
    p.write_text("<!doctype html><html><head><meta charset='utf-8'><title>softphantom demo</title></head><body>"
                 f"<h1>softphantom demo</h1><p>virtual phantom, {len(rows)} scenarios, {wall_s:.0f} s</p>"
                 f"<ul>{items}</ul></body></html>\n")
    return p
