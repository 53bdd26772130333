"""The parametric bio-inspired prostate phantom (BIP): a small validated parameter object.

Everything else (geometry, mesh, named points) is derived from a :class:`BIPDesign`. Lengths in
the parameters are millimetres and volumes mm³ (the unit is in every field name); the mesh and
the :class:`~softphantom.design.model.PhantomModel` convert to SI.

Geometry (frame of docs/architecture.md: origin at the bulb centre, y = needle direction, the
needle coming from −y, z up/anterior):

- **bulb**: an ellipsoid with semi-axes (x, y, z); the default 32.0 × 25.0 × 29.9639 mm has the
  paper's 100.41 mL exactly (c solved from the volume).
- **urethra**: a closed capsule (cylinder with hemispherical ends) of ``radius_mm`` whose
  cylinder length is derived from ``volume_mm3`` (2078 mm³), centred at ``center_mm`` (default
  4 mm anterior) along ``axis``; ``inlet_mm`` is where its tube leaves the bulb (a point on the
  surface; the channel itself is not meshed). Other internal cavities (``[cavities.NAME]``: a
  capsule like the urethra, or an ellipsoid balloon) join or replace it: M ≥ 0 of them,
  :attr:`BIPDesign.cavities` (docs/architecture.md, "Internal cavities"). Each is ``role =
  "actuated"`` (a known pressure load; the urethra always) or ``"measured"`` (a sealed cavity read
  as a volume channel, like an arm's).
- **arms**: by default the BIP's four cylinders ``front_zpos``, ``front_zneg`` (needle side,
  above/below, cavities of 514 mm³) and ``back_xpos``, ``back_xneg`` (+y, left/right, 486 mm³);
  any :data:`MIN_ARMS` or more, each named, in the sensor order (a design file lists them in
  ``arm_names`` when they are not the BIP's four). An arm's axis is the
  line through ``axis_point_mm`` along ``direction``; its *root* is where that line leaves the
  bulb. The arm cylinder starts ``embed_mm`` inside the bulb (so that it fuses with it without
  a gap) and ends ``length_mm`` beyond the root: that end disk is the fixed face clamped to the
  frame, and its centre is the tube inlet. The air cavity is a capsule of radius
  ``radius_mm − wall_mm`` whose cylinder length comes from ``cavity_volume_mm3``, centred
  ``cavity_offset_mm`` from the root along the axis.
- **interaction** (p_ext): ``on-centre`` is where the −y axis leaves the bulb, (0, −b, 0);
  ``off-centre`` is the point of the front surface at straight-line distance ``offcentre_mm``
  (10 mm) from it, in the direction ``offcentre_angle_deg`` measured in the x–z plane from +x
  towards +z (45°: diagonal, +x and +z). Further named **contacts** (``[contacts]``,
  ``NAME = [x, y, z]`` mm, on the surface, not under an arm) follow them.
- **markers**: tracker points on the bulb surface (≥ 4, non-coplanar, not under an arm);
  **targets**: named points inside the bulb, outside the urethra (``near_urethra`` is 3 mm
  from its wall).

A design that cannot be built raises :class:`~softphantom.errors.DesignError` on construction,
with a one-line message naming the field and the limit.

>>> d = BIPDesign()
>>> round(d.bulb.volume_mm3, 6)
100410.0
>>> [a.name for a in d.arms]
['front_zpos', 'front_zneg', 'back_xpos', 'back_xneg']
>>> BIPDesign(bulb=BulbParams(semi_axes_mm=(32.0, -1.0, 30.0)))
Traceback (most recent call last):
...
softphantom.errors.DesignError: bulb.semi_axes_mm[1] = -1 must be > 0 mm
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tomli_w
from pydantic import AfterValidator, SkipValidation, Strict

from softphantom.design import geometry as geo
from softphantom.design.fabrication import MoldParams
from softphantom.design.shapes import EXPONENT_RANGE, bend_axes, body_surface
from softphantom.errors import DesignError, UserError
from softphantom.records.names import ARM_NAMES
from softphantom.schema import Field, Number, between, checked, refuse
from softphantom.schema import Vec3 as _Vec3  # params.Vec3 is the plain type of a point

Vec3 = tuple[float, float, float]
# field types of the parameter tables (softphantom.schema.checked): finite numbers, lengths and volumes > 0
_Size = Annotated[Number, Field(gt=0)]
_Sizes3 = Annotated[tuple[_Size, ...], Field(min_length=3, max_length=3)]


def _bare_name(name: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9_-]+", name):
        raise refuse("must be letters, digits, _ or -")
    return name


_Name = Annotated[str, Strict(), AfterValidator(_bare_name)]

MIN_ARMS = 3  # four arm volumes see three force components; fewer cannot (docs/estimation.md, observability)
RESERVED_NAMES = ("urethra", "bulb", "shell")  # cavity and region names an arm may not take
CAVITY_NAMES: tuple[str, ...] = ARM_NAMES + ("urethra",)
REGION_NAMES: tuple[str, ...] = ("bulb", *(f"arm_{n}" for n in ARM_NAMES))
DEFAULT_MATERIAL = "ecoflex_00_50"
MIN_WALL_MM = 1.0
SURFACE_TOL_MM = 0.1
MIN_MARKERS = 4
MIN_MARKER_SPREAD_MM = 1.0
DERIVED_CONTACTS = ("on-centre", "off-centre")  # every design's first contact points, from [interaction]
MAX_CAVITY_SEGMENTS = 256.0  # volume error (2π/n)²/6 = 0.01 %: more buys nothing but elements

BULB_VOLUME_MM3 = 100_410.0
URETHRA_VOLUME_MM3 = 2078.0
CAVITY_VOLUME_VERTICAL_MM3 = 514.0  # front pair (±z)
CAVITY_VOLUME_HORIZONTAL_MM3 = 486.0  # back pair (±x)
DEFAULT_JUNCTION_FILLET_MM = 2.0  # arm-bulb edge: sharp (0) is singular, the yaw never converges (docs/model.md)
_A_MM, _B_MM = 32.0, 25.0
_C_MM = BULB_VOLUME_MM3 / (4.0 / 3.0 * math.pi * _A_MM * _B_MM)  # 29.9639… mm


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def _num(path: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise DesignError(f"{path}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise DesignError(f"{path} = {value!r} must be finite")
    return v


def _vec3(path: str, value: Any) -> Vec3:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 3:
        raise DesignError(f"{path}: expected 3 numbers [x, y, z], got {value!r}")
    return tuple(_num(f"{path}[{i}]", v) for i, v in enumerate(value))  # type: ignore[return-value]


def _set(obj: Any, name: str, value: Any) -> None:
    object.__setattr__(obj, name, value)


@functools.lru_cache(maxsize=16)
def _shape_triangles(semi_axes: Vec3, exponents: tuple[float, float], bend_mm: float) -> tuple[tuple, tuple]:
    """A parametric body's triangles as the bulb's nested tuples (cached: a design is made often)."""
    v, f = body_surface(semi_axes, exponents, bend_mm)
    return tuple(map(tuple, v.tolist())), tuple(map(tuple, f.tolist()))


@checked("bulb", DesignError)
class BulbParams:
    """The body (the gland), centred at the origin, semi-axes (x, y, z) in mm, one of:

    - ``shape = "ellipsoid"`` (the default): closed forms for every query;
    - ``shape = "superellipsoid"``: Barr's superquadric with ``exponents`` (e1 north–south along
      z, e2 east–west in x–y; [1, 1] is the ellipsoid), bent into a bean by ``bend_mm`` (the
      longest axis curved towards the next longest, its ends ``bend_mm`` off its middle:
      design/shapes.py). The file keeps these parameters; the triangles are derived from them
      into ``surface_vertices_mm`` / ``surface_faces`` (within about 0.05 mm of the shape);
    - from an anatomy import (design/anatomy.py), a closed triangle surface
      ``surface_vertices_mm`` / ``surface_faces`` in the model frame (then ``semi_axes_mm`` are
      its half extents, for information).

    A triangulated body answers the geometry queries (:meth:`signed_distance`, :meth:`ray_exit`,
    :meth:`normal`) through design/surface.py; the mesher meshes an imported surface as a
    polyhedron and a superellipsoid as a smooth loft (design/occ_shapes.py).

    >>> b = BulbParams(semi_axes_mm=(30.0, 25.0, 20.0), shape="superellipsoid", exponents=(1.0, 1.0))
    >>> b.is_surface, round(b.volume_mm3 / (4 / 3 * math.pi * 30 * 25 * 20), 12)
    (True, 1.0)
    >>> BulbParams(shape="superellipsoid", exponents=(0.2, 1.0))
    Traceback (most recent call last):
    ...
    softphantom.errors.DesignError: bulb.exponents[0] = 0.2 must be in [0.3, 1.5] (1: round, lower: boxier, higher: pinched)
    """

    semi_axes_mm: _Sizes3 = (_A_MM, _B_MM, _C_MM)
    surface_vertices_mm: tuple[_Vec3, ...] = ()
    surface_faces: tuple[Annotated[tuple[Annotated[int, Strict(), Field(ge=0)], ...],
                                   Field(min_length=3, max_length=3)], ...] = ()
    shape: Literal["ellipsoid", "superellipsoid"] = "ellipsoid"
    exponents: Annotated[tuple[Annotated[Number, between(*EXPONENT_RANGE, "(1: round, lower: boxier, higher: pinched)")],
                               ...], Field(min_length=2, max_length=2)] = (1.0, 1.0)
    bend_mm: Number = 0.0

    def __post_init__(self) -> None:
        if self.shape == "ellipsoid":
            if tuple(self.exponents) != (1.0, 1.0):
                raise DesignError(f"bulb.exponents = {list(self.exponents)}: only with shape = \"superellipsoid\"")
            if self.bend_mm != 0.0:
                raise DesignError(f"bulb.bend_mm = {_fmt(self.bend_mm)}: only with shape = \"superellipsoid\" "
                                  "(exponents = [1, 1] for a bent ellipsoid)")
        else:
            lo, w = bend_axes(self.semi_axes_mm)
            half = self.semi_axes_mm[w]
            if abs(self.bend_mm) > half:
                raise DesignError(f"bulb.bend_mm = {_fmt(self.bend_mm)} bends the body by more than its half-width "
                                  f"along {'xyz'[w]} (max {_fmt(half)} mm: semi_axes_mm[{w}])")
            # derived: replace() with other semi-axes or exponents derives them again
            verts, faces = _shape_triangles(tuple(self.semi_axes_mm), tuple(self.exponents), float(self.bend_mm))
            _set(self, "surface_vertices_mm", verts)
            _set(self, "surface_faces", faces)
            return
        verts, faces = self.surface_vertices_mm, self.surface_faces
        for i, f in enumerate(faces):
            if max(f) >= len(verts):
                raise DesignError(f"bulb.surface_faces[{i}]: expected 3 vertex indices in 0..{len(verts) - 1}, got {f!r}")
        if bool(verts) != bool(faces) or (faces and len(faces) < 4):
            raise DesignError("bulb: surface_vertices_mm and surface_faces come together (a closed surface, >= 4 faces)")
        if faces and not self.volume_mm3 > 0.0:
            raise DesignError(f"bulb.surface_faces: the surface encloses {_fmt(self.volume_mm3)} mm³ (inside out or open)")

    @property
    def is_parametric(self) -> bool:
        """A shape whose triangles are derived from its parameters (not stored in the file)."""
        return self.shape != "ellipsoid"

    @property
    def is_surface(self) -> bool:
        return bool(self.surface_faces)

    def _mesh(self):
        from softphantom.design.surface import surface_mesh

        return surface_mesh(self.surface_vertices_mm, self.surface_faces)

    @property
    def volume_mm3(self) -> float:
        if self.is_parametric:  # Barr's closed form; the bend is a shear, which keeps it
            return geo.superellipsoid_volume(self.semi_axes_mm, self.exponents)
        if self.is_surface:
            return geo.surface_enclosed_volume(np.asarray(self.surface_vertices_mm), np.asarray(self.surface_faces))
        return geo.ellipsoid_volume(self.semi_axes_mm)

    @property
    def area_mm2(self) -> float:
        """Surface area: the triangles' sum, or Knud Thomsen's ellipsoid approximation (within 1.1 %)."""
        if self.is_surface:
            v = np.asarray(self.surface_vertices_mm)[np.asarray(self.surface_faces)]
            return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())
        a, b, c = self.semi_axes_mm
        p = 1.6075
        return 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)

    def signed_distance(self, points) -> np.ndarray:
        """Signed distance of ``points`` (mm) to the bulb surface, negative inside."""
        if self.is_surface:
            from softphantom.design.surface import signed_distance

            return signed_distance(self._mesh(), points)
        return geo.ellipsoid_signed_distance(points, self.semi_axes_mm)

    def closest_surface_point(self, points) -> np.ndarray:
        """(n, 3) mm: the point of the body's surface closest to each of ``points`` (its triangles
        for a triangulated body: the surface every on-the-surface check measures against).

        >>> BulbParams(semi_axes_mm=(30.0, 20.0, 25.0)).closest_surface_point([[0, -21.5, 0]]).round(9).tolist()
        [[0.0, -20.0, 0.0]]
        """
        if self.is_surface:
            from softphantom.design.surface import closest_point

            return closest_point(self._mesh(), points)
        return geo.ellipsoid_closest_point(points, self.semi_axes_mm)

    def ray_exit(self, origin, direction) -> float | None:
        """Largest s with origin + s·direction on the surface (None: the line misses the bulb)."""
        if self.is_surface:
            from softphantom.design.surface import ray_exit

            return ray_exit(self._mesh(), origin, direction)
        return geo.ray_exit(origin, direction, self.semi_axes_mm)

    def normal(self, point) -> np.ndarray:
        """Outward unit normal at a surface point."""
        if self.is_surface:
            from softphantom.design.surface import normal_at

            return normal_at(self._mesh(), point)
        return geo.unit(np.asarray(point, float) / np.asarray(self.semi_axes_mm, float) ** 2)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi)."""
        if self.is_surface:
            v = np.asarray(self.surface_vertices_mm)
            return v.min(axis=0), v.max(axis=0)
        a = np.asarray(self.semi_axes_mm)
        return -a, a


