"""The bulb as an OpenCASCADE solid (gmsh ``occ`` API), for the mesher and the molds, in mm.

An ellipsoid is a unit sphere dilated to its semi-axes; a surface bulb (anatomy import) is a
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

SNAP_DEG = 10.0  # a capsule axis this close to a coordinate axis (but not on it) is built on it, then turned


def bulb_solid(occ, bulb, transform: list[float] | None = None) -> int:
    """Add the bulb of a :class:`~softphantom.design.params.BulbParams`; returns its volume tag."""
    if not bulb.is_surface:
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
