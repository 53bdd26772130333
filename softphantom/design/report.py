"""The short Markdown report of a meshed design (design vs meshed volumes, counts, quality, time)."""

from __future__ import annotations

from softphantom.design.model import PhantomModel, model_summary


def design_report_md(model: PhantomModel) -> str:
    """Markdown report of ``model``: one table of volumes, then mesh figures.

    Volumes are in mm³ (the bulb row is the volume inside its outer surface, urethra included).
    """
    s = model_summary(model)
    d = model.design
    lines = [
        f"# Design `{d.name}`",
        "",
        "| region | design_mm3 | mesh_mm3 | error_percent |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name in ("bulb", *d.cavity_volumes_mm3()):
        des, mesh = s[f"{name}_design_mm3"], s[f"{name}_mesh_mm3"]
        lines.append(f"| {name} | {des:.1f} | {mesh:.1f} | {100.0 * (mesh / des - 1.0):+.2f} |")
    mp = d.mesh
    lines += [
        "",
        f"- nodes: {int(s['nodes'])}, tets: {int(s['tets'])} ({'10' if model.element_order == 2 else '4'}-node), "
        f"fixed nodes: {len(model.fixed_nodes)}",
        *([f"- rounded arm junctions: {s['junction_mesh_mm3']:.1f} mm³ of silicone outside the bulb's surface "
           "(the fillets and the arms' first millimetres, meshed with the bulb)"] if s["junction_mesh_mm3"] else []),
        f"- min dihedral angle: {s['min_dihedral_deg']:.1f} deg",
        f"- mesh sizes: bulb {mp.size_mm:.3g} mm, bulb surface {mp.surface_size_mm:.3g} mm, "
        f"arms {mp.arm_size_mm:.3g} mm, cavity walls {mp.cavity_segments:.3g} segments around",
        f"- meshing time: {model.mesh_seconds:.2f} s" if model.mesh_seconds else
        "- mesh: shipped with softphantom for this design (the same mesh, and atlas keys, whatever gmsh is installed)",
        "",
        "Files: `model.msh` (gmsh 2.2, physical groups), `model.vtu`, `design.toml`, `model.npz`, `mesh.png`.",
        "",
    ]
    return "\n".join(lines)