@checked("layers.lesions.{name}", DesignError)
class LesionParams:
    """A lesion inclusion: an axis-aligned ellipsoid in the bulb's infill, its own mesh region
    ``lesion_<name>`` (and material, through ``[region_materials]``)."""

    name: _Name
    center_mm: _Vec3
    semi_axes_mm: _Sizes3

    @property
    def region(self) -> str:
        return f"lesion_{self.name}"

    @property
    def volume_mm3(self) -> float:
        return geo.ellipsoid_volume(self.semi_axes_mm)


@checked("layers", DesignError)
class LayersParams:
    """The bulb in more than one material: an outer shell ``shell_mm`` thick (region ``shell``;
    0: none) over the infill (region ``bulb``), the infill being the ellipsoid with every semi-axis
    less ``shell_mm`` (so the shell is exactly ``shell_mm`` thick at the six poles and a little
    less, by (a−c)·t/a at most, in between), and lesion inclusions (regions ``lesion_<name>``)."""

    shell_mm: Annotated[Number, Field(ge=0)] = 0.0  # 0: no shell
    lesions: tuple[LesionParams, ...] = ()

    def __post_init__(self) -> None:
        names = [x.name for x in self.lesions]
        for n in names:
            if names.count(n) > 1:
                raise DesignError(f"layers.lesions.{n}: defined twice")

    @property
    def is_default(self) -> bool:
        return self.shell_mm == 0.0 and not self.lesions

    def infill_semi_axes_mm(self, bulb_axes: Vec3) -> Vec3:
        return tuple(a - self.shell_mm for a in bulb_axes)  # type: ignore[return-value]


