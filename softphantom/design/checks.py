"""The checks across a design's parts (each part checks its own fields, design/parts.py): names
unique across arms and cavities, every part inside the body with a wall between them, the layers'
shell and lesions clear of the rest, every region with a material. A design that fails one raises
:class:`~softphantom.errors.DesignError` with one line naming the field.
"""

from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING

import numpy as np

from softphantom.design import geometry as geo
from softphantom.design.derived import _p_ext
from softphantom.design.parts import (
    CAVITY_TYPES,
    MATERIAL_PRESETS,
    MIN_ARMS,
    MIN_MARKER_SPREAD_MM,
    MIN_MARKERS,
    MIN_WALL_MM,
    RESERVED_NAMES,
    SURFACE_TOL_MM,
    ArmParams,
    BulbParams,
    _default_markers,
    _default_targets,
    _fmt,
    _set,
)
from softphantom.errors import DesignError

if TYPE_CHECKING:
    from softphantom.design.params import BIPDesign


def _validate_arm_names(names: tuple[str, ...]) -> None:
    if len(names) < MIN_ARMS:
        raise DesignError(f"arms: {len(names)} given ({', '.join(names) or 'none'}); a phantom needs at least "
                          f"{MIN_ARMS} sensing arms to see the three force components")
    for n in names:
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", n) or n in RESERVED_NAMES:
            raise DesignError(f"arms.{n}: an arm's name must start with a letter and hold letters, digits or _ "
                              f"(not {', '.join(RESERVED_NAMES)})")
        if names.count(n) > 1:
            raise DesignError(f"arms.{n}: two arms have this name")


def _validate_cavity_names(d: "BIPDesign") -> None:
    seen: set[str] = set()
    for c in d.cavities:
        if not isinstance(c, CAVITY_TYPES):
            raise DesignError(f"cavities: expected UrethraParams, CapsuleCavity or EllipsoidCavity, got {c!r}")
        n = c.name
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", n) or n in ("bulb", "shell"):
            raise DesignError(f"cavities.{n}: a cavity's name must start with a letter and hold letters, digits or _ "
                              "(not bulb, shell)")
        if n in seen:
            raise DesignError(f"cavities.{n}: two cavities have this name")
        if n in d.arm_names:
            raise DesignError(f"cavities.{n}: an arm has this name (arms.{n})")
        seen.add(n)


def _validate_materials(d: BIPDesign) -> None:
    names = [m.name for m in d.materials]
    for m in d.materials:
        if names.count(m.name) > 1:
            raise DesignError(f"materials.{m.name}: defined twice")
    known = set(d.region_names) | set(d.region_groups())
    rm = tuple((str(k), v) for k, v in (d.region_materials.items() if isinstance(d.region_materials, dict) else d.region_materials))
    _set(d, "region_materials", rm)
    presets = [MATERIAL_PRESETS[m] for _, m in rm if isinstance(m, str) and m not in names and m in MATERIAL_PRESETS]
    if presets:  # a preset named but not defined: written into the design, so its file is complete
        _set(d, "materials", tuple(d.materials) + tuple(dict.fromkeys(presets)))
        names = [m.name for m in d.materials]
    for region, mat in rm:
        if region not in known:
            raise DesignError(f"region_materials.{region}: not a region (known: {', '.join(sorted(known))})")
        if not isinstance(mat, str) or mat not in names:
            raise DesignError(f"region_materials.{region} = {mat!r}: no such material (defined: {', '.join(names)})")
    d.material_of_regions()


#: Least distance between an arm's end rim and the infill's surface (see _check_arm_ends_clear_of_infill).
ARM_END_CLEARANCE_MM = 1.5


def _check_arm_ends_clear_of_infill(d: BIPDesign, inner, t: float) -> None:
    """The rim of each arm's end face in the bulb must stay :data:`ARM_END_CLEARANCE_MM` off the
    infill's surface (on either side): where it grazes it, gmsh's boolean leaves a sliver it cannot
    mesh ("two facets intersect"). Measured on the default arms: the rim 1.13 mm off (4 mm shell)
    failed at a 6 mm mesh and passed at 10 mm, 0.14 mm off (5 mm) failed at 7–10 mm and passed at
    4 mm; 2.1 mm off (3 mm) passed at 6, 8 and 10 mm."""
    for g in d.arm_geometry():
        rim = geo.disk_rim_points(g.start_mm, g.direction, g.radius_mm, n=180)  # every 2°
        sd = geo.ellipsoid_signed_distance(rim, inner)  # > 0: the rim point lies in the shell
        for near in (float(sd.max()), float(sd.min())):
            if abs(near) < ARM_END_CLEARANCE_MM:
                raise DesignError(f"layers.shell_mm = {_fmt(t)}: the infill's surface passes {_fmt(abs(near))} mm from "
                                  f"the rim of arms.{g.name}'s end in the bulb (min {ARM_END_CLEARANCE_MM:g} mm: the "
                                  "mesher cannot resolve the sliver; a thinner or thicker shell, or another embed_mm)")


