"""A patient's prostate as the bulb of a design: a label map (NIfTI) or a closed surface (STL/OBJ).

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
closest to. The urethra (label) becomes the design's capsule: centroid, principal axis, length
along it, volume from the voxel count, radius from length and volume; without urethra voxels (or
from a surface) it lies along the principal axis the placement turned to y (the one nearest the
template's urethra axis) through the centroid (:func:`axis_urethra`). Its inlet is where its axis
leaves the bulb towards the base. The template's arms (lengths, radius, embedding, cavity offset)
and urethra radius are scaled by the cube root of the gland's volume over the template's
(:func:`part_scale`; cavity volumes by its cube; walls kept at the design's minimum or more), the
arms keep the design's directions and attach where those leave the new surface; markers are
re-projected along their directions; targets are scaled with the gland's extent. Bad input is one
line naming the problem and the value; a part that cannot be made valid is one line naming it and
what fixes it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.design import geometry as geo
from softphantom.design.params import MIN_WALL_MM, ArmParams, BIPDesign, BulbParams, UrethraParams
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


def import_report(anatomy: "Anatomy", template: BIPDesign, design: BIPDesign) -> list[str]:
    """What the import made of the template: the parts' scale, where the urethra came from, then
    :func:`lesion_report`'s lines."""
    u = design.urethra
    where = ("fitted to its label's voxels" if anatomy.urethra is not None else
             "not labelled, placed along the gland's principal axis through its centroid")
    head = f"parts: the template's arms{' and urethra radius' if u is not None else ''} scaled by " \
           f"{part_scale(anatomy, template):.3f} (the cube root of {anatomy.volume_mm3 / 1e3:.1f} mL over the " \
           f"template's {template.bulb.volume_mm3 / 1e3:.1f} mL)"
    if u is None:
        return [head, "urethra: none (--urethra none)", *lesion_report(anatomy)]
    return [head,
            f"urethra: {where}; radius {u.radius_mm:.2f} mm, length {u.cyl_length_mm + 2 * u.radius_mm:.1f} mm, "
            f"{u.volume_mm3:.0f} mm³, inlet ({', '.join(f'{x:.1f}' for x in u.inlet_mm)}) mm",
            *lesion_report(anatomy)]


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


def _project(bulb: BulbParams, name: str, direction, table: str = "markers") -> tuple[float, float, float]:
    s = bulb.ray_exit((0.0, 0.0, 0.0), direction)
    if s is None:
        raise DesignError(f"{table}.{name}: the direction {tuple(direction)} misses the gland")
    p = s * np.asarray(direction, float) / np.linalg.norm(direction)
    return tuple(float(x) for x in p)  # type: ignore[return-value]


def part_scale(anatomy: Anatomy, base: BIPDesign) -> float:
    """The factor on the template's lengths: the cube root of the gland's volume over the
    template bulb's (0.776 for a 47 mL gland against the paper's 100.41 mL)."""
    return float((anatomy.volume_mm3 / base.bulb.volume_mm3) ** (1.0 / 3.0))


def _scaled_cavity(cavity, s: float, scale: np.ndarray, bulb: BulbParams):
    """A template's internal cavity other than the urethra in the gland: its centre scaled with the
    gland's extent (as the targets), its size by ``s`` (volume by s³), its inlet projected onto the
    gland along its direction from the centre (as the markers)."""
    kw = {"center_mm": tuple(float(x) for x in np.asarray(cavity.center_mm) * scale),
          "inlet_mm": _project(bulb, cavity.name, cavity.inlet_mm, "cavities")}
    if cavity.shape == "ellipsoid":
        kw["semi_axes_mm"] = tuple(float(x) * s for x in cavity.semi_axes_mm)
    else:
        kw.update(radius_mm=cavity.radius_mm * s, volume_mm3=cavity.volume_mm3 * s**3)
    return dataclasses.replace(cavity, **kw)


def _scaled_arm(arm: ArmParams, s: float) -> ArmParams:
    """``arm`` with its lengths times ``s`` and its cavity volume times s³, its wall kept at the
    design's minimum or more; sharp junction (OCC rounds smooth surfaces only, not a triangulated
    gland's)."""
    return dataclasses.replace(
        arm, length_mm=arm.length_mm * s, radius_mm=arm.radius_mm * s, wall_mm=max(arm.wall_mm * s, MIN_WALL_MM),
        cavity_offset_mm=arm.cavity_offset_mm * s, embed_mm=arm.embed_mm * s,
        axis_point_mm=tuple(float(x) * s for x in arm.axis_point_mm), cavity_volume_mm3=arm.cavity_volume_mm3 * s**3,
        junction_fillet_mm=0.0)