def _default_inlet() -> Vec3:
    # where the default urethra axis (x = 0, z = 4 mm, along y) leaves the bulb at +y (the base)
    return (0.0, _B_MM * math.sqrt(1.0 - (4.0 / _C_MM) ** 2), 4.0)


class _Cavity:
    """What every internal cavity answers (the urethra's table and ``[cavities.NAME]`` alike)."""

    @property
    def path(self) -> str:
        """Its table in a design file, for messages."""
        return f"cavities.{self.name}"

    @property
    def wall_radius_mm(self) -> float:
        """The radius its wall is meshed for (a capsule's, an ellipsoid's smallest semi-axis)."""
        return self.radius_mm

    def signed_distance(self, points) -> np.ndarray:
        """Signed distance of ``points`` (mm) to its wall, negative inside."""
        a, b = self.segment_mm
        return geo.segment_distance(points, a, b) - self.radius_mm

    def surface_points(self, spacing: float = 0.4) -> np.ndarray:
        a, b = self.segment_mm
        return geo.capsule_surface_points(a, b, self.radius_mm, spacing=spacing)

    def _check_capsule(self) -> None:
        if not np.linalg.norm(self.axis) > 0.0:
            raise DesignError(f"{self.path}.axis must be a non-zero vector")
        sphere = 4.0 / 3.0 * math.pi * self.radius_mm**3
        if self.cyl_length_mm < 0.0:
            raise DesignError(
                f"{self.path}.volume_mm3 = {_fmt(self.volume_mm3)} is below the sphere of "
                f"radius_mm {_fmt(self.radius_mm)} (min {_fmt(sphere)} mm³)"
            )

    @property
    def cyl_length_mm(self) -> float:
        return geo.capsule_cyl_length(self.radius_mm, self.volume_mm3)

    @property
    def segment_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """End points of the capsule's axis segment (centres of the hemispherical ends)."""
        w = geo.unit(self.axis)
        c = np.asarray(self.center_mm)
        h = 0.5 * self.cyl_length_mm
        return c - h * w, c + h * w


@checked("urethra", DesignError)
class UrethraParams(_Cavity):
    """The inflatable urethra cavity (the ``[urethra]`` table, the BIP's one internal cavity): a
    closed capsule along ``axis`` through ``center_mm``, actuated."""

    radius_mm: _Size = 4.5
    volume_mm3: _Size = URETHRA_VOLUME_MM3
    center_mm: _Vec3 = (0.0, 0.0, 4.0)
    axis: _Vec3 = (0.0, 1.0, 0.0)
    inlet_mm: _Vec3 = field(default_factory=_default_inlet)

    name = "urethra"
    shape = "capsule"
    role = "actuated"

    def __post_init__(self) -> None:
        self._check_capsule()

    @property
    def path(self) -> str:
        return "urethra"


_Role = Literal["actuated", "measured"]


@checked("cavities.{name}", DesignError)
class CapsuleCavity(_Cavity):
    """An internal cavity ``[cavities.NAME]`` with ``shape = "capsule"``: an inflatable channel
    like the urethra (the fields of :class:`UrethraParams`), its tube leaving the body at ``inlet_mm``;
    ``role`` ``"actuated"`` (a known pressure load) or ``"measured"`` (read as a volume channel)."""

    name: _Name
    radius_mm: _Size
    volume_mm3: _Size
    center_mm: _Vec3
    inlet_mm: _Vec3
    axis: _Vec3 = (0.0, 1.0, 0.0)
    role: _Role = "actuated"
    shape: Literal["capsule"] = "capsule"

    def __post_init__(self) -> None:
        self._check_capsule()


@checked("cavities.{name}", DesignError)
class EllipsoidCavity(_Cavity):
    """An internal cavity ``[cavities.NAME]`` with ``shape = "ellipsoid"``: a balloon (a lesion or
    tumour to inflate, or to read), an axis-aligned ellipsoid of ``semi_axes_mm`` at ``center_mm``;
    ``role`` as a :class:`CapsuleCavity`'s.

    >>> b = EllipsoidCavity("tumour", center_mm=(0, 0, 0), semi_axes_mm=(3, 3, 3), inlet_mm=(0, 0, 30))
    >>> round(b.volume_mm3, 3), float(b.signed_distance([[0, 0, 5.0]])[0])
    (113.097, 2.0)
    """

    name: _Name
    center_mm: _Vec3
    semi_axes_mm: _Sizes3
    inlet_mm: _Vec3
    role: _Role = "actuated"
    shape: Literal["ellipsoid"] = "ellipsoid"

    @property
    def volume_mm3(self) -> float:
        return geo.ellipsoid_volume(self.semi_axes_mm)

    @property
    def wall_radius_mm(self) -> float:
        return min(self.semi_axes_mm)

    def signed_distance(self, points) -> np.ndarray:
        return geo.ellipsoid_signed_distance(np.atleast_2d(np.asarray(points, float)) - np.asarray(self.center_mm),
                                             self.semi_axes_mm)

    def surface_points(self, spacing: float = 0.4) -> np.ndarray:
        a, b, c = self.semi_axes_mm
        area = 4 * math.pi * max(a * b, b * c, a * c)
        return geo.ellipsoid_surface_points(self.center_mm, self.semi_axes_mm,
                                            n=int(min(20000, max(1200, area / spacing**2))))


#: what a design's ``cavities`` hold
CAVITY_TYPES = (UrethraParams, CapsuleCavity, EllipsoidCavity)
_CAVITY_KEYS = {"capsule": [f.name for f in dataclasses.fields(CapsuleCavity) if f.name != "name"],
                "ellipsoid": [f.name for f in dataclasses.fields(EllipsoidCavity) if f.name != "name"]}
_CAVITY_NEEDS = {"capsule": ("radius_mm", "volume_mm3", "center_mm", "inlet_mm"),
                 "ellipsoid": ("center_mm", "semi_axes_mm", "inlet_mm")}


