"""The bulb as an OpenCASCADE solid (gmsh ``occ`` API), for the mesher and the molds, in mm.

An ellipsoid is a unit sphere dilated to its semi-axes; a superellipsoid a loft through splines
(design/shapes.py); a surface bulb (anatomy import) is a
polyhedral solid: one point per vertex, one line per edge shared by its two faces, one plane
surface per triangle, sewn into a volume, so booleans with the arms and cavities work as on the
ellipsoid. ``transform`` (12 numbers, row-major 3×4) maps it afterwards, e.g. into an arm's frame.

A capsule (cavity, core) is two spheres fused with a cylinder. OCC's spheres have their poles on
z: a cylinder that ends at a sphere's centre touches it tangentially along a great circle, which
the fuse cuts cleanly when that circle is a meridian or the equator (axis along x, y or z, or
well away from them) but into sliver faces when the axis is a fraction of a degree off an axis
(an imported, fitted urethra): degenerate tetrahedra and "Identical points in triangulation".
Such a capsule is built on the nearest coordinate axis and turned onto its own.
"""

from __future__ import annotations

import math

import numpy as np

from softphantom.errors import MeshError

FILLET_BOOLEAN_TOLERANCE_MM = 1e-3
"""Fuzzy tolerance of the booleans after :func:`junction_fillets`: a ring shares faces with the
bulb and its arm (coincident surfaces, not crossing ones), which OCC glues only with a fuzzy
value (on the default design 0 and 1e-4 mm left duplicate faces and zero-volume slivers)."""
SNAP_DEG = 10.0  # a capsule axis this close to a coordinate axis (but not on it) is built on it, then turned


def bulb_solid(occ, bulb, transform: list[float] | None = None) -> int:
    """Add the bulb of a :class:`~softphantom.design.params.BulbParams`; returns its volume tag."""
    if bulb.is_parametric:  # smooth, not its triangles (design/shapes.py)
        from softphantom.design.shapes import occ_body

        tag = occ_body(occ, bulb.semi_axes_mm, bulb.exponents, bulb.bend_mm)
    elif not bulb.is_surface:
        tag = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, tag)], 0.0, 0.0, 0.0, *bulb.semi_axes_mm)
    else:
        verts = np.asarray(bulb.surface_vertices_mm, float)
        pts = [occ.addPoint(*v) for v in verts]
        lines: dict[tuple[int, int], int] = {}
        surfaces = []
        for f in bulb.surface_faces:
            loop = []
            for i, j in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
                key = (min(i, j), max(i, j))
                if key not in lines:
                    lines[key] = occ.addLine(pts[key[0]], pts[key[1]])
                loop.append(lines[key] if i < j else -lines[key])
            surfaces.append(occ.addPlaneSurface([occ.addCurveLoop(loop)]))
        tag = occ.addVolume([occ.addSurfaceLoop(surfaces)])
    if transform is not None:
        occ.affineTransform([(3, tag)], transform)
    return tag