def _chord(bulb: BulbParams, point, axis) -> tuple[float, float]:
    """(backward, forward) distances from ``point`` to where the line along ``axis`` leaves ``bulb``."""
    fwd, back = bulb.ray_exit(point, axis), bulb.ray_exit(point, -np.asarray(axis, float))
    if fwd is None or back is None or fwd <= 0.0 or back <= 0.0:
        raise DesignError(f"urethra: the line along {tuple(np.round(axis, 3))} through "
                          f"{tuple(np.round(point, 1))} mm does not cross the gland")
    return float(back), float(fwd)


def axis_urethra(bulb: BulbParams, template: BIPDesign, s: float) -> UrethraParams:
    """A urethra for a gland without a urethra label: along the model's y (the principal axis
    the placement turned there, the one nearest the template's +y) through the gland's centroid
    (the origin), centred on the chord it cuts; radius the template's times ``s``, total length the
    same fraction of that chord as the template's of its own (0.72 for the paper's BIP); the inlet
    where the axis leaves the gland at +y.

    >>> u = axis_urethra(BIPDesign().bulb, BIPDesign(), 1.0)  # the template itself: its radius, on y
    >>> u.radius_mm, u.axis, [round(x, 6) for x in u.center_mm]
    (4.5, (0.0, 1.0, 0.0), [0.0, 0.0, 0.0])
    """
    t = template.urethra
    ta, tb = t.segment_mm
    tback, tfwd = _chord(template.bulb, np.asarray(t.center_mm, float), geo.unit(t.axis))
    frac = (float(np.linalg.norm(tb - ta)) + 2.0 * t.radius_mm) / (tback + tfwd)
    axis = np.array([0.0, 1.0, 0.0])
    back, fwd = _chord(bulb, np.zeros(3), axis)
    r = t.radius_mm * s
    length = max(frac * (back + fwd), 2.0 * r + 1e-3)  # no shorter than its sphere
    c = 0.5 * (fwd - back) * axis
    return UrethraParams(radius_mm=r, volume_mm3=geo.capsule_volume(r, length - 2.0 * r),
                         center_mm=tuple(float(x) for x in c), axis=tuple(float(x) for x in axis),
                         inlet_mm=tuple(float(x) for x in c + bulb.ray_exit(c, axis) * axis))


def _fitted_urethra(bulb: BulbParams, u: dict) -> UrethraParams:
    c, axis = np.asarray(u["center_mm"]), np.asarray(u["axis"])
    s = bulb.ray_exit(c, axis)
    if s is None:
        raise DesignError("urethra: the urethra label's axis does not leave the gland")
    return UrethraParams(radius_mm=float(u["radius_mm"]), volume_mm3=float(u["volume_mm3"]),
                         center_mm=tuple(float(x) for x in c), axis=tuple(float(x) for x in axis),
                         inlet_mm=tuple(float(x) for x in c + s * axis))


#: what fixes a part the import could not make valid, by the part its message starts with
_FIXES = {
    "urethra": "a smaller [urethra] radius_mm in --config (the principal-axis urethra's, before the scaling), "
               "or a urethra label (--urethra-label)",
    "arms": "[arms.{name}] radius_mm, embed_mm or direction in --config (before the scaling)",
    "markers": "[markers] in --config (points whose directions from the centre miss the arms)",
    "contacts": "[contacts] in --config (points whose directions from the centre miss the arms)",
    "cavities": "[cavities.{name}] center_mm or size in --config (before the scaling)",
    "targets": "[targets] in --config",
    "interaction": "[interaction] offcentre_mm in --config",
    "layers": "--lesion-labels without that label",
}


def design_from_anatomy(anatomy: Anatomy, base: BIPDesign | None = None, name: str = "anatomy", *,
                        urethra: bool = True) -> BIPDesign:
    """``base`` (default: the paper's BIP) with the gland's surface and urethra (its label's fit,
    else :func:`axis_urethra`; ``urethra=False``: none, the template's dropped too, and a urethra
    label is refused); the arms and urethra radius scaled by :func:`part_scale`, markers
    and named contacts projected along their directions, targets and the other internal cavities'
    centres scaled with the gland's extent (the cavities' sizes by the part scale). A part that still
    cannot be made valid raises a one-line DesignError naming it and the option that fixes it."""
    base = base or BIPDesign()
    if not urethra and anatomy.urethra is not None:
        raise DesignError("urethra: the label map has a urethra label and --urethra none drops it "
                          "(--urethra-label 0 to import no urethra label)")
    s = part_scale(anatomy, base)
    try:
        return _design_from_anatomy(anatomy, base, name, s, urethra)
    except DesignError as exc:
        msg = str(exc)
        path = msg.split(":", 1)[0].split(" ", 1)[0].split(".")
        fix = _FIXES.get(path[0])
        if fix is None:
            raise
        fix = fix.format(name=path[1] if len(path) > 1 else "NAME")
        raise DesignError(f"{msg} [a {anatomy.volume_mm3 / 1e3:.1f} mL gland, the template's parts scaled by "
                          f"{s:.3f}; fix: {fix}]") from None