@checked("arms.{name}", DesignError)
class ArmParams:
    """One sensing arm (see the module docstring for how the fields place it).

    ``junction_fillet_mm``: radius of the concave fillet that rounds the edge where the arm's side
    meets the bulb (cast with the arm: its mold's floor is rounded; 0 = a sharp edge). The edge
    is re-entrant, so without it the stress there is singular and the model's rotation does not
    converge with the mesh (docs/model.md, "Convergence"); the default, 2 mm, is the smallest
    radius a cast part or glue bead at this joint realistically has."""

    name: str
    direction: _Vec3
    cavity_volume_mm3: _Size
    length_mm: _Size = 32.0
    radius_mm: _Size = 6.0
    wall_mm: _Size = 2.5
    cavity_offset_mm: Number = 17.0
    embed_mm: _Size = 8.0
    axis_point_mm: _Vec3 = (0.0, 0.0, 0.0)
    junction_fillet_mm: Number = DEFAULT_JUNCTION_FILLET_MM

    def __post_init__(self) -> None:
        p = f"arms.{self.name}"
        if not np.linalg.norm(self.direction) > 0.0:
            raise DesignError(f"{p}.direction must be a non-zero vector")
        r = self.junction_fillet_mm
        if not 0.0 <= r <= self.radius_mm:
            raise DesignError(f"{p}.junction_fillet_mm = {_fmt(r)} must be in [0, radius_mm = {_fmt(self.radius_mm)}] mm "
                              "(0: a sharp edge)")
        if self.wall_mm < MIN_WALL_MM:
            raise DesignError(f"{p}.wall_mm = {_fmt(self.wall_mm)} is below the minimum wall of {MIN_WALL_MM:g} mm")
        if self.wall_mm >= self.radius_mm:
            raise DesignError(
                f"{p}.wall_mm = {_fmt(self.wall_mm)} leaves no cavity (must be < radius_mm {_fmt(self.radius_mm)})"
            )
        if self.cavity_cyl_length_mm < 0.0:
            r = self.cavity_radius_mm
            raise DesignError(
                f"{p}.cavity_volume_mm3 = {_fmt(self.cavity_volume_mm3)} is below the sphere of radius "
                f"{_fmt(r)} mm (radius_mm − wall_mm; min {_fmt(4 / 3 * math.pi * r**3)} mm³)"
            )
        room = self.length_mm - 2 * MIN_WALL_MM  # the capsule lies in the arm, a wall from each end
        if self.cavity_cyl_length_mm + 2 * self.cavity_radius_mm > room:
            r = self.cavity_radius_mm
            vmax = geo.capsule_volume(r, max(0.0, room - 2 * r))
            raise DesignError(
                f"{p}.cavity_volume_mm3 = {_fmt(self.cavity_volume_mm3)} does not fit in the arm: a capsule of "
                f"radius {_fmt(r)} mm that long exceeds length_mm − 2 walls = {_fmt(room)} mm (max {_fmt(vmax)} mm³)"
            )

    @property
    def cavity_radius_mm(self) -> float:
        return self.radius_mm - self.wall_mm

    @property
    def cavity_cyl_length_mm(self) -> float:
        return geo.capsule_cyl_length(self.cavity_radius_mm, self.cavity_volume_mm3)


def _default_arms() -> tuple[ArmParams, ...]:
    # Arms along (0, ∓0.6, ±1) and (±1, 0.6, 0): a 5 N push along y at p_ext moves the markers
    # ~10 mm (co-rotational FEM, coarse mesh; linear elasticity ~9.5 mm, along x ~11, z ~14).
    # A smaller y-component makes y more compliant (0.3: ~15 mm); bench_design.py --compliance.
    v, h = CAVITY_VOLUME_VERTICAL_MM3, CAVITY_VOLUME_HORIZONTAL_MM3
    return (
        ArmParams("front_zpos", (0.0, -0.6, 1.0), v),
        ArmParams("front_zneg", (0.0, -0.6, -1.0), v),
        ArmParams("back_xpos", (1.0, 0.6, 0.0), h),
        ArmParams("back_xneg", (-1.0, 0.6, 0.0), h),
    )


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


@checked("interaction", DesignError)
class InteractionParams:
    """Where p_ext lies: ``off-centre`` is ``offcentre_mm`` from ``on-centre`` (straight line)."""

    offcentre_mm: _Size = 10.0
    offcentre_angle_deg: Number = 45.0


@checked("mesh", DesignError)
class MeshParams:
    """Target element sizes: ``size_mm`` inside the bulb, ``surface_size_mm`` on its outer
    surface, ``arm_size_mm`` in the arms; on each cavity wall ``2π·r / cavity_segments`` (r the
    cavity radius), so every cavity gets the same relative volume accuracy.

    ``--mesh-size-mm H`` scales all sizes by H / size_mm (and the segments by its inverse).
    ``element_order``: 1 (4-node tets) or 2 (10-node tets, mid-edge nodes placed on the CAD
    surfaces by gmsh, so curved walls stay curved).

    Local refinements (0 = off, the default): ``contact_size_mm`` within ``contact_zone_mm`` of
    the interaction points (``p_ext``: a contact patch's rim then falls on small elements), and
    ``junction_size_mm`` along the edges where the arms meet the bulb (re-entrant edges, where the
    stress is singular); both grow about 1:1 with the distance to the background sizes
    (docs/model.md, "Convergence").

    >>> MeshParams().scaled_to(12.0).arm_size_mm
    6.0
    """

    size_mm: _Size = 6.0
    surface_size_mm: _Size = 4.0
    arm_size_mm: _Size = 3.0
    cavity_segments: Annotated[Number, between(6, MAX_CAVITY_SEGMENTS)] = 22.0
    element_order: Literal[1, 2] = 1
    contact_size_mm: Annotated[Number, Field(ge=0)] = 0.0  # 0: no local refinement
    contact_zone_mm: _Size = 8.0
    junction_size_mm: Annotated[Number, Field(ge=0)] = 0.0

    def cavity_size_mm(self, radius_mm: float) -> float:
        """Element size on the wall of a cavity of ``radius_mm``."""
        return 2.0 * math.pi * radius_mm / self.cavity_segments

    def scaled_to(self, size_mm: float) -> "MeshParams":
        """The same grading with a bulb size of ``size_mm``."""
        s = dataclasses.replace(self, size_mm=size_mm).size_mm / self.size_mm  # checks size_mm
        segments = min(MAX_CAVITY_SEGMENTS, max(6.0, self.cavity_segments / s))
        return MeshParams(size_mm, self.surface_size_mm * s, self.arm_size_mm * s, segments, self.element_order,
                          self.contact_size_mm * s, self.contact_zone_mm, self.junction_size_mm * s)


@checked("sensors", DesignError)
class SensorParams:
    """The bench's sensors as calibrated (``softphantom calibrate``): ``gains`` of the volume
    channels' transducers (the arms', then the measured cavities': ``BIPDesign.sensing_names``)
    relative to their datasheet sensitivity, ``tube_volume_factor`` the
    real tube volume over the one its length and bore give, ``tube_tau_ms`` each volume channel's
    fitted tube time constant (empty: from the tube). Defaults: the datasheet, no correction."""

    gains: Annotated[tuple[Annotated[Number, between(0.5, 2.0, "(a transducer's sensitivity / datasheet)")], ...],
                     Field(min_length=MIN_ARMS)] = (1.0, 1.0, 1.0, 1.0)  # one per volume channel, in the sensor order
    tube_volume_factor: Annotated[Number, between(0.2, 5.0)] = 1.0
    tube_tau_ms: tuple[Annotated[Number, between(0.01, 5000.0, "(a tube's time constant, ms)")], ...] = ()


def _on_surface(direction: Vec3) -> Vec3:
    p = geo.project_to_ellipsoid(direction, (_A_MM, _B_MM, _C_MM))
    return tuple(float(x) for x in p)  # type: ignore[return-value]


def _default_markers() -> tuple[tuple[str, Vec3], ...]:
    # five sockets spread over the bulb, away from the arm roots and from p_ext
    dirs = {
        "m1": (1.0, -0.3, 0.35),
        "m2": (-1.0, -0.3, 0.35),
        "m3": (0.35, 0.2, 1.0),
        "m4": (-0.5, 0.2, -1.0),
        "m5": (0.3, 1.0, -0.5),
    }
    return tuple((k, _on_surface(v)) for k, v in dirs.items())


def _default_targets() -> tuple[tuple[str, Vec3], ...]:
    return (
        ("seed_apex", (-8.0, -14.0, -6.0)),
        ("seed_mid", (10.0, 2.0, -8.0)),
        ("seed_base", (-6.0, 14.0, 10.0)),
        # 3 mm lateral of the urethra wall (radius 4.5 mm, axis x = 0, z = 4 mm)
        ("near_urethra", (7.5, 0.0, 4.0)),
    )