def _validate_layers(d: BIPDesign) -> None:
    """Shell and lesions: each lesion inside the infill and clear of the internal cavities, the arms
    and the other lesions by the minimum wall; the internal cavities inside the infill."""
    lay = d.layers
    if lay.is_default:
        return
    t = lay.shell_mm
    axes = d.bulb.semi_axes_mm
    if t > 0.0:
        if d.bulb.is_surface:
            body = f"a {d.bulb.shape}" if d.bulb.is_parametric else "an imported surface"
            raise DesignError(f"layers.shell_mm = {_fmt(t)}: a shell needs an ellipsoid bulb ({body} has no inner "
                              "offset yet; use 0)")
        if t > 0.5 * min(axes):
            raise DesignError(f"layers.shell_mm = {_fmt(t)} is more than half the bulb's smallest semi-axis "
                              f"({_fmt(min(axes))} mm)")
        inner = lay.infill_semi_axes_mm(axes)
        for u in d.cavities:
            wall = -float(geo.ellipsoid_signed_distance(u.surface_points(), inner).max())
            if wall < 0.0:
                raise DesignError(f"layers.shell_mm = {_fmt(t)}: the {u.name} cavity cuts {_fmt(-wall)} mm into the "
                                  f"shell (the infill must hold it; a thinner shell or a smaller {u.name})")
        _check_arm_ends_clear_of_infill(d, inner, t)

        def host(pts):
            return geo.ellipsoid_signed_distance(pts, inner)
        where = "infill"
    else:
        host = d.bulb.signed_distance
        where = "bulb"
    cav_pts = [(u, u.surface_points(spacing=0.8)) for u in d.cavities]
    arm_pts = {g.name: (geo.capsule_surface_points(g.start_mm, g.root_mm, g.radius_mm, spacing=0.8), g)
               for g in d.arm_geometry()}
    for k, les in enumerate(lay.lesions):
        p = f"layers.lesions.{les.name}"
        c, s = np.asarray(les.center_mm), les.semi_axes_mm
        pts = geo.ellipsoid_surface_points(c, s)
        inside = -float(host(pts).max())
        if inside < MIN_WALL_MM:
            how = (f"reaches {_fmt(-inside)} mm beyond the {where}'s surface" if inside < 0.0 else
                   f"comes {_fmt(inside)} mm from the {where}'s surface")
            raise DesignError(f"{p}.center_mm = {list(les.center_mm)}: the lesion {how} (min wall {MIN_WALL_MM:g} mm)")

        def gap(q, a, b, r):
            """Wall between the lesion and a capsule [a, b] of radius r (sampled both ways: one
            solid inside the other shows in either)."""
            return min(float(geo.ellipsoid_signed_distance(q - c, s).min()),
                       float((geo.segment_distance(pts, a, b) - r).min()))

        for u, q in cav_pts:
            g_u = min(float(geo.ellipsoid_signed_distance(q - c, s).min()), float(u.signed_distance(pts).min()))
            if g_u < MIN_WALL_MM:
                raise DesignError(f"{p}.center_mm = {list(les.center_mm)}: the lesion "
                                  f"{f'cuts the {u.name} cavity' if g_u < 0 else f'comes {_fmt(g_u)} mm from the {u.name} cavity'}"
                                  f" (min wall {MIN_WALL_MM:g} mm)")
        for name, (q, g) in arm_pts.items():
            g_a = gap(q, g.start_mm, g.root_mm, g.radius_mm)
            if g_a < MIN_WALL_MM:
                raise DesignError(f"{p}.center_mm = {list(les.center_mm)}: the lesion "
                                  f"{'cuts' if g_a < 0 else f'comes {_fmt(g_a)} mm from'} arms.{name}'s end in the bulb"
                                  f" (min wall {MIN_WALL_MM:g} mm)")
        for other in lay.lesions[k + 1:]:
            g_o = float(geo.ellipsoid_signed_distance(geo.ellipsoid_surface_points(other.center_mm, other.semi_axes_mm)
                                                      - c, s).min())
            if g_o < MIN_WALL_MM:
                raise DesignError(f"{p} and layers.lesions.{other.name}: "
                                  f"{'they overlap' if g_o < 0 else f'{_fmt(g_o)} mm apart'} (min wall {MIN_WALL_MM:g} mm)")


