"""``softphantom design``: mesh a BIP design and write the model, a report and a PNG view."""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path
from typing import Optional

import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import (Force, MeshSizeMm, Out, Overwrite, Png, check_choice, check_positive,
                                     staged_output)
from softphantom.errors import UserError
from softphantom.progress import status


def _labels(text: str, option: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UserError(f"{option}: expected integers separated by commas, got {text!r}") from None


OBSERVE = ("auto", "envelope", "rest", "off")


def _observability(model, shipped: Path | None, observe: str, force: bool):
    """(the model's :class:`~softphantom.estimation.observability.Observability` or None, warnings):
    at rest (and over the envelope with ``observe == "envelope"``); a shipped model's at rest is
    read from its directory ``shipped``, not solved. A layout that cannot see a load is refused
    unless ``force``."""
    from softphantom.estimation import ForwardModel
    from softphantom.estimation.observability import (check_layout, observability, observability_at_rest,
                                                      shipped_rest_W)

    W = shipped_rest_W(shipped) if shipped is not None and observe == "rest" else None
    if W is not None:
        obs = observability_at_rest(model, W)
        check_layout(obs, force=force)
        return obs, []
    where = "at rest" + (" and over the load envelope" if observe == "envelope" else "")
    with status(f"solving the observability {where}", console):
        try:
            fm = ForwardModel(model)
        except UserError as exc:  # e.g. a marker off a mesh kept with --force: not solvable
            if not force:
                raise
            return None, [f"observability not checked: {exc}"]
        check_layout(observability(model, fm, loaded=False), force=force)  # refused: nothing written
        return observability(model, fm, loaded=observe == "envelope"), []


@app.command("design")
def design_command(
    out: Out = ...,
    config: Optional[Path] = typer.Option(None, "--config", help="Design file (.toml or .json); default: the "
                                          "default design, quadratic, shipped meshed (its atlas too)."),
    mesh_size_mm: MeshSizeMm = None,
    element_order: Optional[int] = typer.Option(None, "--element-order", help="1 (4-node tets: fast, about half "
                                                "the yaw) or 2 (10-node tets); default: the design's."),
    png: Png = True,
    force: Force = False,
    observe: str = typer.Option("auto", "--observability",
                                help="How well the arm volumes see the loads (docs/estimation.md): 'envelope' solves the model "
                                "at rest and at 8 loads over the load envelope, 'rest' at rest only, 'off' not at all; "
                                "'auto': envelope for 4-node tets, rest for 10-node ones (a loaded solve of the "
                                "quadratic default costs about 25 CPU-s). A rank-deficient arm layout is refused."),
    anatomy: Optional[Path] = typer.Option(
        None, "--anatomy", help="Prostate label map (.nii/.nii.gz) or closed surface (.stl/.obj): the bulb's shape."
    ),
    gland_labels: str = typer.Option("", "--gland-labels", help="Labels whose union is the gland, comma-separated "
                                     "(e.g. 1,2: peripheral and transition zone); default every non-zero label."),
    urethra_label: Optional[int] = typer.Option(
        None, "--urethra-label", help="Label of the urethra in a label map (0: none); default 2, or none when "
        "--gland-labels names 2."),
    urethra: str = typer.Option("auto", "--urethra", help="auto: the urethra label's voxels, or without any a "
                                "urethra along the gland's principal axis through its centroid; none: no urethra "
                                "cavity (the template's dropped; its other cavities kept)."),
    surface_size_mm: float = typer.Option(3.0, "--surface-size-mm", help="Triangle size of the imported surface, mm."),
    lesion_labels: str = typer.Option("", "--lesion-labels", help="Labels of lesions in a label map, comma-separated "
                                      "(e.g. 3,4): each becomes [layers.lesions.labelN], the ellipsoid of its voxels."),
    overwrite: Overwrite = False,
) -> None:
    """Build the BIP design, mesh it (gmsh), check its observability and write model.msh/.vtu/.npz, design.toml,
    report.md, mesh.png into the new directory --out."""
    from softphantom.design import build_model, default_design, load_design, save_model
    from softphantom.design.model import shipped_model_dir
    from softphantom.design.report import design_report_md

    lesions = _labels(lesion_labels, "--lesion-labels")
    gland = _labels(gland_labels, "--gland-labels")
    check_choice(observe, OBSERVE, "--observability")
    check_positive(surface_size_mm, "--surface-size-mm", "mm")
    no_urethra = check_choice(urethra, ("auto", "none"), "--urethra") == "none"
    if no_urethra and anatomy is None:
        raise UserError("--urethra none: only with --anatomy (a design file without a urethra says so: "
                        "[cavities] without [urethra])")
    if urethra_label is not None and urethra_label < 0:
        raise UserError(f"--urethra-label: must be >= 0 (0: none), got {urethra_label}")
    if urethra_label is not None and urethra_label > 0 and urethra_label in gland:
        raise UserError(f"--urethra-label {urethra_label} is one of --gland-labels {gland_labels} (0: no urethra label)")
    if urethra_label is None:
        urethra_label = 0 if 2 in gland or no_urethra else 2
    for option, given in (("--lesion-labels", lesions), ("--gland-labels", gland)):
        if given and anatomy is None:
            raise UserError(f"{option}: only with --anatomy (labels of a label map)")
    if element_order is not None and element_order not in (1, 2):
        raise UserError(f"--element-order: 1 or 2, got {element_order}")
    design = load_design(config) if config is not None else default_design()
    if element_order is not None and element_order != design.mesh.element_order:
        design = dataclasses.replace(design, mesh=dataclasses.replace(design.mesh, element_order=element_order))
    if anatomy is not None:
        from softphantom.design.anatomy import AnatomyOptions, design_from_anatomy, load_anatomy

        with status(f"importing the anatomy {anatomy}", console):
            imported = load_anatomy(anatomy, AnatomyOptions(gland_labels=gland, urethra_label=urethra_label,
                                                            surface_size_mm=surface_size_mm, lesion_labels=lesions))
            template = design
            design = design_from_anatomy(imported, template, name=f"{design.name}_anatomy", urethra=not no_urethra)
        vox = "" if imported.voxel_volume_mm3 is None else (
            f" (label voxel count {imported.voxel_volume_mm3:.0f} mm³, "
            f"{100 * (imported.volume_mm3 / imported.voxel_volume_mm3 - 1):+.2f} %)")
        console.print(f"anatomy: bulb surface {len(imported.faces)} triangles, {imported.volume_mm3:.0f} mm³{vox}",
                      highlight=False)
        from softphantom.design.anatomy import import_report

        for line in import_report(imported, template, design):
            console.print(line, highlight=False, markup=False)
    from softphantom.fem.model import laws_of_design

    laws_of_design(design, design.region_names)  # an unknown law or a bad parameter fails here (exit 2)
    t0 = time.perf_counter()
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        with status(f"meshing design '{design.name}'", console):
            model = build_model(design, mesh_size_mm, force=force)
        report = design_report_md(model)
        shipped = shipped_model_dir(design)  # the shipped model's mesh: its observability and drawing ship with it
        warnings: list[str] = []
        if observe == "auto":
            observe = "envelope" if model.element_order == 1 else "rest"
        if observe != "off":
            from softphantom.estimation.observability import check_layout, observability_md

            obs, warnings = _observability(model, shipped, observe, force)
            if obs is not None:
                warnings = check_layout(obs, force=True)
                report += "\n" + observability_md(obs)
            report += "".join(f"- warning: {w}\n" for w in warnings)
        save_model(model, work)
        (work / "report.md").write_text(report, encoding="utf-8")
        if png:
            from softphantom.viz.mesh_view import render_mesh_png

            if shipped is not None and (shipped / "mesh.png").is_file():  # the shipped mesh's, drawn once
                shutil.copyfile(shipped / "mesh.png", work / "mesh.png")
            else:
                with status("drawing mesh.png", console):
                    render_mesh_png(model, work / "mesh.png")
    console.print(report, highlight=False, soft_wrap=True)
    for line in warnings:
        console.print(f"warning: {line}", style="yellow", markup=False, highlight=False)
    console.print(f"wrote {out}/ in {time.perf_counter() - t0:.1f} s", highlight=False)
