"""A patient's prostate as the bulb of a design: the gland imported from a label map or a surface
(:func:`load_anatomy`, design/anatomy_import.py) made into a design of a template
(:func:`design_from_anatomy`).

The urethra (label) becomes the design's capsule: centroid, principal axis, length along it,
volume from the voxel count, radius from length and volume; without urethra voxels (or from a
surface) it lies along the principal axis the placement turned to y (the one nearest the
template's urethra axis) through the centroid (:func:`axis_urethra`). Its inlet is where its axis
leaves the bulb towards the base. The template's arms (lengths, radius, embedding, cavity offset)
and urethra radius are scaled by the cube root of the gland's volume over the template's
(:func:`part_scale`; cavity volumes by its cube; walls kept at the design's minimum or more), the
arms keep the design's directions and attach where those leave the new surface; markers are
re-projected along their directions; targets are scaled with the gland's extent. A part that
cannot be made valid is one line naming it and what fixes it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from softphantom.design import geometry as geo
from softphantom.design.anatomy_import import (  # the import, re-exported
    MAX_URETHRA_SHARE, RAS_TO_MODEL, Anatomy, AnatomyOptions, _check_surface, anatomy_from_labels,
    anatomy_from_surface, lesion_name, lesion_report, load_anatomy)
from softphantom.design.derived import _arm_geometry
from softphantom.design.params import MIN_WALL_MM, ArmParams, BIPDesign, BulbParams, UrethraParams
from softphantom.errors import DesignError

__all__ = ["MAX_URETHRA_SHARE", "RAS_TO_MODEL", "Anatomy", "AnatomyOptions", "anatomy_from_labels",
           "anatomy_from_surface", "axis_urethra", "design_from_anatomy", "import_report", "lesion_name",
           "lesion_report", "load_anatomy", "part_scale"]


def import_report(anatomy: "Anatomy", template: BIPDesign, design: BIPDesign) -> list[str]:
    """What the import made of the template: the parts' scale, where the urethra came from, then
    :func:`lesion_report`'s lines."""
    u = design.urethra
    where = ("fitted to its label's voxels" if anatomy.urethra is not None else
             "not labelled, placed along the gland's principal axis through its centroid")
    head = f"parts: the template's arms{' and urethra radius' if u is not None else ''} scaled by " \
           f"{part_scale(anatomy, template):.3f} (the cube root of {anatomy.volume_mm3 / 1e3:.1f} mL over the " \
           f"template's {template.bulb.volume_mm3 / 1e3:.1f} mL)"
    if u is None:
        return [head, "urethra: none (--urethra none)", *lesion_report(anatomy)]
    return [head,
            f"urethra: {where}; radius {u.radius_mm:.2f} mm, length {u.cyl_length_mm + 2 * u.radius_mm:.1f} mm, "
            f"{u.volume_mm3:.0f} mm³, inlet ({', '.join(f'{x:.1f}' for x in u.inlet_mm)}) mm",
            *lesion_report(anatomy)]


def _project(bulb: BulbParams, name: str, direction, table: str = "markers") -> tuple[float, float, float]:
    s = bulb.ray_exit((0.0, 0.0, 0.0), direction)
    if s is None:
        raise DesignError(f"{table}.{name}: the direction {tuple(direction)} misses the gland")
    p = s * np.asarray(direction, float) / np.linalg.norm(direction)
    return tuple(float(x) for x in p)  # type: ignore[return-value]


def part_scale(anatomy: Anatomy, base: BIPDesign) -> float:
    """The factor on the template's lengths: the cube root of the gland's volume over the
    template bulb's (0.776 for a 47 mL gland against the paper's 100.41 mL)."""
    return float((anatomy.volume_mm3 / base.bulb.volume_mm3) ** (1.0 / 3.0))