def _named_points(path: str, value: Any) -> tuple[tuple[str, Vec3], ...]:
    items = value.items() if isinstance(value, dict) else value
    out = []
    seen = set()
    for item in items:
        if not (isinstance(item, (tuple, list)) and len(item) == 2 and isinstance(item[0], str)):
            raise DesignError(f"{path}: expected name = [x, y, z] pairs, got {item!r}")
        name, xyz = item
        if not name or name in seen:
            raise DesignError(f"{path}: duplicate or empty name {name!r}")
        seen.add(name)
        out.append((name, _vec3(f"{path}.{name}", xyz)))
    return tuple(out)


def _contact_points(value: Any) -> tuple[tuple[str, Vec3], ...]:
    """``[contacts]`` as (name, point) pairs; a name is refused here, its point in _validate_geometry."""
    items = value.items() if isinstance(value, dict) else value
    seen: list[str] = []
    for item in items:
        name = item[0] if isinstance(item, (tuple, list)) and len(item) == 2 else None
        if not isinstance(name, str):
            raise DesignError(f"contacts: expected name = [x, y, z] pairs, got {item!r}")
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
            raise DesignError(f"contacts.{name}: a contact's name must start with a letter and hold letters, "
                              "digits, _ or -")
        if name in DERIVED_CONTACTS:
            raise DesignError(f"contacts.{name}: reserved (on-centre and off-centre come from [interaction])")
        if name in seen:
            raise DesignError(f"contacts.{name}: two contact points have this name")
        seen.append(name)
    return _named_points("contacts", items)


def check_contact(name: str, names, option: str = "--at", whose: str = "this model", hint: str = "") -> str:
    """``name`` if it is one of ``names`` (a model's contact points), else a one-line UserError
    naming ``option`` and listing them (then ``hint``, e.g. the other forms the option takes).

    >>> check_contact("front-lobe", ("on-centre", "off-centre"))
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --at front-lobe: not a contact point of this model (on-centre, off-centre)
    """
    if name not in names:
        raise UserError(f"{option} {name}: not a contact point of {whose} ({', '.join(names)})"
                        + (f"; {hint}" if hint else ""))
    return name


@checked("materials.{name}", DesignError)
class MaterialSpec:
    """A named material of the design file: ``law`` (``corotational``, ``neo-hookean``, ``yeoh``)
    and its parameters in the units of their names (``E_kPa``, ``nu``, ``C10_kPa``, …,
    ``density_kg_m3``). The design checks the form (names, numbers); the FEM stage
    (:func:`softphantom.fem.material.law_from_spec`) checks the law and its physics, naming the field."""

    name: _Name
    law: Annotated[str, Strict()]
    values: SkipValidation[tuple[tuple[str, float], ...]]  # or a dict; checked below, naming the parameter

    def __post_init__(self) -> None:
        p = f"materials.{self.name}"
        vals = dict(self.values.items() if isinstance(self.values, dict) else self.values)
        _set(self, "values", tuple((str(k), _num(f"{p}.{k}", v)) for k, v in vals.items()))


def _default_materials() -> tuple[MaterialSpec, ...]:
    # the model's Ecoflex 00-50 (softphantom.fem.material.ECOFLEX_00_50): E = 3 x 83 kPa / 1.75
    # compressible neo-Hookean: as cheap as the co-rotational law on P1 and right in the arms' ΔV
    # at large pushes, where co-rotational gets even their sign wrong (docs/model.md)
    return (MaterialSpec(DEFAULT_MATERIAL, "neo-hookean",
                         (("E_kPa", 3 * 83.0 / 1.75), ("nu", 0.45), ("density_kg_m3", 1070.0))),)


def _from_100_percent_modulus(name: str, sigma100_kPa: float, density_kg_m3: float) -> MaterialSpec:
    # incompressible neo-Hookean in uniaxial tension: nominal stress μ(λ − λ⁻²), so the 100 %
    # modulus (λ = 2) is 1.75 μ and the small-strain E = 3μ (fem/material.py, ECOFLEX_00_50)
    return MaterialSpec(name, "neo-hookean", (("E_kPa", 3.0 * sigma100_kPa / 1.75), ("nu", 0.45),
                                               ("density_kg_m3", density_kg_m3)))


#: Materials a design may name in ``[region_materials]`` without a ``[materials.NAME]`` table (the
#: preset is then written into the design's ``[materials]``). Sources in docs/fabrication.md:
#: Smooth-On technical bulletins — Ecoflex 00-50 (100 % modulus 12 psi = 83 kPa, specific gravity
#: 1.07, the paper's figure), Sorta-Clear 12 (100 % modulus 28 psi = 193 kPa, s.g. 1.04) and
#: Ecoflex GEL (Shore 000-35, s.g. 0.98; no 100 % modulus: E = 10 kPa is an order-of-magnitude
#: placeholder). The Sorta-Clear 12 and GEL figures were NOT checked against the bulletins here.
MATERIAL_PRESETS: dict[str, MaterialSpec] = {
    m.name: m for m in (
        _default_materials()[0],
        _from_100_percent_modulus("sorta_clear_12", 193.0, 1040.0),
        MaterialSpec("ecoflex_gel", "neo-hookean", (("E_kPa", 10.0), ("nu", 0.45), ("density_kg_m3", 980.0))),
    )
}


def _default_region_materials() -> tuple[tuple[str, str], ...]:
    return (("bulb", DEFAULT_MATERIAL), ("arms", DEFAULT_MATERIAL))


