"""A patient's gland from a label map (NIfTI) or a closed surface (STL/OBJ), in the model frame:
an :class:`Anatomy` (its surface, the urethra's and the lesions' fits). design/anatomy.py makes a
design of it.

Label map (read by nibabel; world coordinates from its affine, RAS+ mm as NIfTI defines them):
the gland (``bulb``) is the union of ``gland_labels`` (e.g. a data set's peripheral and
transition zones, 1 and 2) with the urethra's and the lesions' labels, or every non-zero voxel
without ``gland_labels``; label ``urethra_label`` (default 2) is the urethra, the labels in
``lesion_labels`` are lesions: each becomes a design lesion ``[layers.lesions.labelN]``, the
axis-aligned ellipsoid of its voxels' centroid and second moments (:func:`lesion_report` gives its
volume against the voxel count). The gland must be one connected component (26-connectivity). Its
surface: the mask resampled to ``resample_mm`` (linear), smoothed by a Gaussian of ``smooth_mm``,
marching cubes at the 0.5 level (scikit-image), then an even remesh at ``surface_size_mm`` by
gmsh (its surface classification and reparametrization). On MRI-like spacing (0.5 × 0.5 × 3 mm)
the enclosed volume stays within 2 % of the voxel count (tests/test_anatomy.py).

Surface file (trimesh): must be closed, consistently oriented and not self-intersecting
(design/solid_check.py); it is remeshed the same way.

Placement in the model frame (docs/architecture.md): the input's RAS axes are first turned to the
model's (x = left, y = superior = perineum → base, z = anterior); the gland's centroid goes to the
origin and its principal axes (of the enclosed volume's inertia) to the model axes they are
closest to. The urethra label's fit: centroid, principal axis, length along it, volume from the
voxel count. Bad input is one line naming the problem and the value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.errors import DesignError, FileFormatError

MAX_URETHRA_SHARE = 0.10
"""The most of the gland's voxels a urethra label may hold (a prostate's urethra: 1–3 %; the BIP's 2 %)."""

# RAS+ (NIfTI world) → model frame: x = left (−R), y = superior, z = anterior (a proper rotation)
RAS_TO_MODEL = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class AnatomyOptions:
    """How a label map or surface becomes a bulb (lengths in mm). ``gland_labels``: the labels
    whose union is the gland (with the urethra's and the lesions'); empty: every non-zero label."""

    gland_labels: tuple[int, ...] = ()
    urethra_label: int = 2
    lesion_labels: tuple[int, ...] = ()
    resample_mm: float = 1.0
    smooth_mm: float = 1.0
    surface_size_mm: float = 3.0


@dataclass(frozen=True)
class Anatomy:
    """A gland in the model frame, mm: its surface, the urethra fit and what the import measured."""

    vertices_mm: np.ndarray
    faces: np.ndarray
    urethra: dict | None  # center_mm, axis, radius_mm, volume_mm3, length_mm
    lesions: dict[int, dict]  # label → center_mm, volume_mm3 (voxels), semi_axes_mm, ... (_ellipsoid_fit)
    voxel_volume_mm3: float | None  # gland volume from the voxel count (label maps only)
    rotation: np.ndarray  # input frame → model frame
    translation: np.ndarray

    @property
    def volume_mm3(self) -> float:
        from softphantom.design.geometry import surface_enclosed_volume

        return surface_enclosed_volume(self.vertices_mm, self.faces)


def _components(mask: np.ndarray) -> tuple[int, list[int]]:
    from scipy import ndimage

    lab, n = ndimage.label(mask, structure=np.ones((3, 3, 3), bool))
    sizes = sorted(np.bincount(lab.ravel())[1:].tolist(), reverse=True)
    return n, sizes


def _marching_cubes(mask: np.ndarray, affine: np.ndarray, opt: AnatomyOptions):
    """Smoothed iso-surface of a binary mask, vertices in world mm (the affine applied)."""
    from scipy import ndimage
    from skimage import measure

    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    zoom = np.maximum(spacing / opt.resample_mm, 1.0)
    pad = int(math.ceil(3.0 * opt.smooth_mm / opt.resample_mm)) + 2
    f = ndimage.zoom(mask.astype(np.float32), zoom, order=1, mode="grid-constant", grid_mode=True)
    eff = np.asarray(f.shape) / np.asarray(mask.shape)  # actual zoom per axis
    f = np.pad(f, pad)
    f = ndimage.gaussian_filter(f, opt.smooth_mm / (spacing / eff))
    verts, faces, _, _ = measure.marching_cubes(f, 0.5)
    ijk = (verts - pad + 0.5) / eff - 0.5  # voxel-centre index coordinates of the original grid
    world = ijk @ affine[:3, :3].T + affine[:3, 3]
    if np.linalg.det(affine[:3, :3]) < 0.0:
        faces = faces[:, ::-1]
    return world, faces


