"""The atlas catalogue: which atlas a model uses at a contact point, where it comes from, and the
key that names it.

One lookup order, per piece of the atlas (:meth:`AtlasConfig.pieces`):

1. the model directory's own file, ``MODEL/atlas/<key>.npz`` (built there, or installed by
   ``softphantom atlas add``);
2. the package's shipped file: one listed in a shipped model's manifest
   (``softphantom/data/models/<name>/atlas.json``), at ``<name>/atlas/<key>.npz``: the one rule
   for what counts as shipped;
3. built (:func:`~softphantom.estimation.atlas.build.build_atlas`) and saved in the model
   directory.

The key (:func:`atlas_key`) is made from inputs only: the model's arrays as stored (the shipped
mesh is the same bits everywhere), each region's law and parameters as the design file writes
them, the contact point and patch radius, the tracked points, the loads and sensing rows, the
atlas settings, the solver tolerance, the key format and the build's constants that change the
numbers. No float computed at run time goes into it, so it is the same on every CPU, BLAS and
SIMD level. It is computed once per lookup and carried with what is found (:class:`Found`).

Staleness is caught by numbers, not bits (:func:`verify_atlas`): the rest state the atlas was
built on, the model's rest cavity volumes, the contact patch's force sums and the atlas at zero
load are recomputed from the model and compared within stated tolerances (:data:`REST_TOL`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.atlas.config import AtlasConfig, model_atlas_config
from softphantom.estimation.atlas.identity import (KEY_FORMAT, REST_TOL, Check, atlas_key, key_inputs,  # noqa: F401
                                                   piece_keys, rest_checks, rest_record)
from softphantom.estimation.atlas.map import Atlas, AtlasPatches, AtlasStack, regroup
from softphantom.estimation.atlas.store import (AtlasCorrupt, AtlasMismatch, atlas_path, estimator_config,
                                                load_atlas, read_meta, save_atlas)
from softphantom.estimation.config import EstimatorConfig

log = logging.getLogger(__name__)

MANIFEST = "atlas.json"  # a shipped model directory's list of its atlas files
ORIGINS = {"model": "model directory", "shipped": "shipped with softphantom", "built": "built now"}

class ShippedMissing(UserError):
    """A file the package's manifest lists is not there (a damaged install)."""


# -- shipped atlases ------------------------------------------------------------------------------

def shipped_manifests() -> list[tuple[Path, dict]]:
    """(shipped model directory, its manifest) for each shipped model that lists atlases."""
    from softphantom.design.model import SHIPPED_MODELS

    out = []
    for f in sorted(SHIPPED_MODELS.glob(f"*/{MANIFEST}")):
        try:
            out.append((f.parent, json.loads(f.read_text())))
        except (OSError, ValueError):
            raise ShippedMissing(f"{f}: the package's atlas manifest is unreadable (reinstall softphantom)") from None
    return out


def shipped_entries() -> list[tuple[Path, dict]]:
    """(path, manifest entry) of every atlas file the package ships: the one rule for "shipped"."""
    return [(d / "atlas" / f"{e['key'][:32]}.npz", e) for d, m in shipped_manifests() for e in m.get("pieces", ())]


def shipped_atlas(key: str) -> Path | None:
    """The shipped file of atlas ``key`` (listed in a shipped model's manifest), else None; a listed
    file that is missing is a one-line :class:`ShippedMissing` naming it.

    >>> shipped_atlas("0" * 64) is None
    True
    """
    for path, _ in shipped_entries():
        if path.stem == key[:32]:
            if not path.is_file():
                raise ShippedMissing(f"{path}: listed in {path.parent.parent / MANIFEST} but missing: the package "
                                     f"is damaged (reinstall softphantom)")
            return path
    return None


# -- lookup ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Piece:
    """Where one piece of an atlas came from: its ``key``, its file ``path`` and ``origin`` (a key of
    :data:`ORIGINS`: ``model``, ``shipped`` or ``built``)."""

    key: str
    path: Path | None
    origin: str

    def describe(self) -> str:
        return f"{self.path or '(in memory)'} ({ORIGINS[self.origin]})"


