"""The atlas build's fine task graph and its cost model, and the draft atlas: found where the full
atlas is missing, refused with --require-full, its error measured from full solves started at its
own field (the same equilibria as solves from rest)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from softphantom.estimation import EstimatorConfig
from softphantom.estimation.atlas.build import (AtlasMissing, DraftRefused, _piece_tasks, build_atlas, estimate_build,
                                                face_segments, plan_tasks)
from softphantom.estimation.atlas.catalogue import atlas_key, load_or_build
from softphantom.estimation.atlas.config import AtlasConfig, default_atlas_config, model_atlas_config
from softphantom.estimation.atlas.store import atlas_path, save_atlas
from softphantom.estimation.atlas.tasks import bottom_levels
from softphantom.estimation.forward import ForwardModel

CFG = EstimatorConfig(contact="on-centre")


def test_the_fine_graph_covers_every_grid_point_once_and_each_line_waits_for_its_two_face_points():
    acfg = default_atlas_config(2).pieces()[1]
    n1, n2, n3, n4 = acfg.shape
    tasks = _piece_tasks(None, None, acfg, None, "p1", 1)
    by = {t.name: t for t in tasks}
    j0 = face_segments(acfg)[0][1][0][0]
    assert sum(t.points for t in tasks) == n1 * n2 * n3 * n4  # every grid point, once
    for t in tasks:
        what, *n = t.name.split("-")[1:]
        if what != "line":
            continue
        k, l, j = map(int, n)
        for d, i in zip(t.deps, (0, n1 - 1)):
            assert d.endswith(f"-{i}-{l}") and by[d].points in (n3, n2 - 1)
            assert ("spine" in d) == (j == j0) and ("spine" in d or d.startswith(f"p1-branch-{k}-"))
    # the longest chain of grid points: a spine, a branch, a line — not a plane and its lines
    chain = max(bottom_levels(tasks, {t.name: float(t.points) for t in tasks}).values())
    assert chain == n3 + (n2 - 1) + (n1 - 2)


def test_the_cost_model_predicts_a_critical_path_far_below_the_wall_time_and_schedules_workers():
    one, two, many = (estimate_build(2, 28329, default_atlas_config(2), w, pardiso=False) for w in (1, 2, 1000))
    assert one.wall_s == pytest.approx(one.cpu_s)  # one worker: the tasks one after the other
    assert one.cpu_s / 2 <= two.wall_s <= one.cpu_s / 2 * 1.02  # two: nearly all of both
    assert many.wall_s == pytest.approx(many.critical_path_s) and many.critical_path_s < 600  # a worker a task
    tasks = plan_tasks(2, 28329, default_atlas_config(2), pardiso=False)
    level = bottom_levels(tasks, {t.name: t.cost for t in tasks})
    probes = [t for t in tasks if t.priority > 10 * max(level.values())]
    # the long chains first, but one task of each kind as soon as it can run (the ETA's rates)
    assert sorted(t.kind for t in probes) == sorted({t.kind for t in tasks})
    assert all(t.priority == round(level[t.name] * 10) for t in tasks if t not in probes)


@pytest.fixture(scope="module")
def draft(coarse_model):
    """A draft atlas of the coarse model over a small envelope, 3 × 3 × 3 × 2 points (the real
    draft's build takes minutes), and its config: built once for the two tests below."""
    acfg = AtlasConfig(force_min_N=(-0.5, -0.3, -0.5), force_max_N=(0.5, 1.2, 0.5), p_min_kPa=-1.0, p_max_kPa=4.0,
                       n_force=(3, 3, 3), n_pressure=2, draft=True)
    return acfg, build_atlas(coarse_model, CFG, acfg, n_workers=1, processes=False)


@pytest.mark.slow
def test_a_draft_is_its_own_key_and_is_used_where_the_full_atlas_is_missing(coarse_model, draft, tmp_path):
    fwd = ForwardModel(coarse_model, CFG)
    full = model_atlas_config(1, tmp_path)
    draft, at = draft
    assert atlas_key(fwd.model, fwd.config, draft) != atlas_key(fwd.model, fwd.config, replace(draft, draft=False))
    assert "draft" not in full.as_dict()  # a full atlas's key is the one it had before the flag

    with pytest.raises(AtlasMissing) as exc:  # nothing built: how long the full atlas and a draft take
        load_or_build(coarse_model, CFG, cache_dir=tmp_path, fwd=fwd, max_build_s=0.0)
    assert "--draft" in str(exc.value) and "\n" not in str(exc.value)

    assert at.draft and at.config.draft
    save_atlas(at, atlas_path(tmp_path, at.key))
    import softphantom.estimation.atlas.build as build_mod
    import softphantom.estimation.atlas.config as config_mod

    # the model's draft config is this small grid here (the real one's build takes minutes)
    orig = config_mod.draft_atlas_config
    try:
        config_mod.draft_atlas_config = lambda order=1: draft
        got = load_or_build(coarse_model, CFG, cache_dir=tmp_path, fwd=fwd, max_build_s=0.0)
        assert got.draft and got.key == at.key
        with pytest.raises(DraftRefused) as exc:
            load_or_build(coarse_model, CFG, cache_dir=tmp_path, fwd=fwd, max_build_s=0.0, require_full=True)
        msg = str(exc.value)
        assert "\n" not in msg and "--require-full" in msg and "softphantom atlas build --model" in msg
    finally:
        config_mod.draft_atlas_config = orig
    assert build_mod.draft_points(2) == 120


@pytest.mark.slow
def test_a_draft_checks_against_the_same_equilibria_as_solves_from_rest(coarse_model, draft):
    from softphantom.estimation.atlas.check import _solve_near

    _, at = draft
    for lam in (np.array([0.31, 0.77, -0.22, 2.1e3]), np.array([-0.4, 1.1, 0.4, -0.5e3])):
        near = _solve_near(ForwardModel(coarse_model, CFG), at, lam, lam)
        rest = ForwardModel(coarse_model, CFG).solve(lam)
        scale = np.abs(rest.x - coarse_model_x_rest(coarse_model)).max()
        assert np.abs(near.x - rest.x).max() <= 1e-6 * scale
        assert near.residual <= CFG.tol


def coarse_model_x_rest(model) -> np.ndarray:
    from softphantom.fem import fem_from_phantom

    return fem_from_phantom(model).x_rest


def test_the_eta_is_exact_once_every_kind_has_a_finished_task_when_tasks_take_their_predicted_cost():
    """A run whose tasks take their predicted cost times an unknown rate per kind (a loaded machine,
    another model): once a task of each kind has finished, the printed time left is the time the
    run still takes, tail of the graph included."""
    import heapq

    from softphantom.estimation.atlas.tasks import Eta

    tasks = plan_tasks(2, 28329, default_atlas_config(2), pardiso=True)
    rate = {"spine": 0.7, "branch": 1.3, "line": 2.1}  # wall-s per predicted CPU-s, unknown to the ETA
    true = {t.name: t.cost * rate[t.kind.split()[-1]] * (1.3 if t.kind.startswith("piece 1") else 1.0) for t in tasks}
    workers = 4
    eta = Eta(tasks, workers=workers)
    eta.start(0.0)
    done: set[str] = set()
    queued: list[tuple[int, int, str]] = []  # (-priority, submission order, name): Dask's order
    running: list[tuple[float, str]] = []
    submitted, now, checks = set(), 0.0, []
    order = 0

    def submit_ready(now):
        nonlocal order
        for t in tasks:
            if t.name not in submitted and all(d in done for d in t.deps):
                submitted.add(t.name)
                eta.started(t.name, now)
                heapq.heappush(queued, (-t.priority, order, t.name))
                order += 1
        while queued and len(running) < workers:
            _, _, n = heapq.heappop(queued)
            heapq.heappush(running, (now + true[n], n))

    submit_ready(0.0)
    end = None
    log = []
    while running:
        now, n = heapq.heappop(running)
        done.add(n)
        eta.finished(n, cpu_s=true[n], wall_s=true[n], now=now)
        submit_ready(now)
        kinds = {eta.by[m].kind for m in done}
        if len(kinds) == len({t.kind for t in tasks}) and running:
            log.append((now, eta.seconds_left(now)))
        end = now
    assert log
    for t, left in log:
        checks.append(abs(left - (end - t)) / (end - t))
    assert max(checks) < 1e-6, max(checks)


@pytest.mark.slow
def test_with_draft_a_missing_atlas_is_built_as_the_draft_and_a_shipped_draft_is_found(coarse_model, draft, tmp_path,
                                                                                        monkeypatch):
    """``--draft`` (demo, estimate): no full atlas anywhere → the draft is built, its error measured
    once and kept in its file; a draft the package ships stands in for a missing full atlas too."""
    import contextlib

    import softphantom.estimation.atlas.build as build_mod
    import softphantom.estimation.atlas.catalogue as cat
    import softphantom.estimation.atlas.check as check_mod
    import softphantom.estimation.atlas.config as config_mod
    import softphantom.parallel as parallel_mod
    from softphantom.estimation.atlas.catalogue import find_or_build
    from softphantom.estimation.atlas.check import find_or_build_measured

    acfg, at = draft
    fwd = ForwardModel(coarse_model, CFG)
    monkeypatch.setattr(config_mod, "draft_atlas_config", lambda order=1: acfg)
    built, measured = [], []
    monkeypatch.setattr(build_mod, "build_atlas", lambda *a, **k: built.append(k["keys"]) or [at])
    monkeypatch.setattr(parallel_mod, "dask_client", lambda *a, **k: contextlib.nullcontext(None))
    held = {"loads": 12, "worst": {"force_N": 0.01, "pos_mm": 0.02, "ang_deg": 0.05}}
    monkeypatch.setattr(check_mod, "check_draft", lambda *a, **k: measured.append(1) or held)

    with pytest.raises(AtlasMissing) as exc:  # without --draft: refused, naming --draft here
        find_or_build(coarse_model, CFG, model_dir=tmp_path, fwd=fwd, max_build_s=0.0)
    assert "give --draft here" in str(exc.value) and not built
    with pytest.raises(DraftRefused):
        find_or_build_measured(coarse_model, CFG, model_dir=tmp_path, fwd=fwd, max_build_s=0.0, require_full=True)

    got = find_or_build_measured(coarse_model, CFG, model_dir=tmp_path, fwd=fwd, max_build_s=0.0)
    assert built == [(at.key,)] and measured == [1]
    assert got.atlas.draft and got.keys == (at.key,) and got.atlas.provenance["held_out"] == held
    again = find_or_build_measured(coarse_model, CFG, model_dir=tmp_path, fwd=fwd, max_build_s=0.0)
    assert [p.origin for p in again.pieces] == ["model"] and measured == [1]  # its error kept, not measured again

    shipped = atlas_path(tmp_path, at.key)
    monkeypatch.setattr(cat, "shipped_atlas", lambda key: shipped if key == at.key else None)
    other = tmp_path / "other"
    got = find_or_build(coarse_model, CFG, model_dir=other, fwd=fwd, max_build_s=0.0)
    assert [p.origin for p in got.pieces] == ["shipped"] and got.atlas.draft and len(built) == 1
    with pytest.raises(DraftRefused):
        find_or_build(coarse_model, CFG, model_dir=other, fwd=fwd, max_build_s=0.0, require_full=True)