def _check_sizes(d: BIPDesign) -> None:
    """Closed-form bounds checked before any sampled geometry (whose cost grows with the sizes)."""
    axes = d.bulb.semi_axes_mm
    room = 4 * max(axes)  # twice the bulb's length: far out (the wall check below is the exact one)
    for u in d.cavities:
        if u.shape == "ellipsoid":
            if max(u.semi_axes_mm) > max(axes):
                raise DesignError(f"{u.path}.semi_axes_mm = {list(u.semi_axes_mm)} does not fit in the bulb (max "
                                  f"{_fmt(max(axes))} mm, its largest semi-axis)")
            continue
        if u.radius_mm > min(axes) - MIN_WALL_MM:
            raise DesignError(f"{u.path}.radius_mm = {_fmt(u.radius_mm)} does not fit in the bulb (max "
                              f"{_fmt(min(axes) - MIN_WALL_MM)} mm: smallest semi-axis less a wall)")
        if u.cyl_length_mm + 2 * u.radius_mm > room:
            vmax = geo.capsule_volume(u.radius_mm, max(0.0, room - 2 * u.radius_mm))
            raise DesignError(f"{u.path}.volume_mm3 = {_fmt(u.volume_mm3)} does not fit in the bulb: the capsule would "
                              f"be {_fmt(u.cyl_length_mm + 2 * u.radius_mm)} mm long, the bulb is "
                              f"{_fmt(2 * max(axes))} mm (at most {_fmt(vmax)} mm³)")
    for a in d.arms:
        if a.radius_mm > max(axes):
            raise DesignError(f"arms.{a.name}.radius_mm = {_fmt(a.radius_mm)} is wider than the bulb (max "
                              f"{_fmt(max(axes))} mm, its largest semi-axis)")


_GIVE_MARKERS = (f"markers: none given, and {{why}}: give [markers]: at least {MIN_MARKERS} points on your body's "
                 "surface, not coplanar, not under an arm (NAME = [x, y, z] mm; snap_to_surface = true moves "
                 "them onto the surface)")


def _check_arm_axis(arm: ArmParams, bulb: BulbParams) -> None:
    """An arm stands where its axis, from ``axis_point_mm`` (inside the body) along ``direction``,
    leaves the body. Refused before any other arm check: an axis point outside the body, or one
    just under the surface with ``direction`` pointing into the body (the arm would stand on the
    far side: the usual slip is a direction given from the arm towards the body)."""
    p = f"arms.{arm.name}"
    o = np.asarray(arm.axis_point_mm, float)
    where, dirn = (f"{key} = [{', '.join(_fmt(x) for x in v)}]"
                   for key, v in (("axis_point_mm", arm.axis_point_mm), ("direction", arm.direction)))
    sd = float(bulb.signed_distance([o])[0])
    if sd > -0.5:
        raise DesignError(
            f"{p}.{where} is {'outside the body' if sd > 0 else 'at the body surface'} ({_fmt(sd)} mm from it): an "
            f"arm's axis runs from axis_point_mm inside the body along direction, out through the surface where the "
            f"arm stands; give a point inside (default [0, 0, 0]) and a direction out of the body")
    d = geo.unit(arm.direction)
    ahead, behind = bulb.ray_exit(o, d), bulb.ray_exit(o, -d)
    if ahead is not None and behind is not None and behind < arm.embed_mm + arm.radius_mm and behind < ahead / 3:
        raise DesignError(
            f"{p}.{where} is {_fmt(behind)} mm under the surface behind it, and {dirn} takes the arm "
            f"{_fmt(ahead)} mm across the body to its far side: direction points from axis_point_mm out of the "
            "body, where the arm stands (reverse it to put the arm near axis_point_mm)")


def _validate_geometry(d: BIPDesign) -> None:
    """The parts placed together: cavities, arms, markers, targets and contact points on or in the
    body with a wall between them (the first problem raises, in that order)."""
    for arm in d.arms:
        if arm.junction_fillet_mm > 0.0 and d.bulb.is_surface:
            raise DesignError(f"arms.{arm.name}.junction_fillet_mm = {_fmt(arm.junction_fillet_mm)}: an imported "
                              "(triangulated) bulb cannot be filleted (OCC rounds smooth surfaces only); 0 there")
    _check_sizes(d)
    sdist = d.bulb.signed_distance
    cav_pts = _check_cavities(d, sdist)
    geoms = _check_arms(d, sdist, cav_pts)
    _check_markers(d, sdist, geoms)
    _check_targets(d, sdist)
    _p_ext(d.bulb, d.interaction)
    _check_contacts(d, sdist, geoms)