def _coarsen(mesh, faces: int = 6000):
    """Quadric decimation (fast-simplification through trimesh) before the remesh: it keeps the
    shape and volume, and the remesh then runs on a few thousand triangles instead of 10⁵."""
    if len(mesh.faces) > faces:
        mesh = mesh.simplify_quadric_decimation(face_count=faces)
        mesh.remove_unreferenced_vertices()
    return mesh


def _geodesic_sphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the unit sphere: each face of an icosahedron split into n² triangles
    (a class I geodesic polyhedron), outward.

    >>> v, f = _geodesic_sphere(3)
    >>> len(v), len(f)  # 10 n² + 2 vertices, 20 n² faces
    (92, 180)
    """
    import trimesh

    ico = trimesh.creation.icosahedron()
    corners = np.asarray(ico.vertices)[np.asarray(ico.faces)]  # (20, 3, 3)
    ij = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    at = {k: m for m, k in enumerate(ij)}
    w = np.array([[1.0 - (i + j) / n, i / n, j / n] for i, j in ij])
    pts = np.einsum("pk,fkx->fpx", w, corners).reshape(-1, 3)
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    local = [(at[i, j], at[i + 1, j], at[i, j + 1]) for i in range(n) for j in range(n - i)]
    local += [(at[i + 1, j], at[i + 1, j + 1], at[i, j + 1]) for i in range(n) for j in range(n - i - 1)]
    faces = (np.arange(len(corners))[:, None, None] * len(ij) + np.array(local)[None]).reshape(-1, 3)
    # the points on shared edges come once per face: merge them
    _, first, inverse = np.unique(np.round(pts, 9), axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    faces = rank[inverse.ravel()][faces]
    verts = pts[first[order]]
    tri = verts[faces]
    if np.einsum("ij,ij->", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri[:, 0]) < 0.0:
        faces = faces[:, ::-1]
    return verts, faces


def _radial_remesh(mesh, size_mm: float, min_angle_deg: float = 20.0):
    """An even triangulation of ``mesh`` at about ``size_mm``: a geodesic sphere (n from the area)
    stretched by the surface's extents along its principal axes and cast from its centroid, each
    vertex where its ray leaves the surface. Each triangle lies in its own cone from the centroid,
    so the result cannot intersect itself. None where a ray meets the surface other than once (not
    star-shaped from the centroid) or a triangle's smallest angle is below ``min_angle_deg``."""
    import trimesh

    c = np.asarray(mesh.center_mass, float)
    _, axes = np.linalg.eigh(np.asarray(mesh.moment_inertia, float))
    extent = np.abs((np.asarray(mesh.vertices) - c) @ axes).max(axis=0)
    n = max(2, int(round(math.sqrt(mesh.area / (20.0 * math.sqrt(3.0) / 4.0 * size_mm**2)))))
    unit, faces = _geodesic_sphere(n)
    rays = (unit * extent) @ axes.T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    hits, ray, _ = mesh.ray.intersects_location(np.repeat(c[None], len(rays), axis=0), rays, multiple_hits=True)
    dist = np.einsum("ij,ij->i", hits - c, rays[ray])
    # a ray through an edge or a vertex reports the same point from each face there
    order = np.lexsort((dist, ray))
    r, d = ray[order], dist[order]
    distinct = np.ones(len(r), bool)
    distinct[1:] = (r[1:] != r[:-1]) | (np.diff(d) > 1e-6 * extent.max())
    if np.any(np.bincount(r[distinct], minlength=len(rays)) != 1):
        return None
    far = np.zeros(len(rays))
    np.maximum.at(far, ray, dist)
    out = trimesh.Trimesh(c + far[:, None] * rays, faces, process=False)
    if np.degrees(out.face_angles.min()) < min_angle_deg:
        return None
    return out


def _remesh(mesh, size_mm: float, what: str):
    """An even triangulation of a closed surface at about ``size_mm``: :func:`_radial_remesh`, or
    for a surface it refuses, gmsh's (the surface classified into patches, reparametrized and
    meshed again; on some decimated label maps that fails or does not return). Quadric decimation
    alone keeps the volume but leaves needle triangles (0.1° angles) that become degenerate tetrahedra."""
    out = _radial_remesh(mesh, size_mm)
    return out if out is not None else _gmsh_remesh(mesh, size_mm, what)


