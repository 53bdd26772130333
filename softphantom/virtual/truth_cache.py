"""The truth cache: a solved truth kept by the key of what it depends on (the model, the
scenario's load paths, the settings), read back instead of solved again
(:func:`~softphantom.virtual.truth.solve_truth` with ``cache=True``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from softphantom.design import PhantomModel, design_to_dict
from softphantom.errors import UserError
from softphantom.virtual.scenario import Scenario
from softphantom.virtual.truth_records import EventTruth, GroupTruth, Truth, TruthConfig

log = logging.getLogger(__name__)

#: Bumped when what a solve produces for the same inputs changes, so older entries are not read.
TRUTH_CACHE_FORMAT = 1
#: The environment variable naming the cache directory ("": no cache).
CACHE_ENV = "SOFTPHANTOM_CACHE_DIR"
_EVENT_ARRAYS = ("s", "dV", "markers", "targets", "bulb_dV", "force", "x_peak")
_GROUP_ARRAYS = ("s1", "s2", "dV", "markers", "targets", "bulb_dV", "force", "x_peak")


def truth_cache_dir() -> Path | None:
    """Where solved truths are kept: ``$SOFTPHANTOM_CACHE_DIR`` (empty: nowhere), else
    ``$XDG_CACHE_HOME/softphantom``, else ``~/.cache/softphantom``; each truth under
    ``truth/<key>/`` (:func:`truth_key`)."""
    given = os.environ.get(CACHE_ENV)
    if given is not None:
        return Path(given).expanduser() if given.strip() else None
    base = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(base) if base else Path.home() / ".cache") / "softphantom"


def _scenario_dict(sc: Scenario) -> dict:
    """What a truth depends on in a scenario: its loads and their timing shape (not its name,
    description or file)."""
    d = dataclasses.asdict(sc)
    for k in ("name", "description", "source", "duration_s", "rest_s"):
        d.pop(k)
    for e in d["events"]:  # when an event starts and ends changes no keyframe: only its load path
        for k in ("start_s", "rise_s", "hold_s", "fall_s", "repeat", "period_s"):
            e.pop(k)
    d["groups"] = [list(g) for g in sc.groups]  # which events act at once: the two-parameter paths
    return d


def _model_digest(h, model: PhantomModel) -> None:
    h.update(json.dumps(design_to_dict(model.design), sort_keys=True).encode())
    for a in (model.nodes, model.tets, getattr(model, "tets10", None)):
        if a is not None:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())


def truth_key(scenario: Scenario, model: PhantomModel, config: TruthConfig,
              truth_mesh: PhantomModel | None = None) -> str:
    """SHA-256 (hex) of what a solved truth depends on: the model (its design and mesh; or the
    given truth mesh), the scenario's load paths (:func:`_scenario_dict`, its cavities named:
    ``scenario`` as :func:`solve_truth` checked it), the truth settings and
    :data:`TRUTH_CACHE_FORMAT`. Only the inputs as given: no number computed while solving."""
    h = hashlib.sha256()
    _model_digest(h, model)
    if truth_mesh is not None:
        h.update(b"truth mesh")
        _model_digest(h, truth_mesh)
    h.update(json.dumps({"format": TRUTH_CACHE_FORMAT, "config": dataclasses.asdict(config),
                         "scenario": _scenario_dict(scenario)}, sort_keys=True).encode())
    return h.hexdigest()


def save_truth(truth: Truth, entry: Path, key: str) -> None:
    """Keep ``truth`` in the cache directory ``entry`` (its truth mesh, keyframes and peak states):
    written beside it and moved into place, so a reader never sees half an entry. A cache that
    cannot be written is logged and left out (the run goes on)."""
    from softphantom.design import save_model

    entry = Path(entry)
    tmp = entry.with_name(f".{entry.name}.{os.getpid()}.tmp")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        save_model(truth.model, tmp / "truth_model", mesh_files=False)
        arrays = {"rest_markers": truth.rest_markers, "rest_volumes": truth.rest_volumes}
        for i, et in enumerate(truth.events):
            arrays.update({f"e{i}_{k}": np.asarray(getattr(et, k)) for k in _EVENT_ARRAYS})
        for i, g in enumerate(truth.groups):
            arrays.update({f"g{i}_{k}": np.asarray(getattr(g, k)) for k in _GROUP_ARRAYS})
        np.savez(tmp / "truth.npz", **arrays)
        meta = {"key": key, "format": TRUTH_CACHE_FORMAT, "solve_s": truth.solve_s,
                "marker_names": list(truth.marker_names), "target_names": list(truth.target_names),
                "events": [{"p_Pa": et.p_Pa, "iterations": et.iterations, "note": et.note} for et in truth.events],
                "groups": [{"pair": list(g.pair), "pressures_Pa": g.pressures_Pa, "solves": g.solves,
                            "iterations": g.iterations} for g in truth.groups]}
        (tmp / "truth.json").write_text(json.dumps(meta, sort_keys=True), encoding="utf-8")
        entry.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(tmp, entry)
        except OSError:  # another run kept the same truth first
            shutil.rmtree(tmp, ignore_errors=True)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        log.warning("truth cache: cannot write %s (%s); the truth is not kept", entry, exc.strerror or exc)


def load_truth(entry: Path, scenario: Scenario, config: TruthConfig) -> Truth | None:
    """The truth kept in ``entry`` for ``scenario`` (as :func:`solve_truth` checked it), or None when
    there is none or it cannot be read (it is then solved again)."""
    from softphantom.design import load_model

    entry = Path(entry)
    if not (entry / "truth.json").is_file():
        return None
    try:
        meta = json.loads((entry / "truth.json").read_text(encoding="utf-8"))
        if meta.get("format") != TRUTH_CACHE_FORMAT or len(meta["events"]) != len(scenario.events):
            return None
        tm = load_model(entry / "truth_model")
        with np.load(entry / "truth.npz", allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        events = tuple(EventTruth(e, *(a[f"e{i}_{k}"] for k in _EVENT_ARRAYS[:6]), float(m["p_Pa"]),
                                  a[f"e{i}_x_peak"], int(m["iterations"]), m["note"])
                       for i, (e, m) in enumerate(zip(scenario.events, meta["events"])))
        groups = tuple(GroupTruth(tuple(m["pair"]), tuple(scenario.events[j] for j in m["pair"]),
                                  *(a[f"g{i}_{k}"] for k in _GROUP_ARRAYS[:7]), dict(m["pressures_Pa"]),
                                  a[f"g{i}_x_peak"], int(m["solves"]), int(m["iterations"]))
                       for i, m in enumerate(meta["groups"]))
    except (OSError, ValueError, KeyError, TypeError, UserError) as exc:
        log.warning("truth cache: %s cannot be read (%s); solving the truth again", entry, exc)
        return None
    return Truth(scenario, tm, tuple(meta["marker_names"]), tuple(meta["target_names"]), a["rest_markers"],
                 a["rest_volumes"], events, float(meta["solve_s"]), config, groups, cached=True)