def _check_cavities(d: BIPDesign, sdist) -> list[np.ndarray]:
    """Each internal cavity wholly inside with a wall, its inlet on the surface, a wall from the
    others; returns the points sampled on their walls."""
    cav_pts = [c.surface_points() for c in d.cavities]
    for u, pts in zip(d.cavities, cav_pts):
        wall = -float(sdist(pts).max())
        if wall < MIN_WALL_MM:
            what = "radius_mm, volume_mm3, center_mm" if u.shape == "capsule" else "semi_axes_mm, center_mm"
            raise DesignError(
                f"{u.path}: wall to the bulb surface is {_fmt(wall)} mm (min {MIN_WALL_MM:g} mm; check {what})"
            )
        off = abs(float(sdist([u.inlet_mm])[0]))
        if off > SURFACE_TOL_MM:
            raise DesignError(f"{u.path}.inlet_mm is {_fmt(off)} mm off the bulb surface (tolerance "
                              f"{SURFACE_TOL_MM:g} mm; snap_to_surface = true moves it onto the surface)")
    for i, (ci, pi) in enumerate(zip(d.cavities, cav_pts)):
        for cj, pj in zip(d.cavities[i + 1:], cav_pts[i + 1:]):
            gap = min(float(ci.signed_distance(pj).min()), float(cj.signed_distance(pi).min()))
            if gap < MIN_WALL_MM:
                raise DesignError(f"{ci.path} and {cj.path}: "
                                  f"{'they overlap' if gap < 0 else f'{_fmt(gap)} mm apart'} (min wall {MIN_WALL_MM:g} mm)")
    return cav_pts


def _check_arms(d: BIPDesign, sdist, cav_pts) -> tuple:
    """Each arm rooted in the body, its end face and cavity a wall from it, clear of the cavities
    and of the other arms; returns the arms' geometry."""
    for arm in d.arms:
        _check_arm_axis(arm, d.bulb)
    geoms = d.arm_geometry()
    for arm, g in zip(d.arms, geoms):
        p = f"arms.{arm.name}"
        inner = sdist(geo.disk_rim_points(g.start_mm, g.direction, g.radius_mm))
        if inner.max() > -0.5:
            raise DesignError(
                f"{p}: the arm misses the bulb (its inner end is {_fmt(inner.max() + 0.5)} mm short of 0.5 mm "
                "inside; aim it at the bulb or raise embed_mm)"
            )
        outer = sdist(geo.disk_rim_points(g.end_mm, g.direction, g.radius_mm))
        if outer.min() < MIN_WALL_MM:
            raise DesignError(
                f"{p}.length_mm = {_fmt(arm.length_mm)}: the fixed end face comes {_fmt(outer.min())} mm from "
                f"the bulb (min {MIN_WALL_MM:g} mm)"
            )
        ca, cb = g.cavity_segment_mm
        cav = geo.capsule_surface_points(ca, cb, g.cavity_radius_mm)
        to_bulb = float(sdist(cav).min())
        if to_bulb < MIN_WALL_MM:
            where = f"comes {_fmt(to_bulb)} mm from" if to_bulb >= 0 else f"cuts {_fmt(-to_bulb)} mm into"
            raise DesignError(
                f"{p}.cavity_offset_mm = {_fmt(arm.cavity_offset_mm)}: the cavity {where} the bulb "
                f"(min wall {MIN_WALL_MM:g} mm)"
            )
        to_end = arm.length_mm - (arm.cavity_offset_mm + 0.5 * arm.cavity_cyl_length_mm + g.cavity_radius_mm)
        if to_end < MIN_WALL_MM:
            raise DesignError(
                f"{p}.cavity_offset_mm = {_fmt(arm.cavity_offset_mm)}: the cavity is {_fmt(to_end)} mm from "
                f"the fixed end face (min wall {MIN_WALL_MM:g} mm)"
            )
        for u, pts in zip(d.cavities, cav_pts):
            if u.shape == "capsule":
                ua, ub = u.segment_mm
                gap = geo.segment_segment_distance(g.start_mm, g.end_mm, ua, ub) - g.radius_mm - u.radius_mm
            else:  # sampled both ways: one solid inside the other shows in either
                arm_pts = geo.capsule_surface_points(g.start_mm, g.end_mm, g.radius_mm, spacing=0.8)
                gap = min(float(u.signed_distance(arm_pts).min()),
                          float((geo.segment_distance(pts, g.start_mm, g.end_mm) - g.radius_mm).min()))
            if gap < MIN_WALL_MM:
                raise DesignError(
                    f"{p}.embed_mm = {_fmt(arm.embed_mm)}: the arm comes {_fmt(gap)} mm from the {u.name} cavity "
                    f"(min wall {MIN_WALL_MM:g} mm)"
                )
    for i in range(len(geoms)):
        for j in range(i + 1, len(geoms)):
            gi, gj = geoms[i], geoms[j]
            dist = geo.segment_segment_distance(gi.root_mm, gi.end_mm, gj.root_mm, gj.end_mm)
            need = gi.radius_mm + gj.radius_mm + gi.fillet_mm + gj.fillet_mm + MIN_WALL_MM
            if dist < need:
                raise DesignError(
                    f"arms.{gi.name} and arms.{gj.name} overlap (axes {_fmt(dist)} mm apart, min {_fmt(need)} mm)"
                )
    return geoms