def _turn(frm: np.ndarray, to: np.ndarray) -> np.ndarray:
    """The rotation taking unit ``frm`` to unit ``to`` (Rodrigues; they are < 90° apart here)."""
    v, c = np.cross(frm, to), float(frm @ to)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def capsule(occ, a, b, r: float) -> int:
    """A capsule (cylinder with hemispherical ends) with axis [a, b]; returns its volume tag."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ax = b - a
    length = float(np.linalg.norm(ax))
    turn = None
    if length > 1e-9:
        w = ax / length
        k = int(np.argmax(np.abs(w)))
        e = np.zeros(3)
        e[k] = math.copysign(1.0, w[k])
        off = math.degrees(math.acos(min(1.0, abs(float(w[k])))))
        if 0.0 < off < SNAP_DEG:
            turn, b = _turn(e, w), a + length * e
            ax = b - a
    parts = [(3, occ.addSphere(*a, r)), (3, occ.addSphere(*b, r))]
    if length > 1e-9:
        parts.append((3, occ.addCylinder(*a, *ax, r)))
    out = [t for d, t in occ.fuse(parts[:1], parts[1:])[0] if d == 3]
    if len(out) != 1:
        raise MeshError(f"capsule fuse gave {len(out)} volumes, expected 1")
    if turn is not None:
        t = a - turn @ a  # turn about the end a
        occ.affineTransform([(3, out[0])], [float(x) for x in np.hstack([turn, t[:, None]]).ravel()])
    return out[0]


def seam_side(bulb, start, end, radius: float, n: int = 72) -> np.ndarray | None:
    """For a surface bulb: the side (a unit vector normal to the arm's axis) on which the seam of
    the arm's cylinder should run, the one of ``n`` where it crosses the bulb's triangles farthest
    from their edges; None for an ellipsoid. OCC's cylinder has a seam line (where its angle wraps
    round); where it crosses the surface on a triangle's edge, the cut makes two vertices µm apart
    there, and the tets between them slivers (0.01-0.05° on an imported gland whose edges lie in the
    arms' planes, as the template's arms' seams do)."""
    if not bulb.is_surface:
        return None
    from softphantom.design import geometry as geo
    from softphantom.design.surface import surface_mesh

    mesh = surface_mesh(bulb.surface_vertices_mm, bulb.surface_faces)
    start, end = np.asarray(start, float), np.asarray(end, float)
    u, v, d = geo.orthonormal_frame(end - start)
    phi = 2.0 * math.pi * np.arange(n) / n
    sides = np.outer(np.cos(phi), u) + np.outer(np.sin(phi), v)
    hits, ray, tri = mesh.ray.intersects_location(start + radius * sides, np.repeat(d[None], n, axis=0),
                                                  multiple_hits=True)
    corners = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[tri]]  # (hits, 3, 3)
    gap = np.full(n, np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        a, ab = corners[:, i], corners[:, j] - corners[:, i]
        t = np.clip(np.einsum("ij,ij->i", hits - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
        np.minimum.at(gap, ray, np.linalg.norm(hits - a - t[:, None] * ab, axis=1))
    gap[np.bincount(ray, minlength=n) == 0] = -np.inf  # a seam that never meets the surface: not chosen
    return sides[int(np.argmax(gap))]


def arm_cylinder(occ, start, end, radius: float, seam=None) -> int:
    """The cylinder from ``start`` to ``end``; with ``seam`` (a unit vector normal to its axis, see
    :func:`seam_side`) built on z and turned so that its seam runs on that side; returns its tag."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    if seam is None:
        return occ.addCylinder(*start, *(end - start), radius)
    length = float(np.linalg.norm(end - start))
    d = (end - start) / length
    tag = occ.addCylinder(0.0, 0.0, 0.0, 0.0, 0.0, length, radius)  # OCC puts its seam on +x
    from scipy.spatial.transform import Rotation

    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    sin = float(np.linalg.norm(axis))
    if sin < 1e-12:
        axis, sin = np.array([1.0, 0.0, 0.0]), 0.0  # d = ±z: a half turn about x for -z, none for +z
    angle = math.atan2(sin, float(z @ d))
    k = axis / np.linalg.norm(axis)
    local = Rotation.from_rotvec(angle * k).inv().apply(np.asarray(seam, float))  # the seam's side before the turn
    occ.rotate([(3, tag)], 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, math.atan2(float(local[1]), float(local[0])))
    occ.rotate([(3, tag)], 0.0, 0.0, 0.0, *k, angle)
    occ.translate([(3, tag)], *start)
    return tag


def _on_side(surface: int, root: np.ndarray, axis: np.ndarray, radius: float) -> bool:
    """Whether the face's parametric mid-point lies on the side of the cylinder (root, axis, radius)."""
    import gmsh

    lo, hi = gmsh.model.getParametrizationBounds(2, surface)
    p = np.array(gmsh.model.getValue(2, surface, [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])]))
    return abs(np.linalg.norm(np.cross(p - root, axis)) - radius) < 1e-6 * radius + 1e-9


def _arm_faces(faces: list[int], root, end, radius: float) -> tuple[set[int], set[int]]:
    """(side curves, end-cap curves) of one arm among a solid's ``faces``."""
    import gmsh

    axis = (end - root) / np.linalg.norm(end - root)
    side, cap = set(), set()
    for s in faces:
        kind = gmsh.model.getType(2, s)  # first: a centre of mass integrates over the face (slow on a fillet)
        if kind == "Plane" and np.linalg.norm(np.array(gmsh.model.occ.getCenterOfMass(2, s)) - end) < 1e-3:
            cap |= {abs(c) for _, c in gmsh.model.getBoundary([(2, s)], oriented=False)}  # the end disk
        elif kind == "Cylinder" and _on_side(s, root, axis, radius):
            side |= {abs(c) for _, c in gmsh.model.getBoundary([(2, s)], oriented=False)}
    return side, cap


def filleted_body(occ, bulb: int, arms: list[tuple], radii: list[float], what: str = "arms") -> tuple[int, list[float]]:
    """The bulb fused with the arms (copies; the inputs stay), each arm ``(cylinder tag, root, end
    centre, radius_mm)`` rounded into the bulb by its fillet radius (0: a sharp edge) with OCC's
    rolling-ball fillet. Returns the one volume's tag and, per arm, how far along its axis from
    the root its side starts (the fillet's upper tangent line, or the sharp junction; its highest
    point). Raises :class:`MeshError` starting with ``what`` when OCC cannot round the edges (a
    radius too big for the surface around them)."""
    import gmsh

    body, _ = occ.fuse(occ.copy([(3, bulb)]), [dt for a in arms for dt in occ.copy([(3, a[0])])])
    if len(body) != 1:
        raise MeshError(f"{what}: the bulb fused with the arms gave {len(body)} volumes, expected 1")
    spec = [(np.asarray(root, float), np.asarray(end, float), float(rad)) for _, root, end, rad in arms]

    def junctions(vol: int) -> list[list[int]]:
        occ.synchronize()
        faces = [abs(t) for _, t in gmsh.model.getBoundary([(3, vol)], oriented=False)]
        out = []
        for root, end, rad in spec:
            side, cap = _arm_faces(faces, root, end, rad)
            if not side - cap:
                raise MeshError(f"{what}: found no edge where an arm meets the bulb")
            out.append(sorted(side - cap))  # the side's other boundary: where it meets the bulb
        return out

    tag = body[0][1]
    edges = [(c, float(r)) for cs, r in zip(junctions(tag), radii) if r > 0.0 for c in cs]
    if edges:
        try:
            rounded = occ.fillet([tag], [c for c, _ in edges], [r for _, r in edges], removeVolume=True)
        except Exception as exc:  # OCC's failures arrive as a plain Exception
            raise MeshError(f"{what}: OCC cannot round the arm-bulb edges "
                            f"({(str(exc).splitlines() or ['?'])[0]}): a smaller radius") from None
        if len(rounded) != 1:
            raise MeshError(f"{what}: the fillet gave {len(rounded)} volumes, expected 1")
        tag = rounded[0][1]
    heights = []
    for cs, (root, end, _) in zip(junctions(tag), spec):
        axis = (end - root) / np.linalg.norm(end - root)
        top = -np.inf
        for c in cs:
            lo, hi = gmsh.model.getParametrizationBounds(1, c)
            pts = np.reshape(gmsh.model.getValue(1, c, list(np.linspace(lo[0], hi[0], 65))), (-1, 3))
            top = max(top, float(((pts - root) @ axis).max()))
        heights.append(top)
    return tag, heights


def junction_fillets(occ, bulb: int, arms: list[tuple], radii: list[float], what: str = "arms") -> list[list[int]]:
    """The fillet rings alone: :func:`filleted_body` less fresh copies of the bulb and the arms, per
    arm its ring's volume tags ([] for radius 0); the inputs stay. A ring shares faces with its
    arm and the bulb and ends in knife edges along its tangent lines (a casting's flared foot,
    not a mesh region). Leaves gmsh's boolean tolerance at :data:`FILLET_BOOLEAN_TOLERANCE_MM`
    for the caller's booleans with the rings (fusing a ring back onto its arm)."""
    import gmsh

    out: list[list[int]] = [[] for _ in arms]
    if not any(r > 0.0 for r in radii):
        return out
    rounded, _ = filleted_body(occ, bulb, arms, radii, what)
    tools = occ.copy([(3, bulb)]) + [dt for a in arms for dt in occ.copy([(3, a[0])])]
    gmsh.option.setNumber("Geometry.ToleranceBoolean", FILLET_BOOLEAN_TOLERANCE_MM)
    rings, _ = occ.cut([(3, rounded)], tools)
    roots = [np.asarray(a[1], float) for a in arms]
    for _, t in rings:
        c = np.array(occ.getCenterOfMass(3, t))
        k = int(np.argmin([np.linalg.norm(c - q) if r > 0 else np.inf for q, r in zip(roots, radii)]))
        out[k].append(t)
    for a, r, got in zip(arms, radii, out):
        # a ring lies within the square r × r revolved around the arm at r from its side
        if r > 0.0 and not 0.0 < sum(occ.getMass(3, t) for t in got) < 2 * np.pi * (a[3] + r) * r * r:
            raise MeshError(f"{what}: the fillet's boolean did not leave one ring at an arm")
    return out
