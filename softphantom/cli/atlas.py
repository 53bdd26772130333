"""``softphantom atlas build|info|verify|add``: the estimator's offline atlas as an artefact."""

from __future__ import annotations

from pathlib import Path

import typer

from softphantom.cli.app import app, console, print_error
from softphantom.cli.options import (At, AtlasFYSplitN, AtlasGrid, AtlasXAxis, Envelope, ModelDir, Scheduler, Seed,
                                     Workers, check_workers)
from softphantom.errors import UserError

atlas_app = typer.Typer(help="The atlas estimator's offline stage: build, describe, verify and install atlas "
                        "files (MODEL/atlas/<key>.npz, content-addressed: copy them between machines).",
                        no_args_is_help=True)
app.add_typer(atlas_app, name="atlas")



def _model(model_dir: Path):
    from softphantom.design import load_model

    if not (model_dir / "model.npz").is_file():
        raise UserError(f"--model {model_dir}: not a model directory (no model.npz; run softphantom design)")
    return load_model(model_dir)


def _contact(at: str, model) -> str:
    from softphantom.design.params import check_contact

    return check_contact(at, list(model.p_ext), "--at")


def _print_rows(rows) -> None:
    for label, value in rows:
        console.print(f"  {label:9s} {value}", highlight=False, soft_wrap=True)


@atlas_app.command("build")
def build_cmd(
    model_dir: ModelDir = ...,
    at: At = "on-centre",
    atlas_grid: AtlasGrid = None,
    atlas_x_axis: AtlasXAxis = None,
    atlas_f_y_split: AtlasFYSplitN = None,
    envelope: Envelope = None,
    offline: str = typer.Option("full", "--offline", help="How the grid is solved: full (a converged full solve "
                                "per point) or rom (a reduced model trained on a few full solves and checked "
                                "against others; the checks' error is in atlas info). docs/offline.md."),
    scheduler: Scheduler = None,
    workers: Workers = None,
    rebuild: bool = typer.Option(False, "--rebuild", help="Build again even where an atlas file is cached, "
                                 "replacing a damaged or stale one."),
    discard_partial: bool = typer.Option(False, "--discard-partial", help="Drop the finished tasks of an "
                                         "interrupted build with other settings (by default such a build is "
                                         "refused; one with the same settings resumes)."),
    draft: bool = typer.Option(False, "--draft", help="A quick atlas on a coarse grid (minutes): its held-out "
                               "error is measured, printed and kept in the file; estimate uses it (saying "
                               "'draft atlas') until the full one is built, and --require-full refuses it."),
) -> None:
    """Build the atlas of a model (or find it built) in MODEL/atlas/, on Dask. Every finished task is
    kept in MODEL/atlas/partial/: after Ctrl-C, kill or a reboot the same command goes on where it
    stopped. Progress shows the time left."""
    from dataclasses import replace

    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.catalogue import find_or_build
    from softphantom.estimation.atlas.config import default_atlas_config, model_atlas_config
    from softphantom.estimation.select import atlas_config_from_options

    # bad options fail before the model is read: valid for a model of either element order (a grid
    # of 2 f_z points is one for the quadratic default's Hermite f_z); the model's own check follows
    for order in (1, 2):
        try:
            atlas_config_from_options(atlas_grid, envelope, atlas_x_axis, atlas_f_y_split,
                                      base=default_atlas_config(order))
            break
        except UserError:
            if order == 2:
                raise
    if offline not in ("full", "rom"):
        raise UserError(f"--offline: full or rom, got {offline!r}")
    check_workers(workers)
    model = _model(model_dir)
    _contact(at, model)
    acfg = atlas_config_from_options(atlas_grid, envelope, atlas_x_axis, atlas_f_y_split,
                                     base=model_atlas_config(model.element_order, model_dir, draft=draft))
    acfg = replace(acfg, offline=offline)
    cfg = EstimatorConfig(contact=_contact(at, model))
    found = find_or_build(model, cfg, acfg, model_dir=model_dir, scheduler=scheduler, n_workers=workers,
                          rebuild=rebuild, discard_partial=discard_partial)
    if draft:
        _measure_draft(model, cfg, found, model_dir, scheduler, workers)
    for piece in found.pieces:
        console.print(piece.describe(), highlight=False, soft_wrap=True)


