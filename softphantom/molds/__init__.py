"""Molds stage (after design): the printable parts that cast a design, their checks and the BOM.

``build_parts(design)`` builds every solid with gmsh's OpenCASCADE kernel (molds/parts.py);
``write_molds(parts, out)`` checks each one (closed, manifold, not self-intersecting, fits the
build volume; design/solid_check.py) and writes STL and 3MF files in the print pose, the bill of
materials (CSV and markdown) and a parts list. See docs/fabrication.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.design.fabrication import BUILD_VOLUME_MM
from softphantom.errors import MeshError
from softphantom.molds.bom import material_totals, part_rows, silicone_rows, to_csv, to_markdown
from softphantom.design.solid_check import MeshReport, manifold_volume, report_mesh, to_manifold
from softphantom.molds.parts import Part, build_parts

__all__ = ["Part", "MoldSet", "build_parts", "check_parts", "write_molds", "assembly_groups", "interference"]


@dataclass(frozen=True)
class MoldSet:
    """What ``write_molds`` wrote: the parts, their check reports and the BOM rows."""

    parts: tuple[Part, ...]
    reports: dict[str, MeshReport]
    silicone: list[dict]
    printed: list[dict]


def _one_solid_with_voids(mesh, r: MeshReport) -> bool:
    """A cast piece poured around inclusions (the infill around its lesions): one outer shell and
    inner shells of negative volume, otherwise clean."""
    if not (r.watertight and r.winding_consistent and r.manifold and r.self_intersections == 0 and r.volume > 0):
        return False
    vols = sorted((s.volume for s in mesh.split(only_watertight=False)), reverse=True)
    return vols[0] > 0.0 and all(v < 0.0 for v in vols[1:])


def check_parts(parts) -> dict[str, MeshReport]:
    """Check every part; MeshError naming the first part that is not a clean closed solid."""
    reports = {}
    for p in parts:
        r = report_mesh(p.mesh)
        if r.problem() is not None and not (p.kind == "cast" and _one_solid_with_voids(p.mesh, r)):
            raise MeshError(f"part {p.name}: {r.problem()}")
        reports[p.name] = r
    return reports


def assembly_groups(parts) -> dict[str, list[Part]]:
    """Parts that are assembled together (a mold with its cores and inserts; the phantom in its frame)."""
    groups: dict[str, list[Part]] = {}
    for p in parts:
        groups.setdefault(p.group, []).append(p)
    # an arm core sits in its arm mold and is the part its core mold casts
    for name in [g for g in groups if g.startswith("core_")]:
        core = next(p for p in groups[f"arm_{name[5:]}"] if p.kind == "core")
        groups[name].append(core)
    return groups


def interference(parts) -> list[tuple[str, str, float]]:
    """(a, b, mm³) for every pair of parts assembled together (should all be ≈ 0)."""
    out = []
    solids: dict = {}  # each part converted once: it is in several pairs
    for members in assembly_groups(parts).values():
        for p in members:
            if p.name not in solids:
                solids[p.name] = to_manifold(p.mesh)
        for i in range(len(members)):
            for j in range(i + 1, len(members)):
                a, b = members[i].name, members[j].name
                out.append((a, b, manifold_volume(solids[a] ^ solids[b])))
    return out


def write_molds(parts, out: str | Path, formats=("stl", "3mf")) -> MoldSet:
    """Check ``parts`` and write them (print pose, mm) with the BOM and parts list into ``out``."""
    out = Path(out)
    (out / "parts").mkdir(parents=True, exist_ok=True)
    (out / "cast").mkdir(parents=True, exist_ok=True)
    reports = check_parts(parts)
    for p in parts:
        if p.kind == "cast":  # reference shapes of the silicone pieces, in the model frame
            p.mesh.export(out / "cast" / f"{p.name}.stl")
            continue
        m = p.mesh.copy().apply_transform(p.print_transform())
        for fmt in formats:
            m.export(out / "parts" / f"{p.name}.{fmt}")
    silicone = silicone_rows(parts)
    printed = part_rows(parts, BUILD_VOLUME_MM)
    (out / "bom.csv").write_text(to_csv(silicone), encoding="utf-8")
    (out / "parts.csv").write_text(to_csv(printed), encoding="utf-8")
    md = ["# Bill of materials", "", "## Silicone per cast piece", "", to_markdown(silicone),
          "## Silicone per material", "", to_markdown(material_totals(silicone)),
          f"## Printed parts (print pose; build volume {' × '.join(f'{v:g}' for v in BUILD_VOLUME_MM)} mm)", "",
          to_markdown(printed)]
    (out / "bom.md").write_text("\n".join(md), encoding="utf-8")
    poses = {p.name: np.linalg.inv(p.print_transform()).round(9).tolist() for p in parts if p.kind != "cast"}
    (out / "assembly.json").write_text(json.dumps({"units": "mm", "print_to_model": poses}, indent=1) + "\n",
                                       encoding="utf-8")
    return MoldSet(tuple(parts), reports, silicone, printed)
