"""One printable solid from gmsh's OpenCASCADE kernel, as a triangle mesh (mm).

:func:`occ_solid` runs a builder ``build(occ) -> volume tag`` in a fresh gmsh model (booleans,
transforms), tessellates the one resulting volume's boundary with ``segments`` facets per full
circle of curvature (``Mesh.MeshSizeFromCurvature``) and returns a :class:`trimesh.Trimesh` with
outward normals. gmsh is one process-global library: the same lock as the design mesher
serialises it; deterministic with one thread and a fixed seed.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from softphantom.design.mesh import gmsh_error_line, gmsh_session
from softphantom.errors import MeshError

MAX_FACET_MM = 4.0  # flat faces need no fine facets; curved ones follow ``segments``
MIN_FACET_MM = 0.4  # below a printer's resolution: small radii get fewer facets


def affine_12(rotation: np.ndarray, translation) -> list[float]:
    """The 12 first entries (row major) of the 4×4 affine map x ↦ R·x + t, for occ.affineTransform."""
    m = np.hstack([np.asarray(rotation, float), np.asarray(translation, float).reshape(3, 1)])
    return [float(v) for v in m.ravel()]


def ellipsoid(occ, semi_axes, transform: list[float] | None = None) -> int:
    """An ellipsoid at the origin (a dilated unit sphere), optionally mapped by an affine transform."""
    tag = occ.addSphere(0.0, 0.0, 0.0, 1.0)
    occ.dilate([(3, tag)], 0.0, 0.0, 0.0, *semi_axes)
    if transform is not None:
        occ.affineTransform([(3, tag)], transform)
    return tag


def cone_along(occ, p0, p1, r0: float, draft_deg: float, grow: bool = True) -> int:
    """A truncated cone from ``p0`` (radius ``r0``) to ``p1``, radius changing by the draft angle."""
    p0 = np.asarray(p0, float)
    ax = np.asarray(p1, float) - p0
    dr = float(np.linalg.norm(ax)) * math.tan(math.radians(draft_deg))
    r1 = r0 + dr if grow else r0 - dr
    if abs(r1 - r0) < 1e-6:
        return occ.addCylinder(*p0, *ax, r0)
    return occ.addCone(*p0, *ax, r0, r1)


def one_volume(result, what: str) -> int:
    """The single volume of an occ boolean's result (MeshError if it split or vanished)."""
    out = [t for d, t in result[0] if d == 3]
    if len(out) != 1:
        raise MeshError(f"{what}: the boolean gave {len(out)} volumes, expected 1 (check the [molds] sizes)")
    return out[0]