def _design_from_anatomy(anatomy: Anatomy, base: BIPDesign, name: str, s: float, with_urethra: bool) -> BIPDesign:
    v = anatomy.vertices_mm
    half = 0.5 * (v.max(axis=0) - v.min(axis=0))
    bulb = BulbParams(semi_axes_mm=tuple(float(x) for x in half),
                      surface_vertices_mm=tuple(tuple(float(x) for x in p) for p in v),
                      surface_faces=tuple(tuple(int(k) for k in f) for f in anatomy.faces))
    urethra = (None if not with_urethra else axis_urethra(bulb, base, s) if anatomy.urethra is None
               else _fitted_urethra(bulb, anatomy.urethra))
    markers = tuple((k, _project(bulb, k, p)) for k, p in base.markers)
    scale = half / np.asarray(base.bulb.semi_axes_mm)
    targets = []
    for k, p in base.targets:
        q = np.asarray(p) * scale
        if urethra is None:
            targets.append((k, tuple(float(x) for x in q)))
            continue
        # a target that the new urethra swallowed moves out radially to 3 mm from its wall
        ua, ub = urethra.segment_mm
        t = np.clip((q - ua) @ (ub - ua) / max(float((ub - ua) @ (ub - ua)), 1e-12), 0.0, 1.0)
        foot = ua + t * (ub - ua)
        if np.linalg.norm(q - foot) < urethra.radius_mm + 3.0:
            radial = q - foot
            if np.linalg.norm(radial) < 1e-9:
                radial = np.cross(ub - ua, (0.0, 0.0, 1.0)) if abs((ub - ua)[2]) < 0.9 * np.linalg.norm(ub - ua) else \
                    np.array([1.0, 0.0, 0.0])
            q = foot + (urethra.radius_mm + 3.0) * radial / np.linalg.norm(radial)
        targets.append((k, tuple(float(x) for x in q)))
    arms = tuple(_scaled_arm(a, s) if urethra is None else _arm_clear_of_urethra(_scaled_arm(a, s), bulb, urethra)
                 for a in base.arms)
    contacts = tuple((k, _project(bulb, k, p, "contacts")) for k, p in base.contacts)
    others = tuple(_scaled_cavity(c, s, scale, bulb) for c in base.cavities if c.name != "urethra")
    out = dataclasses.replace(base, name=name, bulb=bulb, arms=arms, markers=markers, contacts=contacts,
                              cavities=(*(() if urethra is None else (urethra,)), *others), targets=tuple(targets))
    if anatomy.lesions:  # each lesion label becomes a lesion region, in the bulb's material unless set
        from softphantom.design.params import LayersParams, LesionParams

        new = tuple(LesionParams(lesion_name(lab), tuple(float(x) for x in les["center_mm"]),
                                 tuple(float(x) for x in les["semi_axes_mm"]))
                    for lab, les in sorted(anatomy.lesions.items()))
        rm = dict(base.region_materials)
        rm.setdefault("lesions", rm.get("bulb", base.material_of_regions(["bulb"])["bulb"]))
        out = dataclasses.replace(out, layers=LayersParams(shell_mm=base.layers.shell_mm,
                                                           lesions=(*base.layers.lesions, *new)),
                                  region_materials=tuple(rm.items()))
    return dataclasses.replace(out, bulb=_clear_of_arm_cuts(out))