def _measure_draft(model, cfg, found, model_dir: Path, scheduler, workers) -> None:
    """A draft's held-out error: measured once (kept in each piece's file), printed every time."""
    from softphantom.estimation.atlas.check import draft_error_text, measure_draft
    from softphantom.progress import status

    with status("draft atlas: held-out full solves", console):
        held = measure_draft(model, cfg, found, model_dir, scheduler, workers)
    console.print(f"draft atlas: {draft_error_text(held)}", highlight=False, soft_wrap=True)


@atlas_app.command("info")
def info_cmd(
    files: list[Path] = typer.Argument(None, help="Atlas files (default: those of --model)."),
    model_dir: ModelDir = None,
) -> None:
    """Describe atlas files: model, contact, envelope, grid, build cost, provenance. With --model: its
    atlases (MODEL/atlas/, and those shipped with softphantom for its mesh)."""
    from softphantom.estimation.atlas.catalogue import atlases_of
    from softphantom.estimation.atlas.store import describe, load_atlas

    if not files:
        if model_dir is None:
            raise UserError("atlas info: give atlas files or --model DIR")
        files = atlases_of(model_dir, _model(model_dir))
        if not files:
            console.print(f"{model_dir}: no atlas built yet (softphantom atlas build --model {model_dir})",
                          highlight=False)
            return
    for f in files:
        at = load_atlas(f)
        console.print(f"{f}", highlight=False, soft_wrap=True)
        rows = describe(at)
        if at.draft:
            from softphantom.estimation.atlas.check import draft_error_text

            held = (at.provenance or {}).get("held_out")
            rows = [*rows, ("draft", draft_error_text(held) if held else "its error not measured yet")]
        _print_rows(rows)


@atlas_app.command("verify")
def verify_cmd(
    files: list[Path] = typer.Argument(None, help="Atlas files (default: every file in MODEL/atlas/, and those "
                                       "shipped with softphantom for the model's mesh)."),
    model_dir: ModelDir = ...,
) -> None:
    """Check atlas files against a model: intact (digest), this softphantom's format, built for this
    model (the key recomputed from the model's inputs), and not stale: the numbers it recorded of the
    model at rest (rest nodes, cavity volumes, the contact patch's force sums, its own error at zero
    load) recomputed from the model within stated tolerances. Exit 2 naming each file that fails and
    the quantity that differs."""
    from softphantom.estimation.atlas.catalogue import atlases_of, verify_atlas
    from softphantom.fem.model import fem_from_phantom

    model = _model(model_dir)
    files = files or atlases_of(model_dir, model)
    if not files:
        raise UserError(f"{model_dir}: no atlas files to verify (softphantom atlas build --model {model_dir})")
    failed = 0
    fem = None
    for f in files:
        if not Path(f).is_file():
            failed += 1
            print_error(f"{f}: no such atlas file")
            continue
        try:
            fem = fem or fem_from_phantom(model)
            v = verify_atlas(f, model, fem)
        except UserError as exc:
            failed += 1
            print_error(str(exc))
            continue
        at = v.atlas
        console.print(f"ok  {f}  (key {at.key[:12]}…, {' × '.join(map(str, at.config.shape))} points)",
                      highlight=False, soft_wrap=True)
        for c in v.checks:
            console.print(f"      {c.quantity:28s} {c.difference:.3g} {c.unit} (tolerance {c.tolerance:g})",
                          highlight=False, soft_wrap=True)
    if failed:
        raise typer.Exit(2)


@atlas_app.command("add")
def add_cmd(
    file: Path = typer.Argument(..., help="An atlas file built elsewhere (e.g. on a lab's cluster)."),
    model_dir: ModelDir = ...,
) -> None:
    """Verify an atlas file against a model and install it in MODEL/atlas/ under its key."""
    from softphantom.estimation.atlas.catalogue import install_atlas

    if not file.is_file():
        raise UserError(f"{file}: no such atlas file")
    dest, what = install_atlas(file, _model(model_dir), model_dir)
    console.print(f"{what}: {dest}" if what != "present" else f"already present (intact): {dest}",
                  highlight=False, soft_wrap=True)