@dataclass(frozen=True)
class Found:
    """An atlas found (or built) for a model and contact: ``atlas`` (an Atlas, AtlasPatches or
    AtlasStack), and each piece's :class:`Piece` in ``pieces`` (the keys, computed once)."""

    atlas: Atlas | AtlasPatches | AtlasStack
    pieces: tuple[Piece, ...]

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(p.key for p in self.pieces)

    def describe(self) -> str:
        """One line for the user: where the atlas came from."""
        by = {}
        for p in self.pieces:
            by.setdefault(p.origin, []).append(p)
        parts = []
        for origin, ps in by.items():
            where = {str(p.path.parent) for p in ps if p.path is not None}
            parts.append(f"{len(ps)} piece{'s' * (len(ps) > 1)} {ORIGINS[origin]}"
                         + (f" ({', '.join(sorted(where))})" if where else ""))
        return "atlas: " + "; ".join(parts)


def _n_solves(at: Atlas) -> str:
    if not at.unsolved:
        return f"{at.solves} forward solves"
    return (f"{at.solves} of {at.config.n_solves} forward solves converged ({at.unsolved} grid points unreachable: "
            f"filled, outside the envelope)")


def _looks_like_atlas_dir(model_dir) -> bool:
    return any(len(q.stem) == 32 and set(q.stem) <= set("0123456789abcdef") for q in Path(model_dir).glob("*.npz"))


def resolve_config(model, acfg: AtlasConfig | None, model_dir=None) -> AtlasConfig:
    """The atlas settings a lookup uses: ``acfg``, or the model's default
    (:func:`~softphantom.estimation.atlas.config.model_atlas_config`), for its internal cavities."""

    order = int(getattr(model, "element_order", 1))
    return (acfg or model_atlas_config(order, model_dir)).for_cavities(len(model.layout.actuated))


