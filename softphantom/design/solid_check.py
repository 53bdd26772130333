"""Is a triangle mesh a clean solid? Closed, manifold, not self-intersecting; do two solids interfere?

- closed and oriented: trimesh (every edge shared by exactly two faces, winding consistent,
  positive volume);
- manifold: manifold3d accepts the mesh (``status() == NoError``) and its volume agrees;
- not self-intersecting: no edge of a triangle crosses another triangle that shares no vertex
  with it (candidate pairs: overlapping face boxes, from a uniform grid; orientation tests in numpy);
- interference (:func:`softphantom.molds.interference`): the volume of the manifold3d intersection
  of two parts, from :func:`to_manifold`.

Used on every printed part (softphantom.molds) and on an anatomy surface (design/anatomy_import.py).

>>> import trimesh
>>> report_mesh(trimesh.creation.box((10, 10, 10))).ok
True
>>> two = trimesh.util.concatenate([trimesh.creation.box((10, 10, 10)),
...                                 trimesh.creation.box((10, 10, 10)).apply_translation((5.0, 4.1, 3.3))])
>>> r = report_mesh(two); r.watertight, r.self_intersections > 0
(True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshReport:
    """What the checks found on one closed triangle mesh (volume in mm³ for mm meshes)."""

    watertight: bool
    winding_consistent: bool
    manifold: bool
    self_intersections: int
    volume: float
    components: int

    @property
    def ok(self) -> bool:
        return (self.watertight and self.winding_consistent and self.manifold
                and self.self_intersections == 0 and self.volume > 0.0 and self.components == 1)

    def problem(self) -> str | None:
        """The first problem in words, or None."""
        if not self.watertight:
            return "not closed (an edge is not shared by exactly two faces)"
        if not self.winding_consistent:
            return "inconsistent face orientation"
        if not self.manifold:
            return "not a manifold solid"
        if self.self_intersections:
            return f"self-intersecting ({self.self_intersections} crossing triangle pairs)"
        if self.components != 1:
            return f"{self.components} disconnected pieces"
        if not self.volume > 0.0:
            return f"inside out (volume {self.volume:.4g})"
        return None


def to_manifold(mesh):
    """A manifold3d solid of a trimesh (float64 kept through Mesh64 where available)."""
    import manifold3d as m3

    ctor = getattr(m3, "Mesh64", None)
    if ctor is not None:
        mm = ctor(vert_properties=np.array(mesh.vertices, np.float64, order="C"),  # writable copies
                  tri_verts=np.array(mesh.faces, np.uint64, order="C"))
    else:  # pragma: no cover - older manifold3d
        mm = m3.Mesh(vert_properties=np.asarray(mesh.vertices, np.float32), tri_verts=np.asarray(mesh.faces, np.uint32))
    return m3.Manifold(mm)


def from_manifold(solid):
    """The trimesh of a manifold3d solid (float64 where available)."""
    import trimesh

    mm = solid.to_mesh64() if hasattr(solid, "to_mesh64") else solid.to_mesh()
    return trimesh.Trimesh(np.ascontiguousarray(mm.vert_properties[:, :3], float), np.asarray(mm.tri_verts, np.int64),
                           process=False)


def manifold_volume(solid) -> float:
    return float(solid.volume())


def _orient(a, b, c, d):
    """Sign of the volume of (a, b, c, d), row-wise."""
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))


def overlapping_boxes(lo, hi):
    """(a, b), a < b: the pairs of boxes (rows of lo, hi) that overlap or touch.

    A uniform grid of cells about twice the median box size (a few times faster than an R-tree on
    the tens of thousands of facets of a mold): every box is listed in each cell it touches, and a
    pair is kept in the one cell that holds the low corner of the two boxes' overlap.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    n = len(lo)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    origin = lo.min(axis=0)
    extent = float((hi.max(axis=0) - origin).max())
    # at most 1e6 cells a side (the cell key fits int64); coarser while a few large boxes would
    # fill more than 16 cells per box on average
    size = max(2.0 * float(np.median(np.max(hi - lo, axis=1))), 1e-6 * extent) or 1.0
    while True:
        c0 = np.floor((lo - origin) / size).astype(np.int64)
        c1 = np.floor((hi - origin) / size).astype(np.int64)
        span = c1 - c0 + 1
        if span.prod(axis=1, dtype=float).sum() <= 16 * n:
            break
        size *= 2.0
    count = span.prod(axis=1)
    box = np.repeat(np.arange(n), count)
    # the k-th cell of a box: k in mixed radix (span_x, span_y, span_z)
    k = np.arange(len(box)) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[box, 1], span[box, 2]
    cell = c0[box] + np.stack([k // (sy * sz), (k // sz) % sy, k % sz], axis=1)
    dims = c1.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key, box = key[order], box[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    size_of = np.diff(np.r_[start, len(key)])
    group_start = np.repeat(start, size_of)
    rank = np.arange(len(key)) - group_start
    later = np.repeat(size_of, size_of) - rank - 1  # members after this one in its cell
    i = np.repeat(np.arange(len(key)), later)
    j = i + 1 + (np.arange(len(i)) - np.repeat(np.cumsum(later) - later, later))
    a, b, kc = box[i], box[j], key[i]
    keep = np.all(np.maximum(lo[a], lo[b]) <= np.minimum(hi[a], hi[b]), axis=1)
    a, b, kc = a[keep], b[keep], kc[keep]
    corner = np.floor((np.maximum(lo[a], lo[b]) - origin) / size).astype(np.int64)
    keep = ((corner[:, 0] * dims[1] + corner[:, 1]) * dims[2] + corner[:, 2]) == kc
    a, b = a[keep], b[keep]
    return np.minimum(a, b), np.maximum(a, b)


def self_intersections(mesh) -> int:
    """Number of face pairs without a shared vertex whose triangles cross (edge through face)."""
    faces = np.asarray(mesh.faces)
    v = np.asarray(mesh.vertices, float)
    tri = v[faces]
    pad = 1e-9 * float(np.ptp(v, axis=0).max() or 1.0)
    fa, fb = overlapping_boxes(tri.min(axis=1) - pad, tri.max(axis=1) + pad)
    shared = (faces[fa][:, :, None] == faces[fb][:, None, :]).any(axis=(1, 2))
    return int(crossing(tri, fa[~shared], fb[~shared]).sum())


def crossing(tri, fa, fb):
    """Whether an edge of triangle ``tri[fa]`` passes through triangle ``tri[fb]`` or the reverse
    (strictly, up to a tolerance scaled to the extent of ``tri``)."""
    hit = np.zeros(len(fa), bool)
    if len(fa) == 0:
        return hit
    scale = float(np.ptp(tri.reshape(-1, 3), axis=0).max()) ** 3
    eps = 1e-12 * scale
    for p_idx, q_idx in ((fa, fb), (fb, fa)):
        t = tri[q_idx]
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            p0, p1 = tri[p_idx, e0], tri[p_idx, e1]
            s0 = _orient(t[:, 0], t[:, 1], t[:, 2], p0)
            s1 = _orient(t[:, 0], t[:, 1], t[:, 2], p1)
            crosses_plane = (s0 * s1 < -eps * eps) & (np.abs(s0) > eps) & (np.abs(s1) > eps)
            a = _orient(p0, p1, t[:, 0], t[:, 1])
            b = _orient(p0, p1, t[:, 1], t[:, 2])
            c = _orient(p0, p1, t[:, 2], t[:, 0])
            inside = ((a > eps) & (b > eps) & (c > eps)) | ((a < -eps) & (b < -eps) & (c < -eps))
            hit |= crosses_plane & inside
    return hit


def report_mesh(mesh) -> MeshReport:
    """Run every check on a closed triangle mesh."""
    import manifold3d as m3

    watertight = bool(mesh.is_watertight)
    winding = bool(mesh.is_winding_consistent)
    try:
        solid = to_manifold(mesh)
        manifold = solid.status() == m3.Error.NoError and not solid.is_empty()
    except Exception:  # manifold3d refuses malformed input with an exception
        manifold = False
    if manifold:
        manifold = abs(manifold_volume(solid) - float(mesh.volume)) <= 1e-6 * max(1.0, abs(float(mesh.volume)))
    n_comp = int(len(mesh.split(only_watertight=False))) if len(mesh.faces) else 0
    return MeshReport(
        watertight=watertight,
        winding_consistent=winding,
        manifold=manifold,
        self_intersections=self_intersections(mesh) if len(mesh.faces) else 0,
        volume=float(mesh.volume) if watertight else float("nan"),
        components=n_comp,
    )
