"""The geometry derived from a design's parts, mm: where each arm stands (:class:`ArmGeometry`,
from its axis and the body) and the interaction's contact points (``on-centre``, ``off-centre``).
:class:`~softphantom.design.params.BIPDesign` answers them through ``arm_geometry()`` and
``p_ext_mm()``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softphantom.design import geometry as geo
from softphantom.design.parts import ArmParams, BulbParams, InteractionParams, Vec3, _fmt
from softphantom.errors import DesignError


@dataclass(frozen=True)
class ArmGeometry:
    """Derived placement of one arm, mm (from :meth:`BIPDesign.arm_geometry`)."""

    name: str
    direction: np.ndarray  # unit, outward
    root_mm: np.ndarray  # where the axis leaves the bulb
    start_mm: np.ndarray  # inner end of the arm cylinder, inside the bulb
    end_mm: np.ndarray  # centre of the fixed end face (= tube inlet)
    radius_mm: float
    cavity_radius_mm: float
    cavity_segment_mm: tuple[np.ndarray, np.ndarray]  # capsule axis end points
    cavity_volume_mm3: float
    fillet_mm: float = 0.0  # ArmParams.junction_fillet_mm

    @property
    def tube_inlet_mm(self) -> np.ndarray:
        return self.end_mm


def _arm_geometry(arm: ArmParams, bulb: BulbParams) -> ArmGeometry:
    d = geo.unit(arm.direction)
    o = np.asarray(arm.axis_point_mm)
    s = bulb.ray_exit(o, d)
    if s is None:
        raise DesignError(f"arms.{arm.name}: the arm misses the body (its axis, from axis_point_mm along direction, does not meet it)")
    root = o + s * d
    c = root + arm.cavity_offset_mm * d
    h = 0.5 * arm.cavity_cyl_length_mm
    return ArmGeometry(
        name=arm.name,
        direction=d,
        root_mm=root,
        start_mm=root - arm.embed_mm * d,
        end_mm=root + arm.length_mm * d,
        radius_mm=arm.radius_mm,
        cavity_radius_mm=arm.cavity_radius_mm,
        cavity_segment_mm=(c - h * d, c + h * d),
        cavity_volume_mm3=arm.cavity_volume_mm3,
        fillet_mm=arm.junction_fillet_mm,
    )


def _front_point(axes: Vec3, t: float, angle: float) -> np.ndarray:
    a, b, c = axes
    x, z = t * math.cos(angle), t * math.sin(angle)
    q = max(0.0, 1.0 - (x / a) ** 2 - (z / c) ** 2)
    return np.array([x, -b * math.sqrt(q), z])


def _p_ext_surface(bulb: BulbParams, inter: InteractionParams) -> dict[str, np.ndarray]:
    """p_ext on a surface bulb: where lines along −y through (x, 0, z) leave its front."""
    ang = math.radians(inter.offcentre_angle_deg)
    y = np.array([0.0, -1.0, 0.0])

    def front(t: float) -> np.ndarray | None:
        o = np.array([t * math.cos(ang), 0.0, t * math.sin(ang)])
        s = bulb.ray_exit(o, y)
        return None if s is None else o + s * y

    on = front(0.0)
    if on is None:
        raise DesignError("interaction: the −y axis misses the bulb (no on-centre point)")
    lo, hi = 0.0, float(np.ptp(np.asarray(bulb.surface_vertices_mm), axis=0).max())
    for _ in range(60):  # the chord grows with t while the line still meets the front
        mid = 0.5 * (lo + hi)
        p = front(mid)
        if p is not None and np.linalg.norm(p - on) < inter.offcentre_mm:
            lo = mid
        else:
            hi = mid
    off = front(lo)
    if off is None or abs(np.linalg.norm(off - on) - inter.offcentre_mm) > 0.05:
        raise DesignError(f"interaction.offcentre_mm = {_fmt(inter.offcentre_mm)} is beyond the front of the bulb")
    return {"on-centre": on, "off-centre": off}


def _p_ext(bulb: BulbParams, inter: InteractionParams) -> dict[str, np.ndarray]:
    if bulb.is_surface:
        return _p_ext_surface(bulb, inter)
    axes = bulb.semi_axes_mm
    a, b, c = axes
    on = np.array([0.0, -b, 0.0])
    ang = math.radians(inter.offcentre_angle_deg)
    # largest in-plane offset that stays on the front half (q = 0)
    t_max = 1.0 / math.sqrt((math.cos(ang) / a) ** 2 + (math.sin(ang) / c) ** 2)
    if np.linalg.norm(_front_point(axes, t_max, ang) - on) < inter.offcentre_mm:
        raise DesignError(
            f"interaction.offcentre_mm = {_fmt(inter.offcentre_mm)} is beyond the front half of the bulb "
            f"(max {_fmt(float(np.linalg.norm(_front_point(axes, t_max, ang) - on)))} mm)"
        )
    lo, hi = 0.0, t_max  # chord length grows monotonically with t on the front half
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if np.linalg.norm(_front_point(axes, mid, ang) - on) < inter.offcentre_mm:
            lo = mid
        else:
            hi = mid
    return {"on-centre": on, "off-centre": _front_point(axes, 0.5 * (lo + hi), ang)}