@atlas_app.command("check")
def check_cmd(
    model_dir: ModelDir = ...,
    at: At = "on-centre",
    loads: int = typer.Option(20, "--loads", help="Held-out loads (seeded, over the whole envelope, a quarter "
                              "near its corners): one converged full solve each."),
    seed: Seed = 0,
    max_force_N: float = typer.Option(0.05, "--max-force-N", help="Goal: largest force error of the inverse (N)."),
    max_pos_mm: float = typer.Option(0.05, "--max-pos-mm", help="Goal: largest marker-pose position error (mm)."),
    max_ang_deg: float = typer.Option(0.1, "--max-ang-deg", help="Goal: largest marker-pose angle error (deg)."),
    max_near_urethra_mm: float = typer.Option(0.02, "--max-near-urethra-mm", help="Goal: largest error of the "
                                              "near_urethra target (mm)."),
    scheduler: Scheduler = None,
    workers: Workers = None,
) -> None:
    """Check a model's atlas against converged full solves at seeded held-out loads: the map (volumes,
    points) and its inverse (force, pose, targets), worst and 90th percentile. Exit 1 when a goal is
    missed, 2 when the model has no atlas. --workers 0: solve in this process."""
    from contextlib import nullcontext

    import numpy as np

    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.atlas.catalogue import load_or_build
    from softphantom.estimation.atlas.check import check_held_out, held_out_loads
    from softphantom.parallel import dask_client
    from softphantom.progress import status

    if loads < 1:
        raise UserError(f"--loads must be >= 1, got {loads}")
    check_workers(workers, zero=True)
    for name, v in (("--max-force-N", max_force_N), ("--max-pos-mm", max_pos_mm), ("--max-ang-deg", max_ang_deg),
                    ("--max-near-urethra-mm", max_near_urethra_mm)):
        if not v > 0:
            raise UserError(f"{name} must be > 0, got {v:g}")
    model = _model(model_dir)
    cfg = EstimatorConfig(contact=_contact(at, model))
    atlas = load_or_build(model, cfg, None, cache_dir=model_dir, max_build_s=0.0)
    c = atlas.config
    further = (np.array(c.further_min_kPa) * 1e3, np.array(c.further_max_kPa) * 1e3)  # a stack's pressures
    L = held_out_loads(np.r_[c.lower, further[0]], np.r_[c.upper, further[1]], loads, seed)
    local = workers == 0 and scheduler is None
    with (nullcontext() if local else dask_client(scheduler, workers)) as client:
        with status(f"{loads} held-out full solves", console) if local else nullcontext():
            res = check_held_out(model, cfg, atlas, L, seed=seed, client=client)
    w, p = res.worst(), res.p90()
    n = len(res.loads)
    console.print(f"{n} held-out loads ({res.skipped} outside the solved cells, {len(res.failed)} unsolved): "
                  f"worst (90th percentile)", highlight=False)
    units = {"dV_mm3": "mm³", "points_mm": "mm", "force_N": "N", "pos_mm": "mm", "ang_deg": "deg"}
    what = {"dV_mm3": "map: arm volumes", "points_mm": "map: tracked points", "force_N": "inverse: force",
            "pos_mm": "inverse: pose position", "ang_deg": "inverse: pose angle"}
    for k, u in units.items():
        console.print(f"  {what[k]:24s} {w[k]:.4f} ({p[k]:.4f}) {u}", highlight=False)
    for t in res.target_names:
        console.print(f"  {'inverse: ' + t:24s} {w[t + '_mm']:.4f} mm", highlight=False)
    for f in res.failed:
        print_error(f"unsolved: {f}")
    missed = res.missed({"force_N": max_force_N, "pos_mm": max_pos_mm, "ang_deg": max_ang_deg,
                         "near_urethra_mm": max_near_urethra_mm})
    if missed or res.failed or not n:
        print_error("atlas check: " + ("; ".join(missed) if missed else "no load checked" if not n else
                                       f"{len(res.failed)} full solves failed"))
        raise typer.Exit(1)
    console.print("all goals met", highlight=False)
