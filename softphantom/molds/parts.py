"""The printable parts of a design (paper Fig. 5), built with gmsh's OpenCASCADE kernel, in mm.

Every part is one closed solid in the model frame (where it sits when assembled), with the
direction that goes down on the build plate (``down``):

- ``bulb_mold_lower`` / ``bulb_mold_upper``: a block around the bulb split at the plane
  z = the first internal cavity's centre (the BIP: the plane of the urethra core's rod; 0 without
  one), conical registration pins on the lower half and matching sockets (``clearance_mm`` bigger)
  in the upper one, a conical pour spout at the bulb's top and two vents, a hole for each core's
  rod and one for each marker socket;
- ``<cavity>_core`` (``urethra_core`` on the BIP), one per internal cavity: its shape (a capsule,
  or an ellipsoid balloon) and its holder rod, which runs out through the cavity's inlet and the
  mold wall (print it soluble, or cast it in wax: it is dissolved out). A capsule's rod starts on
  its axis at the point nearest the inlet, an ellipsoid's at its centre;
- ``marker_socket_<m>``: a post cast into the bulb at each marker point along the surface
  normal, ``depth`` below and ``height`` above the surface, with a blind hole for the marker pin;
- ``arm_mold_<arm>_a`` / ``_b``: a block around the part of the arm outside the bulb (its floor is
  the bulb's surface patch, so the arm fits the bulb it is glued to), split along the arm axis,
  with pins, spout and vent on the fixed end face and a hole for the core's stem;
- ``arm_core_<arm>`` (cast in silicone, paper §III-C) and its ``core_mold_<arm>_a`` / ``_b``:
  the cavity capsule and a stem that leaves the tube channel to the fixed end face;
- ``frame``: the four sockets the arms' fixed ends are glued into, on posts to a base plate.

The cast silicone pieces (``cast_bulb``, ``cast_arm_<arm>``) are built the same way: the bill of
materials and the assembly drawing use them.

An imported bulb (a triangle surface, design/anatomy.py) is a polyhedral solid of thousands of
faces, on which each OCC boolean takes tens of seconds: there OCC builds every part without the
bulb and manifold3d (exact mesh booleans) cuts or keeps the bulb's own triangles afterwards.
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass

import numpy as np

from softphantom.design import geometry as geo
from softphantom.design.params import MIN_WALL_MM, BIPDesign, BulbParams
from softphantom.errors import DesignError
from softphantom.design.occ_shapes import bulb_solid, capsule, junction_fillets
from softphantom.molds.occ import affine_12, built_once, cone_along, ellipsoid, occ_solid, one_volume

OVERHANG_MM = 8.0  # how far rods and stems stick out of a mold, to hold them


@dataclass(frozen=True)
class Part:
    """One solid: ``mesh`` (trimesh, mm, model frame), what it is and how it is made."""

    name: str
    kind: str  # "mold" | "core" | "insert" | "frame" | "cast"
    group: str  # the assembly it belongs to: "bulb", "arm_<arm>", "core_<arm>", "phantom"
    material: str
    mesh: object
    down: tuple[float, float, float]  # model-frame direction that faces the build plate

    @property
    def volume_mm3(self) -> float:
        return float(self.mesh.volume)

    def print_transform(self) -> np.ndarray:
        """4×4 map from the model frame to the print pose (``down`` → −z, bounding box at 0)."""
        import trimesh

        rot = trimesh.geometry.align_vectors(np.asarray(self.down, float), [0.0, 0.0, -1.0])
        pts = trimesh.transform_points(self.mesh.vertices, rot)
        rot[:3, 3] -= pts.min(axis=0)
        return rot

    def print_extents_mm(self) -> np.ndarray:
        import trimesh

        pts = trimesh.transform_points(self.mesh.vertices, self.print_transform())
        return np.ptp(pts, axis=0)


# materials (names used in the bill of materials)
PRINT_MATERIAL = "PLA or PETG (printed)"
SOLUBLE_MATERIAL = "PVA or BVOH (printed, water-soluble) or wax"
BULB_SILICONE = "Ecoflex 00-50"
ARM_SILICONE = "Ecoflex 00-50"
CORE_SILICONE = "Dragon Skin 30"
#: the bill of materials' names of the design's material presets (design.params.MATERIAL_PRESETS)
SILICONE_NAMES = {"ecoflex_00_50": "Ecoflex 00-50", "sorta_clear_12": "Sorta-Clear 12", "ecoflex_gel": "Ecoflex GEL"}


def _frame_of(direction) -> np.ndarray:
    """Columns (u, v, w): w along ``direction``; local coordinates are Rᵀ·(x − origin)."""
    u, v, w = geo.orthonormal_frame(direction)
    return np.column_stack([u, v, w])


def rod_start_mm(cavity) -> np.ndarray:
    """Where the holder rod of an internal cavity's core starts: on a capsule's axis segment at the
    point nearest the inlet (an end when the inlet lies beyond it, as the urethra's), at an
    ellipsoid's centre.

    >>> from softphantom.design.params import CapsuleCavity
    >>> c = CapsuleCavity("cs", radius_mm=5.0, volume_mm3=2880.0, center_mm=(10, 0, 0), axis=(0, 0, 1),
    ...                   inlet_mm=(30.0, 0.0, 4.0))
    >>> rod_start_mm(c).round(6).tolist()
    [10.0, 0.0, 4.0]
    """
    inlet = np.asarray(cavity.inlet_mm, float)
    if cavity.shape == "ellipsoid":
        return np.asarray(cavity.center_mm, float)
    a, b = (np.asarray(p, float) for p in cavity.segment_mm)
    ab = b - a
    t = float((inlet - a) @ ab / (ab @ ab)) if ab @ ab > 0.0 else 0.0
    if t <= 0.0 or t >= 1.0:  # an end itself (its exact coordinates)
        return a if np.linalg.norm(inlet - a) < np.linalg.norm(inlet - b) else b
    return a + t * ab


class _Builder:
    def __init__(self, design: BIPDesign):
        self.d = design
        self.m = design.molds
        self.seg = self.m.segments
        self.cl = self.m.clearance_mm
        self.draft = self.m.draft_deg
        self.cavities = tuple(design.cavities)
        # the bulb mold parts at the first cavity's centre plane: the BIP's urethra rod lies in it
        self.zp = float(self.cavities[0].center_mm[2]) if self.cavities else 0.0
        lo, hi = design.bulb.bounds_mm()
        self.box_lo, self.box_hi = lo - self.m.wall_mm, hi + self.m.wall_mm
        # each core's rod starts inside its cavity and leaves through the inlet and the mold wall
        self.rods: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}
        for c in self.cavities:
            start = rod_start_mm(c)
            d = geo.unit(np.asarray(c.inlet_mm, float) - start)
            self.rods[c.name] = (start, d, self._exit_length(start, d) + OVERHANG_MM)
        self._check_rods()
        self.arms = design.arm_geometry()

    def _check_rods(self) -> None:
        """Each rod's channel in the cast bulb keeps the minimum wall from every other cavity."""
        r = self.m.core_rod_radius_mm
        for c in self.cavities:
            start, d, _ = self.rods[c.name]
            reach = float(np.linalg.norm(np.asarray(c.inlet_mm, float) - start))
            pts = start + np.linspace(0.0, reach, max(2, int(reach / 0.25) + 1))[:, None] * d
            for o in self.cavities:
                if o is c:
                    continue
                gap = float(o.signed_distance(pts).min()) - r
                if gap < MIN_WALL_MM:
                    where = "cuts into" if gap < 0.0 else f"passes {gap:.3g} mm from"
                    raise DesignError(
                        f"{c.path}.inlet_mm: the molds' rod from the {c.name} core to its inlet (radius "
                        f"molds.core_rod_radius_mm = {r:g}) {where} the {o.name} cavity (min wall "
                        f"{MIN_WALL_MM:g} mm; move the inlet)")

    # --- helpers --------------------------------------------------------------------------
    def _exit_length(self, p, d) -> float:
        """Distance from ``p`` along unit ``d`` to beyond the bulb mold's block."""
        # leaves the box through the first slab it leaves: the smallest exit over the axes
        t = [max((self.box_lo[i] - p[i]) / d[i], (self.box_hi[i] - p[i]) / d[i]) for i in range(3) if abs(d[i]) > 1e-12]
        return min(t) + 1.0

    def _bulb(self, occ, transform=None) -> list[tuple[int, int]]:
        """The bulb as an OCC tool, or nothing for a surface bulb (see :meth:`_less_bulb`)."""
        return [] if self.d.bulb.is_surface else [(3, bulb_solid(occ, self.d.bulb, transform))]

    def _bulb_mesh(self, to_local: np.ndarray | None = None):
        """The surface bulb's own triangles (trimesh), optionally in an arm's frame (4×4)."""
        import trimesh

        bulb = trimesh.Trimesh(np.asarray(self.d.bulb.surface_vertices_mm), np.asarray(self.d.bulb.surface_faces),
                               process=False)
        return bulb.apply_transform(to_local) if to_local is not None else bulb

    def _less_bulb(self, mesh, to_local: np.ndarray | None = None):
        """``mesh`` less a surface bulb (manifold3d); ``mesh`` itself for an ellipsoid (cut by OCC)."""
        if not self.d.bulb.is_surface:
            return mesh
        from softphantom.design.solid_check import from_manifold, to_manifold

        return from_manifold(to_manifold(mesh) - to_manifold(self._bulb_mesh(to_local)))

    def _rod(self, occ, name: str, extra: float) -> int:
        start, d, length = self.rods[name]
        return occ.addCylinder(*start, *(d * length), self.m.core_rod_radius_mm + extra)

    def _rods(self, occ, extra: float) -> list[tuple[int, int]]:
        return [(3, self._rod(occ, c.name, extra)) for c in self.cavities]

    def _cavity_shape(self, occ, c) -> int:
        """An internal cavity's own solid (no rod)."""
        if c.shape == "ellipsoid":
            tag = ellipsoid(occ, c.semi_axes_mm)
            occ.translate([(3, tag)], *c.center_mm)
            return tag
        return capsule(occ, *c.segment_mm, c.radius_mm)

    def _core_tools(self, occ) -> list[tuple[int, int]]:
        """Every core's shape and rod, in the cavities' order (disjoint but for each shape and its rod)."""
        out = []
        for c in self.cavities:
            out += [(3, self._cavity_shape(occ, c)), (3, self._rod(occ, c.name, 0.0))]
        return out

    def _core(self, occ, c) -> int:
        return one_volume(occ.fuse([(3, self._cavity_shape(occ, c))], [(3, self._rod(occ, c.name, 0.0))]),
                          f"{c.name} core")

    def _surface_less(self, name: str, tools) -> object:
        """The surface bulb's triangles less each tool (disjoint OCC solids) by manifold3d."""
        from softphantom.design.solid_check import from_manifold, to_manifold

        solid = to_manifold(self._bulb_mesh())
        for k, build in enumerate(tools):
            solid = solid - to_manifold(occ_solid(f"{name}_tool_{k}", build, self.seg))
        return from_manifold(solid)

    def _marker_normals(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {k: (np.asarray(p, float), self.d.bulb.normal(p)) for k, p in self.d.markers}

    def _socket_hole(self, occ, p, n) -> int:
        r = self.m.marker_socket_radius_mm + self.cl
        start = p - 0.5 * n
        return occ.addCylinder(*start, *(n * self._exit_length(start, n)), r)

    def _keys(self, occ, positions, axis, grow_by: float) -> list[tuple[int, int]]:
        """Conical pins (grow_by = 0) or their sockets (grow_by = clearance) along ``axis``."""
        out = []
        h = self.m.key_height_mm + grow_by
        for p in positions:
            p = np.asarray(p, float)
            out.append((3, cone_along(occ, p, p + h * np.asarray(axis, float), self.m.key_radius_mm + grow_by,
                                      self.draft, grow=False)))
        return out

    def _vent_points(self) -> list[np.ndarray]:
        lo, hi = self.d.bulb.bounds_mm()
        out = []
        for y in (0.5 * lo[1], 0.5 * hi[1]):  # halfway to the front and to the back, at the top
            o = np.array([0.0, y, 0.0])
            out.append(o + self.d.bulb.ray_exit(o, (0.0, 0.0, 1.0)) * np.array([0.0, 0.0, 1.0]))
        return out

    # --- the bulb mold --------------------------------------------------------------------
    def _bulb_key_points(self) -> list[np.ndarray]:
        inset = self.m.key_radius_mm + self.cl + 1.5
        pts = []
        for sx in (-1, 1):
            for sy in (-1, 1):
                x = self.box_hi[0] - inset if sx > 0 else self.box_lo[0] + inset
                y = self.box_hi[1] - inset if sy > 0 else self.box_lo[1] + inset
                pts.append(np.array([x, y, self.zp]))
        for p in pts:
            if self.d.bulb.signed_distance([p])[0] < self.m.key_radius_mm + self.cl + 1.0:
                raise DesignError(f"molds.wall_mm = {self.m.wall_mm:.4g}: no room for the registration keys "
                                  "beside the bulb (raise wall_mm)")
        return pts

    def bulb_half(self, upper: bool):
        lo, hi, zp = self.box_lo, self.box_hi, self.zp
        markers = self._marker_normals()

        def build(occ):
            z0, z1 = (zp, hi[2]) if upper else (lo[2], zp)
            block = occ.addBox(lo[0], lo[1], z0, hi[0] - lo[0], hi[1] - lo[1], z1 - z0)
            tools = [*self._bulb(occ), *self._rods(occ, self.cl)]
            tools += [(3, self._socket_hole(occ, p, n)) for p, n in markers.values()]
            keys = self._bulb_key_points()
            if upper:
                top = np.array([0.0, 0.0, self.d.bulb.ray_exit((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))])
                tools.append((3, cone_along(occ, top - [0, 0, 1.0], [0.0, 0.0, hi[2] + 1.0],
                                            self.m.spout_radius_mm, self.draft)))
                for p in self._vent_points():
                    tools.append((3, cone_along(occ, p - [0, 0, 0.5], [p[0], p[1], hi[2] + 1.0],
                                                self.m.vent_radius_mm, self.draft)))
                tools += self._keys(occ, keys, (0, 0, 1), self.cl)
            vol = one_volume(occ.cut([(3, block)], tools), "bulb mold half")
            if not upper:
                vol = one_volume(occ.fuse([(3, vol)], self._keys(occ, keys, (0, 0, 1), 0.0)), "bulb mold pins")
            return vol

        name = "bulb_mold_upper" if upper else "bulb_mold_lower"
        return Part(name, "mold", "bulb", PRINT_MATERIAL, self._less_bulb(occ_solid(name, build, self.seg)),
                    (0.0, 0.0, -1.0))

    def cavity_core(self, name: str) -> Part:
        """The core of internal cavity ``name`` on its holder rod (``<name>_core``), in the bulb mold."""
        c = self.d.cavity(name)
        return Part(f"{name}_core", "core", "bulb", SOLUBLE_MATERIAL,
                    occ_solid(f"{name}_core", lambda occ: self._core(occ, c), self.seg),
                    tuple(-geo.orthonormal_frame(self.rods[name][1])[0]))

    def marker_socket(self, name: str) -> Part:
        p, n = self._marker_normals()[name]
        ms = self.m
        r_pin = 0.5 * ms.marker_socket_radius_mm

        def build(occ):
            post = occ.addCylinder(*(p - ms.marker_socket_depth_mm * n),
                                   *(n * (ms.marker_socket_depth_mm + ms.marker_socket_height_mm)),
                                   ms.marker_socket_radius_mm)
            hole = occ.addCylinder(*(p + 0.5 * n), *(n * (ms.marker_socket_height_mm + 1.0)), r_pin)
            return one_volume(occ.cut([(3, post)], [(3, hole)]), f"marker socket {name}")

        return Part(f"marker_socket_{name}", "insert", "bulb", PRINT_MATERIAL,
                    occ_solid(f"marker_socket_{name}", build, self.seg), tuple(-n))

    def cast_bulb(self) -> Part:
        markers = self._marker_normals()
        ms = self.m

        def socket(occ, p, n) -> int:
            return occ.addCylinder(*(p - ms.marker_socket_depth_mm * n), *(n * (ms.marker_socket_depth_mm + 1.0)),
                                   ms.marker_socket_radius_mm)

        if self.d.bulb.is_surface:  # the bulb's triangles less each tool (disjoint solids) by manifold3d
            tools = [lambda occ, c=c: self._core(occ, c) for c in self.cavities]
            tools += [lambda occ, p=p, n=n: socket(occ, p, n) for p, n in markers.values()]
            mesh = self._surface_less("cast_bulb", tools)
        else:
            def build(occ):
                tools = self._core_tools(occ) + [(3, socket(occ, p, n)) for p, n in markers.values()]
                return one_volume(occ.cut(self._bulb(occ), tools), "cast bulb")

            mesh = occ_solid("cast_bulb", build, self.seg)
        return Part("cast_bulb", "cast", "phantom", BULB_SILICONE, mesh, (0.0, 0.0, -1.0))

    # --- the two-step cast of a shelled design (shell first, then the infill) ----------------
    def _material(self, region: str) -> str:
        m = self.d.material_of_regions([region])[region]
        return SILICONE_NAMES.get(m, m)

    def _infill(self, occ) -> int:
        inner = self.d.layers.infill_semi_axes_mm(self.d.bulb.semi_axes_mm)
        return bulb_solid(occ, dataclasses.replace(self.d.bulb, semi_axes_mm=inner))

    def _lesion(self, occ, les) -> int:
        # an ellipsoid whatever the body's shape (not the body's exponents, bend or triangles)
        tag = bulb_solid(occ, BulbParams(semi_axes_mm=les.semi_axes_mm))
        occ.translate([(3, tag)], *les.center_mm)
        return tag

    def infill_core(self) -> Part:
        """The infill's shape on the cores' rods (each leaves a channel in the shell): in the bulb
        mold for the shell pour, then dissolved or melted out (print it soluble, or cast it in wax)
        before the infill is poured."""
        if not self.cavities:
            raise DesignError("layers.shell_mm: the molds hold the infill core by an internal cavity's rod; this "
                              "design has no internal cavity")

        def build(occ):
            return one_volume(occ.fuse([(3, self._infill(occ))], self._rods(occ, 0.0)), "infill core")

        return Part("infill_core", "core", "shell_pour", SOLUBLE_MATERIAL, occ_solid("infill_core", build, self.seg),
                    tuple(-geo.orthonormal_frame(self.rods[self.cavities[0].name][1])[0]))

    def cast_layers(self) -> list[Part]:
        """The silicone pieces of a multi-material bulb: shell (less the infill, its core's rod
        channels and the marker sockets), infill (less the cores and lesions), each lesion."""
        ms, lay = self.m, self.d.layers
        markers = self._marker_normals()
        out = []
        if lay.shell_mm > 0.0:
            def shell(occ):
                tools = [(3, self._infill(occ)), *self._rods(occ, 0.0)]
                tools += [(3, occ.addCylinder(*(p - ms.marker_socket_depth_mm * n),
                                              *(n * (ms.marker_socket_depth_mm + 1.0)), ms.marker_socket_radius_mm))
                          for p, n in markers.values()]
                return one_volume(occ.cut(self._bulb(occ), tools), "cast shell")

            out.append(Part("cast_shell", "cast", "phantom", self._material("shell"),
                            occ_solid("cast_shell", shell, self.seg), (0.0, 0.0, -1.0)))

        def infill(occ):
            body = [(3, self._infill(occ))] if lay.shell_mm > 0.0 else self._bulb(occ)
            return one_volume(occ.cut(body, self._core_tools(occ)), "cast infill")

        lesions = [Part(f"cast_{les.region}", "cast", "phantom", self._material(les.region),
                        occ_solid(f"cast_{les.region}", lambda occ, les=les: self._lesion(occ, les), self.seg),
                        (0.0, 0.0, -1.0)) for les in lay.lesions]
        if self.d.bulb.is_surface:  # no shell there (the design refuses one): the body less the cores
            mesh = self._surface_less("cast_infill", [lambda occ, c=c: self._core(occ, c) for c in self.cavities])
        else:
            mesh = occ_solid("cast_infill", infill, self.seg)
        if lesions:  # their voids by manifold3d: it orients inner shells inward (the tessellation does not)
            from softphantom.design.solid_check import from_manifold, to_manifold

            solid = to_manifold(mesh)
            for p in lesions:
                solid = solid - to_manifold(p.mesh)
            mesh = from_manifold(solid)
        return [*out, Part("cast_infill", "cast", "phantom", self._material("bulb"), mesh, (0.0, 0.0, -1.0)), *lesions]

    def lesion_half(self, les, upper: bool) -> Part:
        """A two-part mold of a lesion: a block split at its centre plane, pins on the lower half,
        the spout on the upper one."""
        c, s = np.asarray(les.center_mm, float), np.asarray(les.semi_axes_mm, float)
        room = 2.0 * (self.m.key_radius_mm + self.cl) + 3.0
        lo, hi = c - s - self.m.wall_mm - np.array([room, room, 0.0]), c + s + self.m.wall_mm + np.array([room, room, 0.0])
        inset = self.m.key_radius_mm + self.cl + 1.5
        keys = [np.array([x, y, c[2]]) for x in (lo[0] + inset, hi[0] - inset) for y in (lo[1] + inset, hi[1] - inset)]

        def build(occ):
            z0, z1 = (c[2], hi[2]) if upper else (lo[2], c[2])
            block = occ.addBox(lo[0], lo[1], z0, hi[0] - lo[0], hi[1] - lo[1], z1 - z0)
            tools = [(3, self._lesion(occ, les))]
            if upper:
                top = c + np.array([0.0, 0.0, s[2]])
                tools.append((3, cone_along(occ, top - [0, 0, 1.0], [top[0], top[1], hi[2] + 1.0],
                                            min(self.m.spout_radius_mm, 0.5 * min(s[:2])), self.draft)))
                tools += self._keys(occ, keys, (0, 0, 1), self.cl)
            vol = one_volume(occ.cut([(3, block)], tools), "lesion mold half")
            if not upper:
                vol = one_volume(occ.fuse([(3, vol)], self._keys(occ, keys, (0, 0, 1), 0.0)), "lesion mold pins")
            return vol

        name = f"lesion_mold_{les.name}_{'upper' if upper else 'lower'}"
        return Part(name, "mold", f"lesion_{les.name}", PRINT_MATERIAL, occ_solid(name, build, self.seg),
                    (0.0, 0.0, -1.0))

    # --- arms -----------------------------------------------------------------------------
    def _arm_local(self, g):
        """(R, origin, to_local 12-affine, floor z, cavity z range) of one arm in its frame."""
        R = _frame_of(g.direction)
        origin = np.asarray(g.root_mm, float)
        to_local = affine_12(R.T, -R.T @ origin)
        rim = geo.disk_rim_points(g.start_mm, g.direction, g.radius_mm, n=128)
        s = [self.d.bulb.ray_exit(p, g.direction) for p in rim]
        arm = next(a for a in self.d.arms if a.name == g.name)
        z_floor = min(s) - arm.embed_mm
        c0, c1 = ((np.asarray(q, float) - origin) @ R[:, 2] for q in g.cavity_segment_mm)
        return R, origin, to_local, z_floor, (min(c0, c1), max(c0, c1)), arm

    def _to_model(self, mesh, R, origin):
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = origin
        return mesh.apply_transform(T)

    def _half_width(self, r: float) -> float:
        return max(r + self.m.wall_mm, r + 2.0 * (self.m.key_radius_mm + self.cl) + 2.0)

    def _split_keys(self, r: float, z_lo: float, z_hi: float) -> list[np.ndarray]:
        y = r + 1.0 + self.m.key_radius_mm + self.cl
        inset = self.m.key_radius_mm + self.cl + 1.5
        return [np.array([0.0, sy * y, z]) for sy in (-1, 1) for z in (z_lo + inset, z_hi - inset)]

    def _split_halves(self, name, group, hw, z_lo, z_hi, r_key, cut_tools, R, origin, minus=None) -> list[Part]:
        """Two halves x < 0 (with pins along +x) and x > 0 (sockets) of a local block, less the
        mesh ``minus`` (local frame, manifold3d) if given."""
        keys = self._split_keys(r_key, z_lo, z_hi)
        out = []
        for side in ("a", "b"):
            def build(occ, side=side):
                x0 = -hw if side == "a" else 0.0
                block = occ.addBox(x0, -hw, z_lo, hw, 2 * hw, z_hi - z_lo)
                tools = cut_tools(occ)
                if side == "b":
                    tools += self._keys(occ, keys, (1, 0, 0), self.cl)
                vol = one_volume(occ.cut([(3, block)], tools), f"{name} half")
                if side == "a":
                    vol = one_volume(occ.fuse([(3, vol)], self._keys(occ, keys, (1, 0, 0), 0.0)), f"{name} pins")
                return vol

            mesh = occ_solid(f"{name}_{side}", build, self.seg)
            if minus is not None:
                from softphantom.design.solid_check import from_manifold, to_manifold

                mesh = from_manifold(to_manifold(mesh) - to_manifold(minus))
            mesh = self._to_model(mesh, R, origin)
            down = R[:, 0] if side == "a" else -R[:, 0]  # the parting face on the plate
            out.append(Part(f"{name}_{side}", "mold", group, PRINT_MATERIAL, mesh, tuple(down)))
        return out

    def arm_parts(self, g) -> list[Part]:
        with tempfile.TemporaryDirectory(prefix="softphantom_arm_") as tmp:
            return self._arm_parts(g, tmp)

    def _arm_parts(self, g, tmp: str) -> list[Part]:
        R, origin, to_local, z_floor, (c0, c1), arm = self._arm_local(g)
        ms, cl = self.m, self.cl
        r, rc, L = g.radius_mm, g.cavity_radius_mm, arm.length_mm
        hw = self._half_width(r)
        z_lo, z_hi = z_floor - ms.wall_mm, L + ms.wall_mm
        stem_end = z_hi + OVERHANG_MM

        def arm_out(occ):
            cyl = occ.addCylinder(0.0, 0.0, -arm.embed_mm, 0.0, 0.0, L + arm.embed_mm, r)
            bulb = self._bulb(occ, to_local)
            if not bulb:
                return cyl
            # the arm is cast with its junction fillet: the mold's floor rounds into the bulb's surface
            rings = junction_fillets(occ, bulb[0][1], [(cyl, (0.0, 0.0, 0.0), (0.0, 0.0, L), r)], [g.fillet_mm],
                                     what=f"arms.{g.name}.junction_fillet_mm")[0]
            out = one_volume(occ.cut([(3, cyl)], bulb), f"arm {g.name}")
            return one_volume(occ.fuse([(3, out)], [(3, t) for t in rings]), f"arm {g.name}") if rings else out

        # a surface bulb: the arm outside it by manifold3d, cut from the mold halves afterwards
        local = np.vstack([np.reshape(to_local, (3, 4)), [0.0, 0.0, 0.0, 1.0]])
        surface = self.d.bulb.is_surface
        arm_mesh = self._less_bulb(occ_solid(f"arm_{g.name}", arm_out, self.seg), local) if surface else None
        if not surface:  # the rounded body's booleans once, for both mold halves and the cast piece
            arm_out = built_once(f"arm_{g.name}", arm_out, tmp)

        def core(occ, grow: float):
            cap = capsule(occ, (0.0, 0.0, c0), (0.0, 0.0, c1), rc + grow)
            stem = occ.addCylinder(0.0, 0.0, c1, 0.0, 0.0, stem_end - c1, ms.stem_radius_mm + grow)
            return one_volume(occ.fuse([(3, cap)], [(3, stem)]), f"core {g.name}")

        def arm_tools(occ):
            spout_r = min(ms.spout_radius_mm, 0.35 * r)
            vent_r = min(ms.vent_radius_mm, 0.2 * r)
            return [
                *([] if surface else [(3, arm_out(occ))]),
                (3, occ.addCylinder(0.0, 0.0, c1, 0.0, 0.0, stem_end + 1.0 - c1, ms.stem_radius_mm + cl)),
                (3, cone_along(occ, (0.0, 0.55 * r, L - 1.0), (0.0, 0.55 * r, z_hi + 1.0), spout_r, self.draft)),
                (3, cone_along(occ, (0.0, -0.7 * r, L - 1.0), (0.0, -0.7 * r, z_hi + 1.0), vent_r, self.draft)),
            ]

        parts = self._split_halves(f"arm_mold_{g.name}", f"arm_{g.name}", hw, z_lo, z_hi, r, arm_tools, R, origin,
                                   minus=arm_mesh)
        core_mesh = self._to_model(occ_solid(f"arm_core_{g.name}", lambda occ: core(occ, 0.0), self.seg), R, origin)
        parts.append(Part(f"arm_core_{g.name}", "core", f"arm_{g.name}", CORE_SILICONE, core_mesh, tuple(R[:, 0])))

        # the core's own mold: around capsule and stem, a spout at the capsule's tip
        hw_c = self._half_width(rc)
        zc_lo, zc_hi = c0 - rc - ms.wall_mm, stem_end + ms.wall_mm

        def core_tools(occ):
            tip = c0 - rc
            return [(3, core(occ, 0.0)),
                    (3, cone_along(occ, (0.0, 0.0, tip + 1.0), (0.0, 0.0, zc_lo - 1.0),
                                   min(ms.spout_radius_mm, 0.6 * rc), self.draft))]

        parts += self._split_halves(f"core_mold_{g.name}", f"core_{g.name}", hw_c, zc_lo, zc_hi, rc, core_tools,
                                    R, origin)

        def cast(occ):
            return one_volume(occ.cut([(3, arm_out(occ))], [(3, core(occ, 0.0))]), f"cast arm {g.name}")

        cast_mesh = self._to_model(self._less_bulb(occ_solid(f"cast_arm_{g.name}", cast, self.seg), local),
                                   R, origin)
        parts.append(Part(f"cast_arm_{g.name}", "cast", "phantom", ARM_SILICONE, cast_mesh, tuple(-R[:, 2])))
        return parts

    # --- the frame ------------------------------------------------------------------------
    def frame(self) -> Part:
        ms, cl = self.m, self.cl
        fw = ms.frame_wall_mm
        post_r = fw + 1.0
        lo_b, hi_b = self.d.bulb.bounds_mm()
        a = float(max(-lo_b[0], hi_b[0]))
        socket_r = max(g.radius_mm for g in self.arms) + cl + fw
        side_x = a + socket_r + post_r + 6.0
        lows = []
        for g in self.arms:
            rim = geo.disk_rim_points(g.end_mm, g.direction, socket_r, n=64)
            lows.append(float(rim[:, 2].min()))
        z_top = min(min(lows), float(lo_b[2])) - 4.0

        def build(occ):
            pieces, bores, feet = [], [], []
            for g in self.arms:
                d, end = g.direction, np.asarray(g.end_mm, float)
                r_out = g.radius_mm + cl + fw
                base = end - ms.frame_socket_depth_mm * d
                pieces.append((3, occ.addCylinder(*base, *(d * (ms.frame_socket_depth_mm + fw)), r_out)))
                bores.append((3, occ.addCylinder(*(base - d), *(d * (ms.frame_socket_depth_mm + 1.0)),
                                                 g.radius_mm + cl)))
                bores.append((3, occ.addCylinder(*(end - d), *(d * (fw + 2.0)), ms.stem_radius_mm + cl)))
                back = end + (fw + post_r) * d
                pieces.append((3, occ.addCylinder(*(end + 0.5 * fw * d), *(back - end - 0.5 * fw * d), post_r)))
                if back[2] < 0.0 or abs(back[0]) > a + post_r + 2.0:
                    foot = back
                else:  # above the bulb: a beam out to the side first, clear of bulb and needle
                    foot = np.array([side_x if back[0] >= 0.0 else -side_x, back[1], back[2]])
                    # axis to axis: an end face on the post's or column's tangent plane touches it
                    # along a line, a face gmsh then fails to mesh for some segment counts
                    pieces.append((3, occ.addCylinder(*back, *(foot - back), 0.85 * post_r)))
                # crossing cylinders of equal radii touch at singular points (a non-manifold
                # edge in the mesh): the beam is thinner and the column thicker than the post
                top = foot + np.array([0.0, 0.0, post_r])
                pieces.append((3, occ.addCylinder(*top, 0.0, 0.0, z_top - 1.0 - top[2], 1.15 * post_r)))
                feet.append(foot)
            f = np.array(feet)
            lo, hi = f.min(axis=0) - post_r - 6.0, f.max(axis=0) + post_r + 6.0
            pieces.append((3, occ.addBox(lo[0], lo[1], z_top - 2 * fw, hi[0] - lo[0], hi[1] - lo[1], 2 * fw)))
            body = one_volume(occ.fuse(pieces[:1], pieces[1:]), "frame")
            return one_volume(occ.cut([(3, body)], bores), "frame sockets")

        return Part("frame", "frame", "phantom", PRINT_MATERIAL, occ_solid("frame", build, self.seg),
                    (0.0, 0.0, -1.0))


def build_parts(design: BIPDesign, bulb_only: bool = False) -> tuple[Part, ...]:
    """Every part of ``design`` (molds, cores, inserts, frame, and the cast pieces), in a fixed
    order; ``bulb_only``: the bulb mold's group alone (halves, one core per internal cavity,
    marker sockets)."""
    b = _Builder(design)
    parts = [b.bulb_half(upper=False), b.bulb_half(upper=True)]
    parts += [b.cavity_core(name) for name in design.internal_cavity_names]
    parts += [b.marker_socket(name) for name, _ in design.markers]
    if bulb_only:
        return tuple(parts)
    lay = design.layers
    if lay.shell_mm > 0.0:
        parts.append(b.infill_core())
    for les in lay.lesions:
        parts += [b.lesion_half(les, upper=False), b.lesion_half(les, upper=True)]
    parts += b.cast_layers() if not lay.is_default else [b.cast_bulb()]
    for g in b.arms:
        parts += b.arm_parts(g)
    parts.append(b.frame())
    return tuple(parts)