def built_once(name: str, build: Callable, directory: str | Path) -> Callable:
    """Run ``build(occ)`` (returns one volume tag) once in its own gmsh model and keep the solid as
    an OCC BREP file in ``directory``; the builder returned imports that very solid into the
    current model, with the boolean tolerance ``build`` left (occ_shapes.junction_fillets raises it).
    For a solid that several parts are cut from or cast in (an arm's rounded body)."""
    path = Path(directory) / f"{name}.brep"
    with gmsh_session(f"softphantom_shape_{name}", f"shape {name!r}") as gmsh:
        vol = build(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        if [t for _, t in gmsh.model.getEntities(3)] != [vol]:
            raise MeshError(f"shape {name}: more than the one volume in the model")
        tolerance = gmsh.option.getNumber("Geometry.ToleranceBoolean")
        gmsh.write(str(path))

    def imported(occ) -> int:
        import gmsh

        gmsh.option.setNumber("Geometry.ToleranceBoolean", tolerance)
        return one_volume((occ.importShapes(str(path)),), name)

    return imported


def occ_solid(name: str, build: Callable, segments: float) -> "trimesh.Trimesh":  # noqa: F821
    """Run ``build(occ)`` (returns one volume tag) and tessellate that volume's boundary."""
    import trimesh

    with gmsh_session(f"softphantom_part_{name}", f"part {name!r}") as gmsh:
        for opt, value in (
            ("General.NumThreads", 1),
            ("Geometry.OCCParallel", 0),
            ("Mesh.RandomSeed", 1),
            ("Mesh.Algorithm", 6),
            ("Mesh.MeshSizeFromCurvature", float(segments)),
            ("Mesh.MeshSizeMin", MIN_FACET_MM),
            ("Mesh.MeshSizeMax", MAX_FACET_MM),
            ("Mesh.MeshSizeFromPoints", 0),
        ):
            gmsh.option.setNumber(opt, value)
        occ = gmsh.model.occ
        vol = build(occ)
        occ.synchronize()
        vols = [t for _, t in gmsh.model.getEntities(3)]
        if vols != [vol]:
            raise MeshError(f"part {name}: {len(vols)} volumes in the model, expected 1")
        try:
            gmsh.model.mesh.generate(2)
        except Exception as exc:  # gmsh's 2-D mesher fails on some faces at some facet counts
            raise MeshError(f"[molds] segments = {float(segments):g}: gmsh could not tessellate part {name!r} "
                            f"({gmsh_error_line(exc)}); try a nearby value") from None
        tags, coords, _ = gmsh.model.mesh.getNodes()
        pos = np.full(int(np.max(tags)) + 1, -1, dtype=np.int64)
        pos[np.asarray(tags, dtype=np.int64)] = np.arange(len(tags))
        xyz = np.asarray(coords, float).reshape(-1, 3)
        tris = []
        for dim, s in gmsh.model.getBoundary([(3, vol)], combined=False, oriented=True):
            types, _, ntags = gmsh.model.mesh.getElements(2, abs(s))
            for t, nt in zip(types, ntags):
                if t != 2:
                    raise MeshError(f"part {name}: surface {abs(s)} has non-triangle elements")
                tri = pos[np.asarray(nt, dtype=np.int64).reshape(-1, 3)]
                tris.append(tri)
    mesh = trimesh.Trimesh(xyz, consistent_surfaces(tris), process=True)
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0.0:
        mesh.invert()
    return mesh


def consistent_surfaces(tris: list[np.ndarray]) -> np.ndarray:
    """Flip whole surfaces so that every shared edge runs opposite ways in its two faces.

    gmsh orients each surface's triangles consistently within the surface but not always with
    the volume; a walk over the surfaces (a few dozen, not the faces) fixes the relative flips,
    the sign of the volume the global one (done by the caller).
    """
    # every directed edge with its surface; a shared edge appears in two surfaces, either the same
    # way round (one of them must flip) or the opposite way (they must flip alike)
    surf = np.concatenate([np.full(3 * len(t), s) for s, t in enumerate(tris)])
    a = np.concatenate([t[:, [0, 1, 2]].T.ravel() for t in tris]).astype(np.int64)
    b = np.concatenate([t[:, [1, 2, 0]].T.ravel() for t in tris]).astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((surf, hi, lo))
    lo, hi, surf, fwd = lo[order], hi[order], surf[order], (a < b)[order]
    same = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1]) & (surf[1:] != surf[:-1])
    s0, s1 = surf[:-1][same], surf[1:][same]
    opposite = fwd[:-1][same] == fwd[1:][same]  # the same direction in both: opposite flips
    differ: dict[int, dict[int, bool]] = {s: {} for s in range(len(tris))}
    for x, y, o in set(zip(s0.tolist(), s1.tolist(), opposite.tolist())):
        differ[x][y] = differ[x].get(y, False) or o
        differ[y][x] = differ[y].get(x, False) or o
    flip: list[bool | None] = [None] * len(tris)
    for start in range(len(tris)):
        if flip[start] is not None:
            continue
        flip[start] = False
        queue = [start]
        while queue:
            s = queue.pop()
            for o, opposite in differ[s].items():
                if flip[o] is None:
                    flip[o] = (not flip[s]) if opposite else flip[s]
                    queue.append(o)
    return np.vstack([t[:, ::-1] if f else t for t, f in zip(tris, flip)])
