"""The parts of a design (:class:`~softphantom.design.params.BIPDesign`): the parameter tables of
a design file, each a frozen dataclass that checks its own fields on construction (the body, its
layers, the internal cavities, the arms, the interaction, the mesh sizes, the sensors, the
materials) and the named points. Checks across parts are in design/checks.py; the geometry
derived from them in design/derived.py; the files in design/io.py.

>>> ArmParams("front", (0.0, -1.0, 0.0), 500.0, wall_mm=0.5)
Traceback (most recent call last):
...
softphantom.errors.DesignError: arms.front.wall_mm = 0.5 is below the minimum wall of 1 mm
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from dataclasses import field
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AfterValidator, SkipValidation, Strict

from softphantom.design import geometry as geo
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