def _gmsh_remesh(mesh, size_mm: float, what: str):
    import trimesh

    from softphantom.design.mesh import gmsh_session

    with gmsh_session("softphantom_anatomy_remesh", f"the surface of {what}") as gmsh:
        for opt, value in (("General.NumThreads", 1), ("Mesh.RandomSeed", 1), ("Mesh.Algorithm", 6),
                           ("Mesh.MeshSizeMax", size_mm), ("Mesh.MeshSizeMin", size_mm),
                           ("Mesh.MeshSizeFromPoints", 0), ("Mesh.MeshSizeFromCurvature", 0)):
            gmsh.option.setNumber(opt, value)
        tag = gmsh.model.addDiscreteEntity(2)
        v = np.asarray(mesh.vertices, float)
        gmsh.model.mesh.addNodes(2, tag, list(range(1, len(v) + 1)), v.ravel().tolist())
        gmsh.model.mesh.addElementsByType(tag, 2, [], (np.asarray(mesh.faces) + 1).ravel().tolist())
        gmsh.model.mesh.classifySurfaces(math.radians(40.0), True, True, math.pi)
        gmsh.model.mesh.createGeometry()
        size = gmsh.model.mesh.field.add("MathEval")  # a constant size everywhere (gmsh t13)
        gmsh.model.mesh.field.setString(size, "F", f"{size_mm:.6g}")
        gmsh.model.mesh.field.setAsBackgroundMesh(size)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.model.mesh.generate(2)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        pos = np.full(int(np.max(tags)) + 1, -1, dtype=np.int64)
        pos[np.asarray(tags, dtype=np.int64)] = np.arange(len(tags))
        tris = []
        for _, s in gmsh.model.getEntities(2):
            types, _, ntags = gmsh.model.mesh.getElements(2, s)
            for t, nt in zip(types, ntags):
                if t == 2:
                    tris.append(pos[np.asarray(nt, dtype=np.int64).reshape(-1, 3)])
        xyz = np.asarray(coords, float).reshape(-1, 3)
    out = trimesh.Trimesh(xyz, np.vstack(tris), process=True)
    out.remove_unreferenced_vertices()
    trimesh.repair.fix_normals(out)
    return out


def _check_surface(mesh, what: str) -> None:
    from softphantom.design.solid_check import report_mesh

    r = report_mesh(mesh)
    if r.problem() is not None:
        raise DesignError(f"{what}: the surface is {r.problem()}")