@checked("", DesignError)
class BIPDesign:
    """The validated BIP design (defaults reproduce the paper; see the module docstring)."""

    name: Annotated[str, Strict(), Field(min_length=1)] = "bip"
    bulb: BulbParams = field(default_factory=BulbParams)
    # the internal cavities (urethra, channels, balloons), in the load order; (name, ...) objects of CAVITY_TYPES
    cavities: SkipValidation[tuple[Any, ...]] = field(default_factory=lambda: (UrethraParams(),))
    arms: tuple[ArmParams, ...] = field(default_factory=_default_arms)
    interaction: InteractionParams = field(default_factory=InteractionParams)
    # (name, point) pairs or a dict; checked below, naming the point
    markers: SkipValidation[tuple[tuple[str, Vec3], ...]] = field(default_factory=_default_markers)
    targets: SkipValidation[tuple[tuple[str, Vec3], ...]] = field(default_factory=_default_targets)
    # further contact points (name, point) after on-centre and off-centre; checked below
    contacts: SkipValidation[tuple[tuple[str, Vec3], ...]] = ()
    mesh: MeshParams = field(default_factory=MeshParams)
    materials: tuple[MaterialSpec, ...] = field(default_factory=_default_materials)
    region_materials: SkipValidation[tuple[tuple[str, str], ...]] = field(default_factory=_default_region_materials)
    molds: MoldParams = field(default_factory=MoldParams)  # how it is cast (design/fabrication.py)
    sensors: SensorParams = field(default_factory=SensorParams)  # as calibrated (softphantom calibrate)
    layers: LayersParams = field(default_factory=LayersParams)  # shell, infill and lesions (multi-material)

    def __post_init__(self) -> None:
        _set(self, "markers", _named_points("markers", self.markers))
        _set(self, "targets", _named_points("targets", self.targets))
        _set(self, "contacts", _contact_points(self.contacts))
        _validate_arm_names(tuple(a.name for a in self.arms))
        _set(self, "cavities", tuple(self.cavities))
        _validate_cavity_names(self)
        g, n = self.sensors.gains, len(self.sensing_names)
        if len(g) != n:
            if any(v != 1.0 for v in g):
                what = f"{n} volume channels" if self.measured_cavity_names else f"{n} arms"
                raise DesignError(f"sensors.gains: {len(g)} given for {what} (one per volume channel, in the "
                                  f"sensor order: {', '.join(self.sensing_names)})")
            _set(self, "sensors", dataclasses.replace(self.sensors, gains=(1.0,) * n))  # the datasheet's
        _validate_geometry(self)
        _validate_layers(self)
        _validate_materials(self)

    @property
    def arm_names(self) -> tuple[str, ...]:
        """The arms' names in the sensor order.

        >>> BIPDesign().arm_names == ARM_NAMES
        True
        """
        return tuple(a.name for a in self.arms)

    @property
    def cavity_names(self) -> tuple[str, ...]:
        """The cavities: the arms' in the sensor order, then the internal ones (the BIP: ``urethra``)."""
        return (*self.arm_names, *self.internal_cavity_names)

    @property
    def internal_cavity_names(self) -> tuple[str, ...]:
        """The internal cavities, actuated and measured, in the file's order (the geometry: mesh,
        molds).

        >>> BIPDesign().internal_cavity_names
        ('urethra',)
        """
        return tuple(c.name for c in self.cavities)

    @property
    def measured_cavity_names(self) -> tuple[str, ...]:
        """The internal cavities of ``role = "measured"``, in the file's order (none on the BIP)."""
        return tuple(c.name for c in self.cavities if c.role == "measured")

    @property
    def sensing_names(self) -> tuple[str, ...]:
        """The volume channels in the sensor order: the arms, then the measured internal cavities
        (each a differential transducer, its volume change by Boyle's law; the rows of ``V`` and ``W``).

        >>> BIPDesign().sensing_names == ARM_NAMES
        True
        >>> ball = EllipsoidCavity("ball", center_mm=(-12, -4, -10), semi_axes_mm=(4, 4, 4),
        ...                        inlet_mm=(-23.355, -7.006, -18.684), role="measured")
        >>> BIPDesign(cavities=(UrethraParams(), ball)).sensing_names[-2:]
        ('back_xneg', 'ball')
        """
        return (*self.arm_names, *self.measured_cavity_names)

    @property
    def pressure_names(self) -> tuple[str, ...]:
        """The actuated internal cavities in the file's order: the pressure loads ``λ[3:]``, each
        read by a pressure transducer (MPX4250D) on the channels after the volume channels.

        >>> BIPDesign().pressure_names
        ('urethra',)
        """
        return tuple(c.name for c in self.cavities if c.role == "actuated")

    @property
    def channel_layout(self):
        """The phantom's :class:`~softphantom.records.channels.ChannelLayout`: its arms, measured and
        actuated cavities, in order; passed to the model, the sensor chain, the estimator and every file.

        >>> BIPDesign().channel_layout.to_dict()
        {'arms': ['front_zpos', 'front_zneg', 'back_xpos', 'back_xneg'], 'measured': [], 'actuated': ['urethra']}
        """
        from softphantom.records.channels import ChannelLayout

        return ChannelLayout(self.arm_names, self.measured_cavity_names, self.pressure_names)

    @property
    def urethra(self):
        """The cavity named ``urethra`` (None without one)."""
        return next((c for c in self.cavities if c.name == "urethra"), None)

    def cavity(self, name: str):
        """The internal cavity ``name``."""
        for c in self.cavities:
            if c.name == name:
                return c
        raise DesignError(f"cavities.{name}: no such cavity (the design's: {', '.join(self.internal_cavity_names) or 'none'})")

    def with_urethra(self, urethra) -> "BIPDesign":
        """This design with ``urethra`` in place of its urethra (first when it had none; None drops it)."""
        rest = [c for c in self.cavities if c.name != "urethra"]
        if urethra is None:
            return dataclasses.replace(self, cavities=tuple(rest))
        names = self.internal_cavity_names
        i = names.index("urethra") if "urethra" in names else 0
        return dataclasses.replace(self, cavities=(*rest[:i], urethra, *rest[i:]))

    @property
    def region_names(self) -> tuple[str, ...]:
        """The mesh's volume regions: ``bulb`` (the infill when there is a shell), the arms, then
        ``shell`` and ``lesion_<name>`` when ``[layers]`` declares them."""
        extra = (("shell",) if self.layers.shell_mm > 0.0 else ()) + tuple(x.region for x in self.layers.lesions)
        return ("bulb", *(f"arm_{n}" for n in self.arm_names), *extra)

    def region_groups(self) -> dict[str, tuple[str, ...]]:
        """Groups usable in ``[region_materials]``: ``arms``, and ``lesions`` (every lesion)."""
        return {"arms": tuple(f"arm_{n}" for n in self.arm_names),
                "lesions": tuple(x.region for x in self.layers.lesions)}

    def material_of_regions(self, regions=None) -> dict[str, str]:
        """Region name -> material name, from ``region_materials`` (a region's own key wins over its
        group's, e.g. ``arm_front_zpos`` over ``arms``). Raises DesignError for a region without one.

        >>> BIPDesign().material_of_regions()["arm_back_xneg"]
        'ecoflex_00_50'
        """
        given = dict(self.region_materials)
        groups = self.region_groups()
        out = {}
        for r in (self.region_names if regions is None else regions):
            group = next((g for g, members in groups.items() if r in members and g in given), None)
            m = given.get(r, given.get(group) if group else None)
            if m is None:
                raise DesignError(f"region_materials.{r}: region {r!r} has no material")
            out[r] = m
        return out

    # --- derived geometry (mm) -------------------------------------------------------------
    def arm_geometry(self) -> tuple[ArmGeometry, ...]:
        """Placement of the arms, in the sensor order."""
        return tuple(_arm_geometry(a, self.bulb) for a in self.arms)

    def p_ext_mm(self) -> dict[str, np.ndarray]:
        """The contact points, mm: ``on-centre`` and ``off-centre`` (from ``[interaction]``), then
        the ``[contacts]`` in the file's order."""
        return {**_p_ext(self.bulb, self.interaction), **{k: np.asarray(v) for k, v in self.contacts}}

    @property
    def contact_names(self) -> tuple[str, ...]:
        """The names of :meth:`p_ext_mm`'s points, without computing them.

        >>> BIPDesign().contact_names
        ('on-centre', 'off-centre')
        """
        return (*DERIVED_CONTACTS, *(k for k, _ in self.contacts))

    @property
    def marker_dict(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v) for k, v in self.markers}

    @property
    def target_dict(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v) for k, v in self.targets}

    def cavity_volumes_mm3(self) -> dict[str, float]:
        """Design volume of each cavity (arms in the sensor order, then the internal ones)."""
        out = {a.name: a.cavity_volume_mm3 for a in self.arms}
        out.update((c.name, c.volume_mm3) for c in self.cavities)
        return out

    def sensing_volumes_mm3(self) -> tuple[float, ...]:
        """Design volume of each volume channel's cavity, in :attr:`sensing_names` order.

        >>> BIPDesign().sensing_volumes_mm3()
        (514.0, 514.0, 486.0, 486.0)
        """
        v = self.cavity_volumes_mm3()
        return tuple(float(v[n]) for n in self.sensing_names)


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
    for arm in d.arms:
        if arm.junction_fillet_mm > 0.0 and d.bulb.is_surface:
            raise DesignError(f"arms.{arm.name}.junction_fillet_mm = {_fmt(arm.junction_fillet_mm)}: an imported "
                              "(triangulated) bulb cannot be filleted (OCC rounds smooth surfaces only); 0 there")
    _check_sizes(d)
    sdist = d.bulb.signed_distance

    # internal cavities: each wholly inside with a wall, its inlet on the surface, a wall from the others
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

    # the BIP's own markers and targets on another body: ask for the design's, not about the prostate's m1
    own_markers = d.markers != _default_markers()
    own_targets = d.targets != _default_targets()
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
        for g in geoms:
            if geo.segment_distance([xyz], g.start_mm, g.end_mm)[0] < g.radius_mm + g.fillet_mm + MIN_WALL_MM:
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
    for name, xyz in d.targets:
        sd = float(sdist([xyz])[0])
        if sd >= 0.0:
            if not own_targets:
                raise DesignError(f"targets: none given, and the default (the prostate's) {name} is outside this "
                                  f"body ({_fmt(sd)} mm beyond its surface): give [targets], named points inside "
                                  "your body (NAME = [x, y, z] mm)")
            raise DesignError(f"targets.{name} is outside the bulb ({_fmt(sd)} mm beyond its surface)")
        for u in d.cavities:
            inside = -float(u.signed_distance([xyz])[0])
            if inside >= 0.0:
                if not own_targets:
                    raise DesignError(f"targets: none given, and the default (the prostate's) {name} is inside the "
                                      f"{u.name} cavity: give [targets], named points inside your body, outside its "
                                      "cavities (NAME = [x, y, z] mm)")
                raise DesignError(f"targets.{name} is inside the {u.name} cavity ({_fmt(inside)} mm from its wall)")
    _p_ext(d.bulb, d.interaction)
    for name, xyz in d.contacts:
        off = abs(float(sdist([xyz])[0]))
        if off > SURFACE_TOL_MM:
            raise DesignError(f"contacts.{name} = {list(xyz)} is {_fmt(off)} mm off the bulb surface "
                              f"(tolerance {SURFACE_TOL_MM:g} mm; snap_to_surface = true moves it onto the surface)")
        for g in geoms:
            if geo.segment_distance([xyz], g.start_mm, g.end_mm)[0] < g.radius_mm + g.fillet_mm + MIN_WALL_MM:
                raise DesignError(f"contacts.{name} lies under arms.{g.name} (min {MIN_WALL_MM:g} mm from its side)")


