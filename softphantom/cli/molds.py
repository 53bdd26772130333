"""``softphantom molds``: the printable molds, cores and frame of a design, with its BOM."""

from __future__ import annotations

import time

from softphantom.cli.app import app, console
from softphantom.cli.options import ModelDir, Out, Overwrite, Png, staged_output


@app.command("molds")
def molds_command(
    model: ModelDir = ...,
    out: Out = ...,
    png: Png = True,
    overwrite: Overwrite = False,
) -> None:
    """Build the molds ([molds] table of the --model's design.toml), check each part and write STL/3MF,
    bom.csv/.md, parts.csv and assembly.png into the new directory --out."""
    from softphantom.design.params import load_design
    from softphantom.errors import FileFormatError
    from softphantom.molds import build_parts, write_molds
    from softphantom.molds.bom import material_totals, to_markdown

    toml = model / "design.toml"
    if not toml.is_file():
        raise FileFormatError(f"{toml}: no such file (expected a directory written by `softphantom design`)")
    design = load_design(toml)
    t0 = time.perf_counter()
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        with console.status(f"building the parts of design '{design.name}' …"):
            parts = build_parts(design)
        with console.status("checking and writing the parts …"):
            result = write_molds(parts, work)
        if png:
            from softphantom.viz.molds_view import render_assembly_png

            render_assembly_png(parts, work / "assembly.png")
    console.print(to_markdown(material_totals(result.silicone)), markup=False, highlight=False)
    n = len(result.printed)
    console.print(f"{n} printed parts, all closed and manifold; wrote {out}/ in {time.perf_counter() - t0:.1f} s",
                  highlight=False)