def _scaled_cavity(cavity, s: float, scale: np.ndarray, bulb: BulbParams):
    """A template's internal cavity other than the urethra in the gland: its centre scaled with the
    gland's extent (as the targets), its size by ``s`` (volume by s³), its inlet projected onto the
    gland along its direction from the centre (as the markers)."""
    kw = {"center_mm": tuple(float(x) for x in np.asarray(cavity.center_mm) * scale),
          "inlet_mm": _project(bulb, cavity.name, cavity.inlet_mm, "cavities")}
    if cavity.shape == "ellipsoid":
        kw["semi_axes_mm"] = tuple(float(x) * s for x in cavity.semi_axes_mm)
    else:
        kw.update(radius_mm=cavity.radius_mm * s, volume_mm3=cavity.volume_mm3 * s**3)
    return dataclasses.replace(cavity, **kw)


def _scaled_arm(arm: ArmParams, s: float) -> ArmParams:
    """``arm`` with its lengths times ``s`` and its cavity volume times s³, its wall kept at the
    design's minimum or more; sharp junction (OCC rounds smooth surfaces only, not a triangulated
    gland's)."""
    return dataclasses.replace(
        arm, length_mm=arm.length_mm * s, radius_mm=arm.radius_mm * s, wall_mm=max(arm.wall_mm * s, MIN_WALL_MM),
        cavity_offset_mm=arm.cavity_offset_mm * s, embed_mm=arm.embed_mm * s,
        axis_point_mm=tuple(float(x) * s for x in arm.axis_point_mm), cavity_volume_mm3=arm.cavity_volume_mm3 * s**3,
        junction_fillet_mm=0.0)


def _chord(bulb: BulbParams, point, axis) -> tuple[float, float]:
    """(backward, forward) distances from ``point`` to where the line along ``axis`` leaves ``bulb``."""
    fwd, back = bulb.ray_exit(point, axis), bulb.ray_exit(point, -np.asarray(axis, float))
    if fwd is None or back is None or fwd <= 0.0 or back <= 0.0:
        raise DesignError(f"urethra: the line along {tuple(np.round(axis, 3))} through "
                          f"{tuple(np.round(point, 1))} mm does not cross the gland")
    return float(back), float(fwd)


def axis_urethra(bulb: BulbParams, template: BIPDesign, s: float) -> UrethraParams:
    """A urethra for a gland without a urethra label: along the model's y (the principal axis
    the placement turned there, the one nearest the template's +y) through the gland's centroid
    (the origin), centred on the chord it cuts; radius the template's times ``s``, total length the
    same fraction of that chord as the template's of its own (0.72 for the paper's BIP); the inlet
    where the axis leaves the gland at +y.

    >>> u = axis_urethra(BIPDesign().bulb, BIPDesign(), 1.0)  # the template itself: its radius, on y
    >>> u.radius_mm, u.axis, [round(x, 6) for x in u.center_mm]
    (4.5, (0.0, 1.0, 0.0), [0.0, 0.0, 0.0])
    """
    t = template.urethra
    ta, tb = t.segment_mm
    tback, tfwd = _chord(template.bulb, np.asarray(t.center_mm, float), geo.unit(t.axis))
    frac = (float(np.linalg.norm(tb - ta)) + 2.0 * t.radius_mm) / (tback + tfwd)
    axis = np.array([0.0, 1.0, 0.0])
    back, fwd = _chord(bulb, np.zeros(3), axis)
    r = t.radius_mm * s
    length = max(frac * (back + fwd), 2.0 * r + 1e-3)  # no shorter than its sphere
    c = 0.5 * (fwd - back) * axis
    return UrethraParams(radius_mm=r, volume_mm3=geo.capsule_volume(r, length - 2.0 * r),
                         center_mm=tuple(float(x) for x in c), axis=tuple(float(x) for x in axis),
                         inlet_mm=tuple(float(x) for x in c + bulb.ray_exit(c, axis) * axis))


def _fitted_urethra(bulb: BulbParams, u: dict) -> UrethraParams:
    c, axis = np.asarray(u["center_mm"]), np.asarray(u["axis"])
    s = bulb.ray_exit(c, axis)
    if s is None:
        raise DesignError("urethra: the urethra label's axis does not leave the gland")
    return UrethraParams(radius_mm=float(u["radius_mm"]), volume_mm3=float(u["volume_mm3"]),
                         center_mm=tuple(float(x) for x in c), axis=tuple(float(x) for x in axis),
                         inlet_mm=tuple(float(x) for x in c + s * axis))