# --- files ---------------------------------------------------------------------------------

_SUBS = {"bulb": BulbParams, "urethra": UrethraParams, "interaction": InteractionParams, "mesh": MeshParams,
         "molds": MoldParams, "sensors": SensorParams}
_ARM_KEYS = [f.name for f in dataclasses.fields(ArmParams) if f.name != "name"]


def _plain(v: Any) -> Any:
    return [_plain(x) for x in v] if isinstance(v, (tuple, list)) else v


def design_to_dict(design: BIPDesign) -> dict[str, Any]:
    """Plain nested dict (TOML/JSON-ready) of a design.

    >>> design_from_dict(design_to_dict(BIPDesign())) == BIPDesign()
    True
    """
    out: dict[str, Any] = {"name": design.name}
    cavs = design.cavities
    for sub in _SUBS:
        if sub == "urethra":  # the BIP's [urethra] table; other cavities under [cavities]
            if isinstance(design.urethra, UrethraParams):
                out[sub] = {k: _plain(v) for k, v in dataclasses.asdict(design.urethra).items()}
            continue
        out[sub] = {k: _plain(v) for k, v in dataclasses.asdict(getattr(design, sub)).items()}
    out["bulb"] = _bulb_to_dict(design.bulb)
    if design.arm_names != ARM_NAMES:  # the BIP's file stays as it was
        out["arm_names"] = list(design.arm_names)
    out["arms"] = {
        a.name: {k: (list(getattr(a, k)) if isinstance(getattr(a, k), tuple) else getattr(a, k)) for k in _ARM_KEYS}
        for a in design.arms
    }
    if not (len(cavs) == 1 and isinstance(cavs[0], UrethraParams)):  # the BIP's file stays as it was
        out["cavities"] = {c.name: {k: _plain(v) for k, v in dataclasses.asdict(c).items() if k != "name"}
                           for c in cavs if not isinstance(c, UrethraParams)}
        if cavs and isinstance(design.urethra, UrethraParams) and cavs[0] is not design.urethra:
            out["cavity_names"] = list(design.internal_cavity_names)
    out["markers"] = {k: list(v) for k, v in design.markers}
    out["targets"] = {k: list(v) for k, v in design.targets}
    if design.contacts:  # a file without them stays as it was
        out["contacts"] = {k: list(v) for k, v in design.contacts}
    out["materials"] = {m.name: {"law": m.law, **dict(m.values)} for m in design.materials}
    out["region_materials"] = dict(design.region_materials)
    if not design.layers.is_default:  # a one-material design's file stays as it was
        out["layers"] = {"shell_mm": design.layers.shell_mm,
                         "lesions": {x.name: {"center_mm": list(x.center_mm), "semi_axes_mm": list(x.semi_axes_mm)}
                                     for x in design.layers.lesions}}
    return out


def _bulb_to_dict(bulb: BulbParams) -> dict[str, Any]:
    """The ``[bulb]`` table: an ellipsoid's semi-axes alone (its file stays as it was), a parametric
    shape's parameters (its triangles are derived on loading), an imported surface's triangles."""
    if bulb.is_parametric:
        return {"shape": bulb.shape, "semi_axes_mm": list(bulb.semi_axes_mm), "exponents": list(bulb.exponents),
                "bend_mm": bulb.bend_mm}
    keys = ("semi_axes_mm", "surface_vertices_mm", "surface_faces") if bulb.is_surface else ("semi_axes_mm",)
    return {k: _plain(getattr(bulb, k)) for k in keys}


def _check_keys(path: str, given: dict, allowed) -> None:
    """A table (and with ``allowed``, of those keys; the parameter tables check their own)."""
    if not isinstance(given, dict):
        raise DesignError(f"{path}: expected a table, got {given!r}")
    unknown = sorted(set(given) - set(allowed if allowed is not None else given))
    if unknown:
        raise DesignError(f"{path}: unknown key {unknown[0]!r} (known: {', '.join(sorted(allowed))})")


@functools.cache
def _default_design() -> BIPDesign:
    return BIPDesign()  # frozen: one validated instance serves every design_from_dict


def _arms_from_dict(data: dict[str, Any], default_arms: tuple[ArmParams, ...], surface: bool) -> tuple[ArmParams, ...]:
    """The arms of a design file: ``arm_names`` (default: the BIP's four) in the sensor order, each
    from its ``[arms.NAME]`` table; a BIP arm's missing keys keep its defaults, another arm gives at
    least ``direction`` and ``cavity_volume_mm3``."""
    given = data.get("arms", {})
    _check_keys("arms", given, None)
    names = data.get("arm_names", [a.name for a in default_arms])
    if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
        raise DesignError(f"arm_names: expected a list of names, got {names!r}")
    _validate_arm_names(tuple(names))
    extra = [n for n in given if n not in names]
    if extra:
        raise DesignError(f"arms.{extra[0]}: not one of the design's arms ({', '.join(names)}); list every arm, in "
                          "the sensor order, in arm_names = [...]")
    by_name = {a.name: a for a in default_arms}
    arms = []
    for n in names:
        over = given.get(n, {})
        _check_keys(f"arms.{n}", over, _ARM_KEYS)
        if n in by_name:
            a = by_name[n]
        else:
            missing = [k for k in ("direction", "cavity_volume_mm3") if k not in over]
            if missing:
                raise DesignError(f"arms.{n}.{missing[0]}: missing (a new arm needs direction and cavity_volume_mm3)")
            a = ArmParams(n, over["direction"], over["cavity_volume_mm3"])
        if surface and "junction_fillet_mm" not in over:
            a = dataclasses.replace(a, junction_fillet_mm=0.0)  # OCC fillets smooth surfaces only
        arms.append(dataclasses.replace(a, **over))
    return tuple(arms)


