"""Bill of materials: silicone volume and mass per cast piece and per material, printed parts.

Densities are the manufacturers' specific gravities (Smooth-On technical bulletins: Ecoflex 00-50
1.07 g/cm³, Dragon Skin 30 1.08 g/cm³). Volumes are those of the cast solids themselves (the bulb
without its internal cavities' cores and marker sockets, each arm without its core), before any
pour margin.

>>> round(mass_g("Ecoflex 00-50", 100_000.0), 1)
107.0
"""

from __future__ import annotations

import csv
import io

CASTING_DENSITY_KG_M3: dict[str, float] = {"Ecoflex 00-50": 1070.0, "Dragon Skin 30": 1080.0,
                                           # as design.params.MATERIAL_PRESETS (not checked here)
                                           "Sorta-Clear 12": 1040.0, "Ecoflex GEL": 980.0}


def mass_g(material: str, volume_mm3: float) -> float:
    """Mass in grams of ``volume_mm3`` of a casting material."""
    return CASTING_DENSITY_KG_M3[material] * volume_mm3 * 1e-9 * 1e3


def silicone_rows(parts) -> list[dict]:
    """One row per cast silicone piece (bulb, arms, arm cores)."""
    rows = []
    for p in parts:
        if p.material in CASTING_DENSITY_KG_M3 and p.kind in ("cast", "core"):
            rows.append({
                "part": p.name,
                "material": p.material,
                "volume_mL": round(p.volume_mm3 / 1000.0, 3),
                "density_kg_m3": CASTING_DENSITY_KG_M3[p.material],
                "mass_g": round(mass_g(p.material, p.volume_mm3), 2),
            })
    return rows


def material_totals(rows: list[dict]) -> list[dict]:
    out: dict[str, dict] = {}
    for r in rows:
        t = out.setdefault(r["material"], {"material": r["material"], "volume_mL": 0.0, "mass_g": 0.0})
        t["volume_mL"] = round(t["volume_mL"] + r["volume_mL"], 3)
        t["mass_g"] = round(t["mass_g"] + r["mass_g"], 2)
    return list(out.values())


def part_rows(parts, build_volume_mm) -> list[dict]:
    """One row per printed part: material, volume and its size in the print pose."""
    rows = []
    for p in parts:
        if p.kind == "cast" or p.material in CASTING_DENSITY_KG_M3:
            continue
        ext = p.print_extents_mm()
        fits = bool(sorted(ext[:2]) <= sorted(build_volume_mm[:2]) and ext[2] <= build_volume_mm[2])
        rows.append({
            "part": p.name, "kind": p.kind, "group": p.group, "material": p.material,
            "volume_mL": round(p.volume_mm3 / 1000.0, 3),
            "x_mm": round(float(ext[0]), 1), "y_mm": round(float(ext[1]), 1), "z_mm": round(float(ext[2]), 1),
            "fits_build_volume": fits,
        })
    return rows


def to_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def to_markdown(rows: list[dict]) -> str:
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + " --- |" * len(keys)]
    lines += ["| " + " | ".join(str(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"