def _clear_of_arm_cuts(design: BIPDesign, frac: float = 0.3):
    """The bulb with each surface vertex that lies within ``frac`` × the median edge of an arm's
    cylinder moved radially to that distance from it (inward or outward, whichever side it is on).
    The cylinder then never cuts a facet next to a vertex, where OCC left edges of a few µm that
    became slivers or degenerate tets (min dihedral 0.04–0.2° on a 6 mm surface at a 12 mm mesh,
    or a 'segment and a facet intersect' failure at 4 mm; 1.9–6.5° with the band, 0 failures)."""
    bulb = design.bulb
    v = np.asarray(bulb.surface_vertices_mm, float).copy()
    f = np.asarray(bulb.surface_faces)
    eps = frac * float(np.median(np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)))
    for g in design.arm_geometry():
        axis = (g.end_mm - g.start_mm) / np.linalg.norm(g.end_mm - g.start_mm)
        rel = v - g.start_mm
        along = rel @ axis
        radial = rel - along[:, None] * axis
        dist = np.linalg.norm(radial, axis=1)
        band = (np.abs(dist - g.radius_mm) < eps) & (along > 0.0) & (dist > 0.0)
        target = np.where(dist[band] < g.radius_mm, g.radius_mm - eps, g.radius_mm + eps)
        v[band] += radial[band] * (target / dist[band] - 1.0)[:, None]
    import trimesh

    _check_surface(trimesh.Trimesh(v, f, process=False), "anatomy (vertices moved off the arms' cylinders)")
    return dataclasses.replace(bulb, surface_vertices_mm=tuple(tuple(float(x) for x in p) for p in v))


def _arm_clear_of_urethra(arm, bulb: BulbParams, urethra: UrethraParams, margin_mm: float = 0.5):
    """``arm`` with its embedding shortened, if needed, so that it keeps the design's minimum wall
    (plus ``margin_mm``) to a fitted urethra, which may lie closer to the surface than the default."""
    from softphantom.design.params import _arm_geometry

    ua, ub = urethra.segment_mm

    def gap(embed: float) -> float:
        g = _arm_geometry(dataclasses.replace(arm, embed_mm=embed), bulb)
        return geo.segment_segment_distance(g.start_mm, g.end_mm, ua, ub) - g.radius_mm - urethra.radius_mm

    need = MIN_WALL_MM + margin_mm
    if gap(arm.embed_mm) >= need:
        return arm
    lo, hi = min(3.0, arm.embed_mm), arm.embed_mm  # the arm still reaches 3 mm into the gland
    if gap(lo) < need:
        return arm  # validation names the problem
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(mid) >= need else (lo, mid)
    return dataclasses.replace(arm, embed_mm=round(lo, 3))


#: half axes (R-L, A-P, S-I, mm) of :func:`zonal_label_map`'s gland before its scaling: 45.2 mL
ZONAL_SEMI_RAS_MM = (25.0, 18.0, 24.0)


def zonal_label_map(volume_mL: float, tilt_deg: float = 0.0, spacing_mm=(0.6, 0.6, 4.0), fov_mm=None):
    """A synthetic prostate label map as the public zonal data sets publish theirs: an ellipsoidal
    gland of ``volume_mL`` (:data:`ZONAL_SEMI_RAS_MM` scaled) tilted by ``tilt_deg`` about R-L (its
    S-I axis towards anterior), a transition zone (label 2, the concentric ellipsoid of 0.65 × the
    semi-axes) inside a peripheral-zone shell (label 1), no urethra label, thick slices of
    ``spacing_mm``; the field of view ``fov_mm`` (default: the gland plus 8 mm each side), centred
    on the gland. Returns (data int16, affine RAS mm, semi-axes mm, the gland's axes as columns in RAS).

    >>> data, affine, semi, axes = zonal_label_map(47.0)
    >>> sorted(set(data.ravel().tolist())), float(affine[2, 2])
    ([0, 1, 2], 4.0)
    >>> round(float((data > 0).sum() * abs(np.linalg.det(affine[:3, :3]))) / 1e3, 0)  # mL, the voxels'
    47.0
    """
    sp = np.asarray(spacing_mm, float)
    base = np.asarray(ZONAL_SEMI_RAS_MM, float)
    semi = base * (volume_mL * 1e3 / (4.0 / 3.0 * np.pi * np.prod(base))) ** (1.0 / 3.0)
    fov = np.full(3, 2.0 * semi.max() + 16.0) if fov_mm is None else np.asarray(fov_mm, float)
    shape = tuple(int(n) for n in np.ceil(fov / sp))
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    axes = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])  # the tilt turns S-I (column 2) towards A
    affine = np.diag([*sp, 1.0])
    affine[:3, 3] = -0.5 * (np.array(shape) - 1) * sp
    q = (np.indices(shape).transpose(1, 2, 3, 0) * sp + affine[:3, 3]) @ axes  # along the gland's axes
    data = np.zeros(shape, np.int16)
    data[np.linalg.norm(q / semi, axis=-1) < 1.0] = 1
    data[np.linalg.norm(q / (0.65 * semi), axis=-1) < 1.0] = 2
    return data, affine, semi, axes