def _cavities_from_dict(data: dict[str, Any], default: tuple) -> tuple:
    """The internal cavities of a design file: ``[urethra]`` (the BIP's; kept by default) and the
    ``[cavities.NAME]`` tables, in ``cavity_names`` order (default: the urethra, then the tables').
    Giving ``[cavities]`` without ``[urethra]`` leaves the urethra out (``cavities = {}``: none)."""
    given_u, given_c = data.get("urethra"), data.get("cavities")
    if given_u is not None:
        _check_keys("urethra", given_u, None)
        if "role" in given_u:
            raise DesignError(f"urethra.role = {given_u['role']!r}: the [urethra] is actuated (its pressure a known "
                              "load); a measured capsule is a [cavities.NAME] table with role = \"measured\"")
    base_u = next((c for c in default if isinstance(c, UrethraParams)), None) or UrethraParams()
    if given_c is None:
        if given_u is None:
            return default
        return (dataclasses.replace(base_u, **given_u),)
    if not isinstance(given_c, dict):
        raise DesignError(f"cavities: expected tables [cavities.NAME] (shape = capsule or ellipsoid), got {given_c!r}")
    cavs = []
    if given_u is not None:
        if "urethra" in given_c:
            raise DesignError("cavities.urethra: the urethra is also given as [urethra] (keep one)")
        cavs.append(dataclasses.replace(base_u, **given_u))
    for name, spec in given_c.items():
        where = f"cavities.{name}"
        _check_keys(where, spec, None)
        shape = spec.get("shape", "capsule")
        if shape not in _CAVITY_KEYS:
            raise DesignError(f"{where}.shape = {shape!r}: expected capsule or ellipsoid")
        _check_keys(where, spec, _CAVITY_KEYS[shape])
        missing = [k for k in _CAVITY_NEEDS[shape] if k not in spec]
        if missing:
            raise DesignError(f"{where}.{missing[0]}: missing (a {shape} cavity needs {', '.join(_CAVITY_NEEDS[shape])})")
        cls = CapsuleCavity if shape == "capsule" else EllipsoidCavity
        cavs.append(cls(name=str(name), **spec))
    order = data.get("cavity_names")
    if order is not None:
        have = [c.name for c in cavs]
        if not (isinstance(order, list) and all(isinstance(n, str) for n in order)):
            raise DesignError(f"cavity_names: expected a list of names, got {order!r}")
        if sorted(order) != sorted(have):
            raise DesignError(f"cavity_names: {order} must list each internal cavity once ({', '.join(have) or 'none'})")
        cavs = [cavs[have.index(n)] for n in order]
    return tuple(cavs)


def design_from_dict(data: dict[str, Any]) -> BIPDesign:
    """A design from a nested dict; missing keys keep their defaults, ``markers``/``targets``/``contacts``
    replace them."""
    _check_keys("design", data, ["name", "arm_names", "arms", "cavities", "cavity_names", "markers", "targets",
                                 "contacts", "materials", "region_materials", "layers", "snap_to_surface", *_SUBS])
    snap = data.get("snap_to_surface", False)
    if not isinstance(snap, bool):
        raise DesignError(f"snap_to_surface: expected true or false, got {snap!r}")
    default = _default_design()
    defaults = {f.name: getattr(default, f.name) for f in dataclasses.fields(BIPDesign)}
    kwargs: dict[str, Any] = dict(defaults)
    if "name" in data:
        kwargs["name"] = data["name"]
    kwargs["cavities"] = _cavities_from_dict(data, defaults["cavities"])
    for sub in _SUBS:
        if sub in data and sub != "urethra":
            _check_keys(sub, data[sub], None)
            if sub == "bulb" and data[sub].get("shape", "ellipsoid") != "ellipsoid":
                given = next((k for k in ("surface_vertices_mm", "surface_faces") if k in data[sub]), None)
                if given:
                    raise DesignError(f"bulb.{given}: not with shape = {data[sub]['shape']!r} (its triangles are "
                                      "derived from semi_axes_mm, exponents and bend_mm)")
            kwargs[sub] = dataclasses.replace(defaults[sub], **data[sub])
    if "layers" in data:
        lay = data["layers"]
        _check_keys("layers", lay, ["shell_mm", "lesions"])
        lesions = lay.get("lesions", {})
        if not isinstance(lesions, dict):
            raise DesignError(f"layers.lesions: expected a table of named lesions, got {lesions!r}")
        les = []
        for name, spec in lesions.items():
            _check_keys(f"layers.lesions.{name}", spec, ["center_mm", "semi_axes_mm"])  # the name is the table's
            les.append(LesionParams(name=str(name), **spec))
        kwargs["layers"] = LayersParams(shell_mm=lay.get("shell_mm", 0.0), lesions=tuple(les))
    kwargs["arms"] = _arms_from_dict(data, defaults["arms"], kwargs["bulb"].is_surface)
    for key in ("markers", "targets", "contacts"):
        if key in data:
            if not isinstance(data[key], dict):
                raise DesignError(f"{key}: expected a table of name = [x, y, z]")
            kwargs[key] = tuple(data[key].items())
    if "materials" in data:
        mats = data["materials"]
        if not isinstance(mats, dict):
            raise DesignError("materials: expected tables [materials.NAME] with law = ... and parameters")
        specs = []
        for name, tbl in mats.items():
            if not isinstance(tbl, dict):
                raise DesignError(f"materials.{name}: expected a table")
            if "law" not in tbl:
                raise DesignError(f"materials.{name}.law: missing (corotational, neo-hookean or yeoh)")
            specs.append(MaterialSpec(name, tbl["law"], tuple((k, v) for k, v in tbl.items() if k != "law")))
        kwargs["materials"] = tuple(specs)
    if "region_materials" in data:
        if not isinstance(data["region_materials"], dict):
            raise DesignError("region_materials: expected a table region = material name")
        kwargs["region_materials"] = tuple(data["region_materials"].items())
    if snap:
        _snap_to_surface(kwargs, data)
    return BIPDesign(**kwargs)


def _snap_to_surface(kwargs: dict[str, Any], data: dict[str, Any]) -> None:
    """``snap_to_surface = true``: the file's markers, contact points and internal cavities' inlets
    moved to the closest point of the body's surface (each move logged); the saved design holds
    the moved points."""
    import logging

    bulb: BulbParams = kwargs["bulb"]
    log = logging.getLogger(__name__)

    def onto(path: str, xyz) -> Vec3:
        q = bulb.closest_surface_point([xyz])[0]
        moved = float(np.linalg.norm(q - np.asarray(xyz, float)))
        if moved > 1e-9:
            log.info("snap_to_surface: %s moved %.3g mm onto the surface, to [%s]", path, moved,
                     ", ".join(f"{x:.4f}" for x in q))
        return tuple(float(x) for x in q)  # type: ignore[return-value]

    for key, check in (("markers", lambda v: _named_points("markers", v)), ("contacts", _contact_points)):
        if key in data:
            kwargs[key] = tuple((n, onto(f"{key}.{n}", xyz)) for n, xyz in check(kwargs[key]))
    if "urethra" in data or "cavities" in data:
        kwargs["cavities"] = tuple(dataclasses.replace(c, inlet_mm=onto(f"{c.path}.inlet_mm", c.inlet_mm))
                                   for c in kwargs["cavities"])


def load_design(path: str | Path) -> BIPDesign:
    """Read a design from a ``.toml`` or ``.json`` file (partial files override the defaults)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DesignError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise DesignError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise DesignError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'} ({exc})") from None
    if not data:  # a blank file would silently be the default design
        raise DesignError(f"{path}: empty design file (no key and no table); leave the file out for the default design")
    return design_from_dict(data)


def design_to_toml(design: BIPDesign) -> str:
    """The design as TOML text (tomli-w): one table per part, one line per scalar and per vector
    component, so a changed value is a one-line diff.

    >>> print(design_to_toml(BIPDesign()).splitlines()[2])
    [bulb]
    """
    return tomli_w.dumps(design_to_dict(design))


def save_design(design: BIPDesign, path: str | Path) -> Path:
    """Write ``design`` as TOML (or JSON for a ``.json`` suffix); floats round-trip exactly."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(design_to_dict(design), indent=2) + "\n", encoding="utf-8")
    else:
        path.write_text(design_to_toml(design), encoding="utf-8")
    return path