def _check_markers(d: BIPDesign, sdist, geoms) -> None:
    # the BIP's own markers and targets on another body: ask for the design's, not about the prostate's m1
    own_markers = d.markers != _default_markers()
    if len(d.markers) < MIN_MARKERS:
        raise DesignError(f"markers: {len(d.markers)} given (min {MIN_MARKERS}, non-coplanar)")
    for name, xyz in d.markers:
        off = abs(float(sdist([xyz])[0]))
        if off > SURFACE_TOL_MM:
            if not own_markers:
                raise DesignError(_GIVE_MARKERS.format(why=f"the default ones (the prostate's) are not on this body "
                                                           f"({name} is {_fmt(off)} mm off it)"))
            raise DesignError(f"markers.{name} is {_fmt(off)} mm off the bulb surface (tolerance {SURFACE_TOL_MM:g} mm; "
                              "snap_to_surface = true moves it onto the surface)")
        g = _arm_over(xyz, geoms)
        if g is not None:
            if not own_markers:
                raise DesignError(_GIVE_MARKERS.format(why=f"the default ones (the prostate's) do not fit this "
                                                           f"design ({name} lies under arms.{g.name})"))
            raise DesignError(f"markers.{name} lies under arms.{g.name} (min {MIN_WALL_MM:g} mm from its side)")
    m = np.array([xyz for _, xyz in d.markers])
    spread = float(np.linalg.svd(m - m.mean(axis=0), compute_uv=False)[-1] / math.sqrt(len(m)))
    if spread < MIN_MARKER_SPREAD_MM:
        raise DesignError(
            f"markers are coplanar (out-of-plane spread {_fmt(spread)} mm, min {MIN_MARKER_SPREAD_MM:g} mm)"
        )


def _check_targets(d: BIPDesign, sdist) -> None:
    own_targets = d.targets != _default_targets()
    for name, xyz in d.targets:
        sd = float(sdist([xyz])[0])
        # (where it is, what the user gives instead): the first place a target may not be
        wrong = [] if sd < 0.0 else [(f"is outside the bulb ({_fmt(sd)} mm beyond its surface)",
                                      f"is outside this body ({_fmt(sd)} mm beyond its surface)", "")]
        for u in d.cavities:
            inside = -float(u.signed_distance([xyz])[0])
            if inside >= 0.0:
                wrong.append((f"is inside the {u.name} cavity ({_fmt(inside)} mm from its wall)",
                              f"is inside the {u.name} cavity", ", outside its cavities"))
        if wrong and own_targets:
            raise DesignError(f"targets.{name} {wrong[0][0]}")
        if wrong:
            raise DesignError(f"targets: none given, and the default (the prostate's) {name} {wrong[0][1]}: give "
                              f"[targets], named points inside your body{wrong[0][2]} (NAME = [x, y, z] mm)")


def _check_contacts(d: BIPDesign, sdist, geoms) -> None:
    for name, xyz in d.contacts:
        off = abs(float(sdist([xyz])[0]))
        if off > SURFACE_TOL_MM:
            raise DesignError(f"contacts.{name} = {list(xyz)} is {_fmt(off)} mm off the bulb surface "
                              f"(tolerance {SURFACE_TOL_MM:g} mm; snap_to_surface = true moves it onto the surface)")
        g = _arm_over(xyz, geoms)
        if g is not None:
            raise DesignError(f"contacts.{name} lies under arms.{g.name} (min {MIN_WALL_MM:g} mm from its side)")


def _arm_over(xyz, geoms):
    """The first arm whose side (or fillet) comes within a wall of the surface point ``xyz``, else None."""
    return next((g for g in geoms
                 if geo.segment_distance([xyz], g.start_mm, g.end_mm)[0] < g.radius_mm + g.fillet_mm + MIN_WALL_MM),
                None)
