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

This module is the design as a whole; its parts (each checking its own fields) are in
design/parts.py, the checks across them in design/checks.py, the geometry derived from them in
design/derived.py and the files in design/io.py. It re-exports their public names.

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
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import SkipValidation, Strict

from softphantom.design.checks import (
    ARM_END_CLEARANCE_MM,
    _validate_arm_names,
    _validate_cavity_names,
    _validate_geometry,
    _validate_layers,
    _validate_materials,
)
from softphantom.design.derived import ArmGeometry, _arm_geometry, _p_ext
from softphantom.design.fabrication import MoldParams
from softphantom.design.io import design_kwargs, design_to_dict, design_to_toml, read_design_file, save_design
from softphantom.design.parts import (  # the parts, re-exported
    BULB_VOLUME_MM3, CAVITY_NAMES, CAVITY_TYPES, CAVITY_VOLUME_HORIZONTAL_MM3, CAVITY_VOLUME_VERTICAL_MM3,
    DEFAULT_JUNCTION_FILLET_MM, DEFAULT_MATERIAL, DERIVED_CONTACTS, MATERIAL_PRESETS, MAX_CAVITY_SEGMENTS, MIN_ARMS,
    MIN_MARKER_SPREAD_MM, MIN_MARKERS, MIN_WALL_MM, REGION_NAMES, RESERVED_NAMES, SURFACE_TOL_MM, URETHRA_VOLUME_MM3,
    ArmParams, BulbParams, CapsuleCavity, EllipsoidCavity, InteractionParams, LayersParams, LesionParams,
    MaterialSpec, MeshParams, SensorParams, UrethraParams, Vec3, _contact_points, _default_arms, _default_markers,
    _default_materials, _default_region_materials, _default_targets, _named_points, _set, check_contact
)
from softphantom.errors import DesignError
from softphantom.records.names import ARM_NAMES
from softphantom.schema import Field, checked

__all__ = [
    "ARM_END_CLEARANCE_MM", "ARM_NAMES", "BULB_VOLUME_MM3", "CAVITY_NAMES", "CAVITY_TYPES",
    "CAVITY_VOLUME_HORIZONTAL_MM3", "CAVITY_VOLUME_VERTICAL_MM3", "DEFAULT_JUNCTION_FILLET_MM", "DEFAULT_MATERIAL",
    "DERIVED_CONTACTS", "MATERIAL_PRESETS", "MAX_CAVITY_SEGMENTS", "MIN_ARMS", "MIN_MARKERS", "MIN_MARKER_SPREAD_MM",
    "MIN_WALL_MM", "REGION_NAMES", "RESERVED_NAMES", "SURFACE_TOL_MM", "URETHRA_VOLUME_MM3", "ArmGeometry",
    "ArmParams", "BIPDesign", "BulbParams", "CapsuleCavity", "EllipsoidCavity", "InteractionParams", "LayersParams",
    "LesionParams", "MaterialSpec", "MeshParams", "MoldParams", "SensorParams", "UrethraParams", "Vec3",
    "check_contact", "design_from_dict", "design_to_dict", "design_to_toml", "load_design", "save_design",
]


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


@functools.cache
def _default_design() -> BIPDesign:
    return BIPDesign()  # frozen: one validated instance serves every design_from_dict


def design_from_dict(data: dict[str, Any]) -> BIPDesign:
    """A design from a nested dict; missing keys keep their defaults, ``markers``/``targets``/``contacts``
    replace them.

    >>> design_from_dict(design_to_dict(BIPDesign())) == BIPDesign()
    True
    """
    return BIPDesign(**design_kwargs(data, _default_design()))


def load_design(path: str | Path) -> BIPDesign:
    """Read a design from a ``.toml`` or ``.json`` file (partial files override the defaults)."""
    return design_from_dict(read_design_file(path))