def find_or_build(model, config: EstimatorConfig | None = None, acfg: AtlasConfig | None = None, *,
                  model_dir=None, scheduler: str | None = None, n_workers: int | None = None, fwd=None,
                  rebuild: bool = False, discard_partial: bool = False,
                  max_build_s: float | None = None, require_full: bool = False, draft: bool = False) -> Found:
    """The atlas ``acfg`` of ``model`` at ``config``'s contact, piece by piece in the catalogue's
    order: ``model_dir``'s own file, the shipped one, else built and saved in ``model_dir``
    (:func:`~softphantom.estimation.atlas.build.build_atlas`; resumable, its finished tasks kept in
    ``MODEL/atlas/partial/``).

    A file of the model directory that is damaged, tampered with or of another format is an error
    (:class:`AtlasCorrupt` / :class:`AtlasMismatch`, one line naming the file, nothing overwritten)
    unless ``rebuild``. With ``max_build_s``, a build estimated to take longer is not started:
    :class:`~softphantom.estimation.atlas.build.AtlasMissing` says how long it takes and how to
    build it. Next to an interrupted build of other settings a build is refused in one line, unless
    ``discard_partial``.

    Where the model's default atlas is missing but its draft (``atlas build --draft``,
    :func:`~softphantom.estimation.atlas.config.draft_atlas_config`) is in ``model_dir`` or ships
    with the package, the draft is used (a warning says so) unless ``require_full``, which refuses a
    draft in one line (:class:`~softphantom.estimation.atlas.build.DraftRefused`). With ``draft``,
    a missing draft is built then (whatever it costs: the user asked for it); its held-out error
    is :func:`~softphantom.estimation.atlas.check.find_or_build_measured`'s."""
    from softphantom.estimation.atlas import build as B
    from softphantom.estimation.atlas.tasks import check_partials, discard_tasks

    B.check_atlas_cavities(model)
    cfg = config or EstimatorConfig()
    acfg = resolve_config(model, acfg, model_dir)
    subs = acfg.pieces()
    keys = piece_keys(model, cfg, acfg)
    found: dict[int, Atlas] = {}
    pieces: dict[int, Piece] = {}
    for p, key in enumerate(keys):
        path = atlas_path(model_dir, key) if model_dir is not None else None
        if path is not None and path.is_file():
            try:
                found[p] = load_atlas(path, key)
                pieces[p] = Piece(key, path, "model")
                continue
            except (AtlasCorrupt, AtlasMismatch) as exc:
                if not rebuild:
                    raise type(exc)(f"{exc}; to build it again: softphantom atlas build --model {model_dir} "
                                    f"--rebuild") from None
                log.warning(f"{exc}: rebuilding")
        shipped = shipped_atlas(key)
        if shipped is not None:  # a damaged shipped file is an error naming it (the package's, not the user's)
            found[p] = load_atlas(shipped, key)
            pieces[p] = Piece(key, shipped, "shipped")
            continue
        if path is not None and _looks_like_atlas_dir(model_dir):
            # the atlas directory given for the model's: its atlases are never found, every run builds
            log.warning(f"atlas: {model_dir} holds atlas files itself, but the cache is a model directory "
                        f"(atlases in its atlas/ subdirectory): building into {path.parent}")
    for p in sorted(found):
        log.info(f"atlas: {pieces[p].describe()}: {_n_solves(found[p])}")
    c = cfg.contact
    at = "" if c == "on-centre" else f" --at {c}" if isinstance(c, str) else " (its contact point)"
    order = int(getattr(model, "element_order", 1))
    if require_full and acfg.draft:
        raise B.DraftRefused(f"{model_dir or 'the model'}: --require-full, but the atlas asked for is a draft; build "
                             f"the full one with `softphantom atlas build --model {model_dir}{at}`")
    missing = tuple(p for p in range(len(subs)) if p not in found)
    if missing and not acfg.draft and not rebuild and acfg == resolve_config(model, None, model_dir):
        dcfg = resolve_config(model, model_atlas_config(order, model_dir, draft=True), model_dir)
        have = all((model_dir is not None and atlas_path(model_dir, k).is_file()) or shipped_atlas(k) is not None
                   for k in piece_keys(model, cfg, dcfg))
        if (have or draft) and require_full:
            raise B.DraftRefused(f"{model_dir or 'the model'}: --require-full, but this model and contact have only a "
                                 f"draft atlas (atlas build --draft); build the full one with `softphantom atlas "
                                 f"build --model {model_dir}{at}`")
        if have or (draft and model_dir is not None):
            log.warning(f"atlas: using a draft atlas at {c} (no full atlas for this model and contact yet: "
                        f"`softphantom atlas build --model {model_dir}{at}` builds it)")
            return find_or_build(model, cfg, dcfg, model_dir=model_dir, fwd=fwd, scheduler=scheduler,
                                 n_workers=n_workers)
    if missing:
        if max_build_s is not None:
            nodes = len(_mesh_nodes(model))
            w = int(n_workers or os.cpu_count() or 1)
            e = B.estimate_build(order, nodes, acfg, w)
            cpu = e.cpu_s * len(missing) / len(subs)
            wall = max(e.wall_s * len(missing) / len(subs), e.critical_path_s)
            if wall > max_build_s:
                n = sum(subs[p].n_solves for p in missing)
                d = B.estimate_build(order, nodes, model_atlas_config(order, model_dir, draft=True), w)
                small = replace(acfg, n_force=(3, 3, 3), n_pressure=2, f_y_splits_N=())
                small_wall = B.estimate_build(order, nodes, small, w).wall_s
                raise B.AtlasMissing(
                    f"{model_dir or 'the model'}: no atlas yet for this model and contact; building it takes about "
                    f"{B.duration_text(wall)} on {w} cores ({n} grid points, ≈ {cpu:.0f} CPU-s), a draft "
                    f"(--draft: {B.draft_points(order)} points, its error measured) about "
                    f"{B.duration_text(d.wall_s)}: build it once with `softphantom atlas build --model {model_dir}{at}` "
                    f"[--draft] (resumable; --scheduler ADDR for a Dask cluster), or give --draft here (demo, "
                    f"estimate); or a small atlas over your own "
                    f"loads, --atlas-grid 3,3,3,2 --envelope FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX (N, kPa; "
                    f"about {B.duration_text(small_wall)}; docs/organs.md); or estimate meanwhile with "
                    f"--estimator refresh")
        if model_dir is not None:
            check_partials(model_dir, B.build_settings(cfg, acfg, len(_mesh_nodes(model))), discard=discard_partial)
        built = B.build_atlas(model, cfg, acfg, keys=keys, scheduler=scheduler, n_workers=n_workers, fwd=fwd,
                              cache_dir=model_dir, pieces=missing)
        for p, at in zip(missing, built if isinstance(built, list) else [built]):
            msg = (f"atlas: {_n_solves(at)} in {at.build_s:.0f} s ({at.build_cpu_s / at.config.n_solves:.2f} CPU-s "
                   f"a solve), {at.nbytes / 1e6:.1f} MB")
            path = None
            if model_dir is not None:
                path = save_atlas(at, atlas_path(model_dir, at.key))
                at = load_atlas(path, at.key)  # as stored (the compact field): the same atlas as a later load
                discard_tasks(model_dir, at.key)  # built and saved: its kept tasks are not needed any more
                msg += f" → {path} ({path.stat().st_size / 1e6:.1f} MB on disk)"
            log.info(msg)
            found[p] = at
            pieces[p] = Piece(at.key, path, "built")
    return Found(regroup(acfg, found), tuple(pieces[p] for p in range(len(subs))))