#: what fixes a part the import could not make valid, by the part its message starts with
_FIXES = {
    "urethra": "a smaller [urethra] radius_mm in --config (the principal-axis urethra's, before the scaling), "
               "or a urethra label (--urethra-label)",
    "arms": "[arms.{name}] radius_mm, embed_mm or direction in --config (before the scaling)",
    "markers": "[markers] in --config (points whose directions from the centre miss the arms)",
    "contacts": "[contacts] in --config (points whose directions from the centre miss the arms)",
    "cavities": "[cavities.{name}] center_mm or size in --config (before the scaling)",
    "targets": "[targets] in --config",
    "interaction": "[interaction] offcentre_mm in --config",
    "layers": "--lesion-labels without that label",
}


def design_from_anatomy(anatomy: Anatomy, base: BIPDesign | None = None, name: str = "anatomy", *,
                        urethra: bool = True) -> BIPDesign:
    """``base`` (default: the paper's BIP) with the gland's surface and urethra (its label's fit,
    else :func:`axis_urethra`; ``urethra=False``: none, the template's dropped too, and a urethra
    label is refused); the arms and urethra radius scaled by :func:`part_scale`, markers
    and named contacts projected along their directions, targets and the other internal cavities'
    centres scaled with the gland's extent (the cavities' sizes by the part scale). A part that still
    cannot be made valid raises a one-line DesignError naming it and the option that fixes it."""
    base = base or BIPDesign()
    if not urethra and anatomy.urethra is not None:
        raise DesignError("urethra: the label map has a urethra label and --urethra none drops it "
                          "(--urethra-label 0 to import no urethra label)")
    s = part_scale(anatomy, base)
    try:
        return _design_from_anatomy(anatomy, base, name, s, urethra)
    except DesignError as exc:
        msg = str(exc)
        path = msg.split(":", 1)[0].split(" ", 1)[0].split(".")
        fix = _FIXES.get(path[0])
        if fix is None:
            raise
        fix = fix.format(name=path[1] if len(path) > 1 else "NAME")
        raise DesignError(f"{msg} [a {anatomy.volume_mm3 / 1e3:.1f} mL gland, the template's parts scaled by "
                          f"{s:.3f}; fix: {fix}]") from None


def _design_from_anatomy(anatomy: Anatomy, base: BIPDesign, name: str, s: float, with_urethra: bool) -> BIPDesign:
    v = anatomy.vertices_mm
    half = 0.5 * (v.max(axis=0) - v.min(axis=0))
    bulb = BulbParams(semi_axes_mm=tuple(float(x) for x in half),
                      surface_vertices_mm=tuple(tuple(float(x) for x in p) for p in v),
                      surface_faces=tuple(tuple(int(k) for k in f) for f in anatomy.faces))
    urethra = (None if not with_urethra else axis_urethra(bulb, base, s) if anatomy.urethra is None
               else _fitted_urethra(bulb, anatomy.urethra))
    markers = tuple((k, _project(bulb, k, p)) for k, p in base.markers)
    scale = half / np.asarray(base.bulb.semi_axes_mm)
    targets = []
    for k, p in base.targets:
        q = np.asarray(p) * scale
        if urethra is None:
            targets.append((k, tuple(float(x) for x in q)))
            continue
        # a target that the new urethra swallowed moves out radially to 3 mm from its wall
        ua, ub = urethra.segment_mm
        t = np.clip((q - ua) @ (ub - ua) / max(float((ub - ua) @ (ub - ua)), 1e-12), 0.0, 1.0)
        foot = ua + t * (ub - ua)
        if np.linalg.norm(q - foot) < urethra.radius_mm + 3.0:
            radial = q - foot
            if np.linalg.norm(radial) < 1e-9:
                radial = np.cross(ub - ua, (0.0, 0.0, 1.0)) if abs((ub - ua)[2]) < 0.9 * np.linalg.norm(ub - ua) else \
                    np.array([1.0, 0.0, 0.0])
            q = foot + (urethra.radius_mm + 3.0) * radial / np.linalg.norm(radial)
        targets.append((k, tuple(float(x) for x in q)))
    arms = tuple(_scaled_arm(a, s) if urethra is None else _arm_clear_of_urethra(_scaled_arm(a, s), bulb, urethra)
                 for a in base.arms)
    contacts = tuple((k, _project(bulb, k, p, "contacts")) for k, p in base.contacts)
    others = tuple(_scaled_cavity(c, s, scale, bulb) for c in base.cavities if c.name != "urethra")
    out = dataclasses.replace(base, name=name, bulb=bulb, arms=arms, markers=markers, contacts=contacts,
                              cavities=(*(() if urethra is None else (urethra,)), *others), targets=tuple(targets))
    if anatomy.lesions:  # each lesion label becomes a lesion region, in the bulb's material unless set
        from softphantom.design.params import LayersParams, LesionParams

        new = tuple(LesionParams(lesion_name(lab), tuple(float(x) for x in les["center_mm"]),
                                 tuple(float(x) for x in les["semi_axes_mm"]))
                    for lab, les in sorted(anatomy.lesions.items()))
        rm = dict(base.region_materials)
        rm.setdefault("lesions", rm.get("bulb", base.material_of_regions(["bulb"])["bulb"]))
        out = dataclasses.replace(out, layers=LayersParams(shell_mm=base.layers.shell_mm,
                                                           lesions=(*base.layers.lesions, *new)),
                                  region_materials=tuple(rm.items()))
    return dataclasses.replace(out, bulb=_clear_of_arm_cuts(out))