def _placement(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(R, t): model = R·input + t, from the RAS turn, the centroid and the principal axes."""
    c = np.asarray(mesh.center_mass, float)
    inertia = RAS_TO_MODEL @ np.asarray(mesh.moment_inertia, float) @ RAS_TO_MODEL.T
    _, vecs = np.linalg.eigh(inertia)
    # match each principal axis to the model axis it is closest to, signs towards that axis
    best, best_score = None, -1.0
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        score = sum(abs(vecs[k, perm[k]]) for k in range(3))
        if score > best_score:
            best, best_score = perm, score
    rows = np.array([vecs[:, best[k]] * np.sign(vecs[k, best[k]] or 1.0) for k in range(3)])
    if np.linalg.det(rows) < 0.0:  # keep it a rotation: flip the least aligned axis
        k = int(np.argmin([abs(rows[i, i]) for i in range(3)]))
        rows[k] = -rows[k]
    R = rows @ RAS_TO_MODEL
    return R, -R @ c


def _capsule_fit(points_mm: np.ndarray, volume_mm3: float, extra_mm: float = 0.0) -> dict:
    """Centre, axis (towards +y), length and radius of the capsule holding ``volume_mm3``."""
    c = points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(points_mm - c, full_matrices=False)
    axis = vt[0] * (1.0 if vt[0][1] >= 0.0 else -1.0)
    proj = (points_mm - c) @ axis
    length = float(proj.max() - proj.min()) + extra_mm
    # V = π r² L − (2/3) π r³ for a capsule of total length L (monotone in r on [0, L/2])
    lo, hi = 0.0, 0.5 * length
    for _ in range(80):
        r = 0.5 * (lo + hi)
        if math.pi * r * r * length - 2.0 / 3.0 * math.pi * r**3 < volume_mm3:
            lo = r
        else:
            hi = r
    return {"center_mm": c, "axis": axis, "length_mm": length, "radius_mm": 0.5 * (lo + hi), "volume_mm3": volume_mm3}


def _ellipsoid_fit(points_mm: np.ndarray, voxel_axes_mm: np.ndarray, volume_mm3: float) -> dict:
    """The ellipsoid with the voxels' centroid and second moments (a solid ellipsoid's covariance
    has eigenvalues a²/5), each voxel counted as a uniform box (adds A·A^T/12, A its edge vectors
    in the model frame). The design's lesions are axis-aligned: ``semi_axes_mm`` come from the
    covariance's diagonal, ``principal_semi_axes_mm`` and ``tilt_deg`` (the largest angle between
    a principal axis and the model axis nearest it) say what that leaves out."""
    c = points_mm.mean(axis=0)
    d = points_mm - c
    cov = d.T @ d / len(points_mm) + voxel_axes_mm @ voxel_axes_mm.T / 12.0
    lam, vec = np.linalg.eigh(cov)
    tilt = float(np.degrees(np.arccos(np.clip(np.abs(vec).max(axis=0), -1.0, 1.0))).max())
    semi = np.sqrt(5.0 * np.diag(cov))
    return {"center_mm": c, "volume_mm3": float(volume_mm3), "semi_axes_mm": semi,
            "principal_semi_axes_mm": np.sqrt(5.0 * np.maximum(lam, 0.0)), "tilt_deg": tilt,
            "ellipsoid_mm3": float(4.0 / 3.0 * math.pi * np.prod(semi))}


def lesion_report(anatomy: "Anatomy") -> list[str]:
    """One line per lesion label: where it went in the design and how its ellipsoid compares with
    the voxel count."""
    out = []
    for lab, les in sorted(anatomy.lesions.items()):
        d = 100.0 * (les["ellipsoid_mm3"] / les["volume_mm3"] - 1.0)
        out.append(f"lesion label {lab} -> layers.lesions.{lesion_name(lab)}: centre "
                   f"({', '.join(f'{x:.1f}' for x in les['center_mm'])}) mm, semi-axes "
                   f"({', '.join(f'{x:.1f}' for x in les['semi_axes_mm'])}) mm; ellipsoid {les['ellipsoid_mm3']:.0f} mm³ "
                   f"vs {les['volume_mm3']:.0f} mm³ of voxels ({d:+.1f} %); principal axes {les['tilt_deg']:.0f}° "
                   "off the model's")
    return out


def lesion_name(label: int) -> str:
    return f"label{int(label)}"


def _gland_mask(data: np.ndarray, opt: AnatomyOptions, source: str) -> np.ndarray:
    """The gland's voxels: the union of ``gland_labels`` with the urethra's and the lesions' labels
    (both lie inside the gland), or every non-zero voxel without ``gland_labels``."""
    if not opt.gland_labels:
        return data > 0
    for lab in opt.gland_labels:
        if lab <= 0:
            raise DesignError(f"{source}: gland label {lab} must be > 0 (--gland-labels)")
        if lab == opt.urethra_label or lab in opt.lesion_labels:
            raise DesignError(f"{source}: gland label {lab} is also the urethra's or a lesion's label "
                              "(--gland-labels, --urethra-label 0 for none, --lesion-labels)")
        if not np.any(data == lab):
            raise DesignError(f"{source}: gland label {lab} has no voxels (--gland-labels; labels present: "
                              f"{sorted(int(x) for x in np.unique(data) if x > 0)[:10]})")
    extra = (opt.urethra_label,) if opt.urethra_label > 0 else ()
    return np.isin(data, (*opt.gland_labels, *extra, *opt.lesion_labels))


def _check_urethra_share(data: np.ndarray, mask: np.ndarray, opt: AnatomyOptions, source: str) -> None:
    """Refuse a urethra label that holds more of the gland than a urethra can (a zone of a zonal
    map taken for the urethra: label 2 is a transition zone in several public data sets)."""
    if not opt.urethra_label:
        return
    share = float(np.count_nonzero(data == opt.urethra_label)) / max(int(np.count_nonzero(mask)), 1)
    if share <= MAX_URETHRA_SHARE:
        return
    zones = sorted(int(x) for x in np.unique(data[mask]) if x > 0 and x not in opt.lesion_labels)
    fix = (f"if the labels are zones, give --gland-labels {','.join(map(str, zones))} (the urethra is then placed "
           "on the gland's axis), or --urethra-label for the urethra's own label" if not opt.gland_labels else
           "give --urethra-label for the urethra's own label (0: none)")
    raise DesignError(f"{source}: urethra label {opt.urethra_label} holds {share:.0%} of the gland, too much for a "
                      f"urethra (at most {MAX_URETHRA_SHARE:.0%}); {fix}")


def anatomy_from_labels(data: np.ndarray, affine: np.ndarray, opt: AnatomyOptions = AnatomyOptions(),
                        source: str = "label map") -> Anatomy:
    """A gland from an integer label map and its voxel → world (mm) affine."""
    import trimesh

    data = np.asarray(data)
    if data.ndim != 3:
        raise FileFormatError(f"{source}: expected a 3-D label map, got {data.ndim} dimensions")
    if not np.issubdtype(data.dtype, np.integer):
        if not np.all(np.isfinite(data)) or np.any(data != np.round(data)):
            raise FileFormatError(f"{source}: labels must be integers")
        data = data.astype(np.int64)
    mask = _gland_mask(data, opt, source)
    n, sizes = _components(mask)
    if n == 0:
        raise DesignError(f"{source}: no labelled voxels (the gland has 0 components)")
    if n > 1:
        raise DesignError(f"{source}: the gland has {n} disconnected components (voxel counts {sizes[:5]}); "
                          "expected one")
    _check_urethra_share(data, mask, opt, source)
    for lab in opt.lesion_labels:  # before the surface, the slow part
        if lab == opt.urethra_label or lab <= 0:
            raise DesignError(f"{source}: lesion label {lab} must be > 0 and not the urethra's ({opt.urethra_label})")
        if not np.any(data == lab):
            raise DesignError(f"{source}: lesion label {lab} has no voxels")
    voxel = float(abs(np.linalg.det(affine[:3, :3])))
    world, faces = _marching_cubes(mask, affine, opt)
    mc = trimesh.Trimesh(world, faces, process=True)
    if mc.volume < 0.0:
        mc.invert()
    mesh = _remesh(_coarsen(mc), opt.surface_size_mm, source)
    _check_surface(mesh, source)
    R, t = _placement(mesh)

    def to_model(ijk):
        return (np.asarray(ijk, float) @ affine[:3, :3].T + affine[:3, 3]) @ R.T + t

    urethra = None
    if opt.urethra_label and np.any(data == opt.urethra_label):
        idx = np.argwhere(data == opt.urethra_label)
        urethra = _capsule_fit(to_model(idx), len(idx) * voxel)
        # voxel centres span the length less one voxel along the axis
        axis_ijk = np.linalg.solve(affine[:3, :3], R.T @ urethra["axis"])
        urethra = _capsule_fit(to_model(idx), len(idx) * voxel,
                               extra_mm=float(np.linalg.norm(affine[:3, :3] @ (axis_ijk / np.abs(axis_ijk).max()))))
    lesions = {}
    for lab in opt.lesion_labels:
        idx = np.argwhere(data == lab)
        lesions[int(lab)] = _ellipsoid_fit(to_model(idx), R @ affine[:3, :3], len(idx) * voxel)
    v = np.asarray(mesh.vertices) @ R.T + t
    return Anatomy(v, np.asarray(mesh.faces), urethra, lesions, float(mask.sum()) * voxel, R, t)


def anatomy_from_surface(mesh, opt: AnatomyOptions = AnatomyOptions(), source: str = "surface") -> Anatomy:
    """A gland from a closed triangle surface (mm, RAS-oriented like a label map's world)."""
    for what, given in (("lesion", opt.lesion_labels), ("gland", opt.gland_labels)):
        if given:
            raise DesignError(f"{source}: {what} labels {list(given)} need a label map (a surface has none)")
    _check_surface(mesh, source)
    mesh = _remesh(_coarsen(mesh), opt.surface_size_mm, source)
    _check_surface(mesh, f"{source} (remeshed)")
    R, t = _placement(mesh)
    v = np.asarray(mesh.vertices) @ R.T + t
    return Anatomy(v, np.asarray(mesh.faces), None, {}, None, R, t)


def load_anatomy(path: str | Path, opt: AnatomyOptions = AnatomyOptions()) -> Anatomy:
    """Read a NIfTI label map (.nii, .nii.gz) or a surface (.stl, .obj, .ply)."""
    path = Path(path)
    name = path.name.lower()
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    if name.endswith((".nii", ".nii.gz")):
        import nibabel as nib

        try:
            img = nib.load(str(path))
            data = np.asanyarray(img.dataobj)
        except Exception as exc:
            raise FileFormatError(f"{path}: not a readable NIfTI file ({exc})") from None
        return anatomy_from_labels(data, np.asarray(img.affine, float), opt, source=str(path))
    if name.endswith((".stl", ".obj", ".ply")):
        import trimesh

        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as exc:
            raise FileFormatError(f"{path}: not a readable surface ({exc})") from None
        if not len(getattr(mesh, "faces", ())):
            raise FileFormatError(f"{path}: no triangles")
        return anatomy_from_surface(mesh, opt, source=str(path))
    raise FileFormatError(f"{path}: unknown anatomy format (expected .nii, .nii.gz, .stl, .obj or .ply)")