def load_or_build(model, config: EstimatorConfig | None = None, atlas: AtlasConfig | None = None, *,
                  cache_dir=None, **kw):
    """The atlas itself of :func:`find_or_build` (``cache_dir``: the model directory)."""
    return find_or_build(model, config, atlas, model_dir=cache_dir, **kw).atlas


def _mesh_nodes(model) -> np.ndarray:
    from softphantom.fem.model import mesh_arrays

    return mesh_arrays(model)[0]


# -- what a model directory has, checking and installing files --------------------------------------

def atlases_of(model_dir, model=None) -> list[Path]:
    """The atlas files of a model directory (``MODEL/atlas/*.npz``, by name); with ``model``, then the
    shipped files that are this model's (their key is the one this model gives for their own
    settings)."""
    d = Path(model_dir) / "atlas"
    own = sorted(p for p in d.glob("*.npz") if p.is_file()) if d.is_dir() else []
    if model is None:
        return own
    names = {q.name for q in own}
    shipped = []
    for path, _ in shipped_entries():
        if path.name in names or not path.is_file():
            continue
        meta = read_meta(path)
        try:
            cfg = estimator_config(meta, path)
            key = atlas_key(model, cfg, AtlasConfig(**meta["config"]))
        except UserError:
            continue  # a contact this model does not have: not its atlas
        if key == meta.get("key"):
            shipped.append(path)
    return own + shipped


@dataclass(frozen=True)
class Verified:
    """An atlas file that passed :func:`verify_atlas`: the ``atlas``, its ``key`` and the ``checks``."""

    atlas: Atlas
    key: str
    checks: tuple[Check, ...]


def verify_atlas(path, model, fem=None) -> Verified:
    """Check the atlas file ``path`` against ``model``: intact (its digest), of this softphantom's
    format, its key the one this model gives for the file's own settings, and the numbers it
    recorded at rest the model's (:func:`rest_checks`). Else one line naming the file and what
    differs (:class:`AtlasCorrupt`, :class:`AtlasMismatch`). ``fem``: the model's FemModel, to
    reuse."""
    at = load_atlas(path)
    cfg = estimator_config(at.provenance or {}, path)
    try:
        key = atlas_key(model, cfg, at.config)
    except UserError as exc:
        raise AtlasMismatch(f"{path}: not for this model ({exc})") from None
    if key != at.key:
        raise AtlasMismatch(f"{path}: atlas built for another model, law, element, mesh or settings than this one "
                            f"(its key {at.key[:12]}…, this model with its settings gives {key[:12]}…)")
    checks = tuple(rest_checks(at, model, fem))
    bad = [c for c in checks if not c.ok]
    if bad:
        c = bad[0]
        raise AtlasMismatch(f"{path}: {c.quantity} differ from this model's by {c.difference:.3g} {c.unit} (tolerance "
                            f"{c.tolerance:g}): the atlas is stale or not this model's; rebuild it")
    return Verified(at, key, checks)


def install_atlas(path, model, model_dir) -> tuple[Path, str]:
    """Verify the atlas file ``path`` against ``model`` and copy it to where the model directory's
    lookups find it (``MODEL/atlas/<key>.npz``). Returns (destination, what happened: ``"added"``,
    ``"present"`` when an intact copy is already there, ``"replaced"`` when the one there was damaged).
    A file that does not verify is refused (nothing is written)."""
    at = verify_atlas(path, model).atlas
    dest = atlas_path(model_dir, at.key)
    what = "added"
    if dest.is_file():
        try:
            load_atlas(dest, at.key)
            return dest, "present"
        except (AtlasCorrupt, AtlasMismatch):
            what = "replaced"
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.copyfile(path, tmp)
    tmp.replace(dest)
    return dest, what