def _clear_of_arm_cuts(design: BIPDesign, frac: float = 0.3):
    """The bulb with each surface vertex that lies within ``frac`` × the median edge of an arm's
    cylinder moved radially to that distance from it (inward or outward, whichever side it is on).
    The cylinder then never cuts a facet next to a vertex, where OCC left edges of a few µm that
    became slivers or degenerate tets (min dihedral 0.04–0.2° on a 6 mm surface at a 12 mm mesh,
    or a 'segment and a facet intersect' failure at 4 mm; 1.9–6.5° with the band, 0 failures)."""
    bulb = design.bulb
    v = np.asarray(bulb.surface_vertices_mm, float).copy()
    f = np.asarray(bulb.surface_faces)
    eps = frac * float(np.median(np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)))
    for g in design.arm_geometry():
        axis = (g.end_mm - g.start_mm) / np.linalg.norm(g.end_mm - g.start_mm)
        rel = v - g.start_mm
        along = rel @ axis
        radial = rel - along[:, None] * axis
        dist = np.linalg.norm(radial, axis=1)
        band = (np.abs(dist - g.radius_mm) < eps) & (along > 0.0) & (dist > 0.0)
        target = np.where(dist[band] < g.radius_mm, g.radius_mm - eps, g.radius_mm + eps)
        v[band] += radial[band] * (target / dist[band] - 1.0)[:, None]
    import trimesh

    _check_surface(trimesh.Trimesh(v, f, process=False), "anatomy (vertices moved off the arms' cylinders)")
    return dataclasses.replace(bulb, surface_vertices_mm=tuple(tuple(float(x) for x in p) for p in v))


def _arm_clear_of_urethra(arm, bulb: BulbParams, urethra: UrethraParams, margin_mm: float = 0.5):
    """``arm`` with its embedding shortened, if needed, so that it keeps the design's minimum wall
    (plus ``margin_mm``) to a fitted urethra, which may lie closer to the surface than the default."""
    ua, ub = urethra.segment_mm

    def gap(embed: float) -> float:
        g = _arm_geometry(dataclasses.replace(arm, embed_mm=embed), bulb)
        return geo.segment_segment_distance(g.start_mm, g.end_mm, ua, ub) - g.radius_mm - urethra.radius_mm

    need = MIN_WALL_MM + margin_mm
    if gap(arm.embed_mm) >= need:
        return arm
    lo, hi = min(3.0, arm.embed_mm), arm.embed_mm  # the arm still reaches 3 mm into the gland
    if gap(lo) < need:
        return arm  # validation names the problem
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(mid) >= need else (lo, mid)
    return dataclasses.replace(arm, embed_mm=round(lo, 3))
