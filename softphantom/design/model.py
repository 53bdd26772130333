"""The :class:`PhantomModel` (mesh + named regions, SI) and its files.

``build_model(design)`` meshes a design; ``save_model(model, dir)`` writes ``model.msh`` (gmsh 2.2
ASCII with physical groups, for gmsh/SOFA users), ``model.vtu`` (ParaView), ``design.toml`` and
``model.npz`` (the arrays; what ``load_model`` reads back, bit-identical).

Orientation conventions (docs/architecture.md): tets have positive signed volume; cavity
triangles have ``(x2−x1)×(x3−x1)`` pointing out of the air into the silicone, so
``Φ = Σ x1·(x2×x3)/6`` is the (positive) cavity volume; ``outer_faces`` (the free outer surface,
*without* the fixed arm ends) and ``fixed_faces`` point outward; together they close the solid.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softphantom.design import geometry as geo
from softphantom.design.mesh import (
    CAVITY_VOLUME_TOLERANCE,
    FIXED_GROUP_ID,
    OUTER_GROUP_ID,
    RawMesh,
    cavity_group_ids,
    check_mesh_budget,
    mesh_design,
)
from softphantom.design.params import (
    MAX_CAVITY_SEGMENTS,
    BIPDesign,
    design_from_dict,
    design_to_dict,
    load_design,
    save_design,
)
from softphantom.errors import FileFormatError, MeshError

MM = 1e-3
MODEL_FILES = ("model.msh", "model.vtu", "design.toml", "model.npz")
NPZ_VERSION = 1
# Models shipped meshed with the package (one directory each: model.npz, design.toml, atlas/):
# their mesh, and so their atlases' keys, do not depend on the gmsh version installed.
SHIPPED_MODELS = Path(__file__).resolve().parent.parent / "data" / "models"
DEFAULT_MODEL = "bip_p2"  # the default design: quadratic neo-Hookean, the mesh that meets the accuracy goals


def _frozen(a: np.ndarray, dtype) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class PhantomModel:
    """Tetra mesh of a design with its named regions, in SI (see docs/architecture.md).

    Arrays are read-only. ``mesh_seconds`` is the meshing wall time (0 for a loaded model and not
    compared by ``==``).

    Quadratic models (``design.mesh.element_order == 2``): ``nodes`` holds the corner nodes first
    (``n_corner_nodes`` of them) then the mid-edge nodes; ``tets``, ``cavities``, ``fixed_faces``
    and ``outer_faces`` stay the corner (linear) connectivity every consumer knows, and
    ``tets10`` (M,10), ``cavities6`` (name -> (K,6)), ``fixed_faces6``, ``outer_faces6`` (·,6)
    add the mid-edge nodes (VTK order, see softphantom.fem.elements); ``fixed_nodes`` includes the
    mid-edge nodes of the fixed faces. For linear models those extra fields are empty and
    ``n_corner_nodes == len(nodes)``.
    """

    design: BIPDesign
    nodes: np.ndarray
    tets: np.ndarray
    tet_region: np.ndarray
    regions: dict[str, int]
    cavities: dict[str, np.ndarray]
    fixed_faces: np.ndarray
    fixed_nodes: np.ndarray
    outer_faces: np.ndarray
    markers: dict[str, np.ndarray]
    targets: dict[str, np.ndarray]
    p_ext: dict[str, np.ndarray]  # the contact points: on-centre, off-centre, then the design's [contacts]
    mesh_seconds: float = field(default=0.0)
    tets10: np.ndarray = field(default_factory=lambda: np.zeros((0, 10), dtype=np.int64))
    cavities6: dict[str, np.ndarray] = field(default_factory=dict)
    fixed_faces6: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), dtype=np.int64))
    outer_faces6: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), dtype=np.int64))
    n_corner_nodes: int = -1

    def __post_init__(self) -> None:
        object.__setattr__(self, "nodes", _frozen(self.nodes, np.float64))
        object.__setattr__(self, "tets", _frozen(self.tets, np.int64))
        object.__setattr__(self, "tet_region", _frozen(self.tet_region, np.int32))
        object.__setattr__(self, "fixed_faces", _frozen(self.fixed_faces, np.int64))
        object.__setattr__(self, "fixed_nodes", _frozen(self.fixed_nodes, np.int64))
        object.__setattr__(self, "outer_faces", _frozen(self.outer_faces, np.int64))
        for name, k in (("tets10", 10), ("fixed_faces6", 6), ("outer_faces6", 6)):
            object.__setattr__(self, name, _frozen(np.asarray(getattr(self, name)).reshape(-1, k), np.int64))
        object.__setattr__(self, "cavities6", {k: _frozen(v, np.int64) for k, v in self.cavities6.items()})
        if self.n_corner_nodes < 0:
            object.__setattr__(self, "n_corner_nodes", len(self.nodes))
        object.__setattr__(self, "n_corner_nodes", int(self.n_corner_nodes))
        # in id order, whatever order they came in (a JSON round trip sorts them by name): the
        # files written from a model must not depend on how it was made
        object.__setattr__(self, "regions", dict(sorted(self.regions.items(), key=lambda kv: kv[1])))
        for name in ("cavities",):
            object.__setattr__(self, name, {k: _frozen(v, np.int64) for k, v in getattr(self, name).items()})
        for name in ("markers", "targets", "p_ext"):
            object.__setattr__(self, name, {k: _frozen(v, np.float64) for k, v in getattr(self, name).items()})
        n = len(self.nodes)
        if self.nodes.ndim != 2 or self.nodes.shape[1] != 3:
            raise MeshError(f"nodes: expected shape (N, 3), got {self.nodes.shape}")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4 or len(self.tet_region) != len(self.tets):
            raise MeshError(f"tets: expected (M, 4) with one region each, got {self.tets.shape}")
        for name, arr in (("tets", self.tets), ("fixed_faces", self.fixed_faces), ("outer_faces", self.outer_faces),
                          *((f"cavities.{k}", v) for k, v in self.cavities.items()),
                          ("tets10", self.tets10), ("fixed_faces6", self.fixed_faces6),
                          ("outer_faces6", self.outer_faces6),
                          *((f"cavities6.{k}", v) for k, v in self.cavities6.items())):
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise MeshError(f"{name}: node index out of range 0..{n - 1}")
        if self.element_order == 2 and (len(self.tets10) != len(self.tets) or set(self.cavities6) != set(self.cavities)):
            raise MeshError("element_order 2: tets10 and cavities6 must match tets and cavities")

    @property
    def layout(self):
        """Its design's :class:`~softphantom.records.channels.ChannelLayout` (arms, measured and
        actuated cavities, in order): the names of its ``cavities`` the sensors read and load."""
        return self.design.channel_layout

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PhantomModel):
            return NotImplemented
        if self.design != other.design or self.regions != other.regions:
            return False
        arrays = ("nodes", "tets", "tet_region", "fixed_faces", "fixed_nodes", "outer_faces", "tets10",
                  "fixed_faces6", "outer_faces6")
        if not all(np.array_equal(getattr(self, k), getattr(other, k)) for k in arrays):
            return False
        for k in ("cavities", "cavities6", "markers", "targets", "p_ext"):
            a, b = getattr(self, k), getattr(other, k)
            if list(a) != list(b) or not all(np.array_equal(a[n], b[n]) for n in a):
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    @property
    def element_order(self) -> int:
        """1 (4-node tets) or 2 (10-node tets; see the class docstring)."""
        return 2 if len(self.tets10) else 1

    # --- derived figures --------------------------------------------------------------------
    def tet_volumes(self) -> np.ndarray:
        """Signed volume of each tet, m³ (all > 0)."""
        return geo.tet_signed_volumes(self.nodes, self.tets)

    def region_volume(self, name: str) -> float:
        """Meshed volume of a region, m³."""
        return float(self.tet_volumes()[self.tet_region == self.regions[name]].sum())

    def cavity_volume(self, name: str) -> float:
        """Φ of a cavity surface at rest, m³ (positive with the model's orientation)."""
        return geo.surface_enclosed_volume(self.nodes, self.cavities[name])

    def bulb_volume(self) -> float:
        """Volume enclosed by the bulb's outer surface, m³ (the bulb region plus the internal cavities).

        The bulb region's tets (with the shell and lesion regions of a multi-material design) fill
        the ellipsoid minus the internal cavities (less :meth:`junction_volume`, the rounded
        junctions outside it), so adding their Φ gives the meshed counterpart of the design's
        100.41 mL.
        """
        return sum(self.region_volume(r) for r in self._body_regions()) \
            + sum(self.cavity_volume(n) for n in self.design.internal_cavity_names) - self.junction_volume()

    def _body_regions(self) -> list[str]:
        """The regions that make up the bulb's body: bulb (or infill), shell, lesions."""
        return [r for r in self.regions if r in ("bulb", "shell") or r.startswith("lesion_")]

    def junction_volume(self) -> float:
        """Volume of the body regions outside the bulb's surface, m³: with rounded arm junctions
        (``junction_fillet_mm`` > 0) the fillet rings and each arm's first millimetres, which
        belong to the bulb (or shell) region; 0 with sharp junctions. Tets are counted by their
        centroid, so a tet across the surface counts wholly on one side."""
        if not any(a.junction_fillet_mm > 0.0 for a in self.design.arms) or self.design.bulb.is_surface:
            return 0.0
        sel = np.isin(self.tet_region, [self.regions[r] for r in self._body_regions()])
        c = self.nodes[self.tets[sel]].mean(axis=1)
        out = geo.ellipsoid_level(c, np.asarray(self.design.bulb.semi_axes_mm) * MM) >= 1.0
        return float(self.tet_volumes()[sel][out].sum())

    def min_dihedral_deg(self) -> float:
        """Smallest dihedral angle over all tets, degrees (a quality figure)."""
        return float(geo.min_dihedral_angles_deg(self.nodes, self.tets).min())

    def tube_inlets(self) -> dict[str, np.ndarray]:
        """Where each cavity's tube enters, m: the arm end-face centres and the internal cavities' inlets."""
        out = {g.name: g.tube_inlet_mm * MM for g in self.design.arm_geometry()}
        out.update((c.name, np.asarray(c.inlet_mm) * MM) for c in self.design.cavities)
        return out


# swapping corners 2 and 3 of a 10-node tet (VTK order) moves its mid-edge nodes too
_TET10_SWAP23 = np.array([0, 1, 3, 2, 4, 8, 7, 6, 5, 9])
# reversing a 6-node triangle (a, b, c, ab, bc, ca) -> (a, c, b, ca, bc, ab)
_TRI6_FLIP = np.array([0, 2, 1, 5, 4, 3])


def _orient(tets: np.ndarray, nodes: np.ndarray, tris: np.ndarray, into_solid: bool) -> np.ndarray:
    """Orient boundary triangles by their one adjacent tet: normal into the solid or out of it.
    6-node triangles are oriented by their corners and keep their mid-edge nodes in step."""
    if len(tris) == 0:
        return tris.reshape(0, tris.shape[1] if tris.ndim == 2 else 3)
    if tris.shape[1] == 6:
        flip = ~np.all(_orient(tets, nodes, tris[:, :3], into_solid) == tris[:, :3], axis=1)
        out = tris.copy()
        out[flip] = tris[flip][:, _TRI6_FLIP]
        return out
    faces = np.vstack([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]])
    opposite = np.concatenate([tets[:, 0], tets[:, 1], tets[:, 2], tets[:, 3]])
    key_f = np.sort(faces, axis=1)
    key_t = np.sort(tris, axis=1)
    n = int(nodes.shape[0])
    enc_f = (key_f[:, 0] * n + key_f[:, 1]) * n + key_f[:, 2]
    enc_t = (key_t[:, 0] * n + key_t[:, 1]) * n + key_t[:, 2]
    order = np.argsort(enc_f, kind="stable")
    idx = np.searchsorted(enc_f[order], enc_t)
    idx = np.clip(idx, 0, len(order) - 1)
    if not np.array_equal(enc_f[order][idx], enc_t):
        raise MeshError("a boundary triangle is not a face of any tet")
    opp = opposite[order[idx]]
    x = nodes[tris]
    nrm = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    towards = np.einsum("ij,ij->i", nrm, nodes[opp] - x[:, 0]) > 0.0
    flip = towards != into_solid
    out = tris.copy()
    out[flip, 1], out[flip, 2] = tris[flip, 2], tris[flip, 1]
    return out


def model_from_raw(design: BIPDesign, raw: RawMesh) -> PhantomModel:
    """Orient and convert a raw gmsh mesh into a :class:`PhantomModel` (SI)."""
    nodes = raw.nodes_mm * MM
    tets = raw.tets.copy()
    vol = geo.tet_signed_volumes(nodes, tets)
    neg = vol < 0.0
    tets[neg, 2], tets[neg, 3] = raw.tets[neg, 3], raw.tets[neg, 2]
    tets10 = np.asarray(raw.tets10).copy()
    if len(tets10):
        tets10[neg] = tets10[neg][:, _TET10_SWAP23]
    if (np.abs(vol) <= 1e-6 * np.abs(vol).mean()).any():
        raise MeshError(f"{int((np.abs(vol) <= 1e-6 * np.abs(vol).mean()).sum())} degenerate tets")
    # cavity normals point out of the air into the silicone: towards the adjacent tet
    cavities = {k: _orient(tets, nodes, v, into_solid=True) for k, v in raw.cavities.items()}
    fixed = _orient(tets, nodes, raw.fixed_faces, into_solid=False)
    outer = _orient(tets, nodes, raw.outer_faces, into_solid=False)
    quad = {}
    if len(tets10):
        cav6 = {k: _orient(tets, nodes, v, into_solid=True) for k, v in raw.cavities6.items()}
        fixed6 = _orient(tets, nodes, raw.fixed_faces6, into_solid=False)
        quad = dict(
            tets10=tets10, cavities6={k: cav6[k] for k in design.cavity_names}, fixed_faces6=fixed6,
            outer_faces6=_orient(tets, nodes, raw.outer_faces6, into_solid=False), n_corner_nodes=raw.n_corner,
        )
        fixed_nodes = np.unique(fixed6)
    else:
        fixed_nodes = np.unique(fixed)
    return PhantomModel(
        design=design,
        nodes=nodes,
        tets=tets,
        tet_region=raw.tet_region,
        regions=dict(raw.regions),
        cavities={k: cavities[k] for k in design.cavity_names},
        fixed_faces=fixed,
        fixed_nodes=fixed_nodes,
        outer_faces=outer,
        markers={k: v * MM for k, v in design.marker_dict.items()},
        targets={k: v * MM for k, v in design.target_dict.items()},
        p_ext={k: v * MM for k, v in design.p_ext_mm().items()},
        mesh_seconds=raw.seconds,
        **quad,
    )


def build_model(design: BIPDesign, mesh_size_mm: float | None = None, *, force: bool = False,
                isolate: bool | None = None) -> PhantomModel:
    """Mesh ``design``; ``mesh_size_mm`` rescales its mesh sizes (bulb size, arms and cavities in
    proportion) and the returned ``model.design.mesh`` records the sizes used. Takes a second or
    two at the default size, so no example runs here: ``model = build_model(BIPDesign())``.

    Guards (docs/robustness.md): before gmsh, :func:`~softphantom.design.mesh.check_mesh_budget`
    (size floor; without ``force`` the element-count limit and the predicted cavity error); after,
    without ``force``, every cavity and the bulb within ``CAVITY_VOLUME_TOLERANCE`` of the design
    (MeshError otherwise). ``isolate``: see :func:`~softphantom.design.mesh.mesh_design`.
    """
    if mesh_size_mm is not None:
        # the model's design records the sizes used, so design.toml alone reproduces the mesh
        design = dataclasses.replace(design, mesh=design.mesh.scaled_to(mesh_size_mm))
    shipped = shipped_model(design)
    if shipped is not None:
        return shipped
    check_mesh_budget(design, design.mesh, force=force)
    model = model_from_raw(design, mesh_design(design, design.mesh, isolate=isolate))
    if not force:
        check_meshed_volumes(model)
    return model


def default_design() -> BIPDesign:
    """The BIP with the quadratic mesh of the shipped model :data:`DEFAULT_MODEL` (neo-Hookean,
    10-node tets, 9 mm bulk, 2 mm arms: the mesh that meets the accuracy goals, docs/model.md),
    which :func:`build_model` returns as shipped.

    >>> d = default_design()
    >>> d.mesh.element_order, d.mesh.size_mm, d.mesh.arm_size_mm
    (2, 9.0, 2.0)
    """
    return load_design(SHIPPED_MODELS / DEFAULT_MODEL / "design.toml")


def shipped_model(design: BIPDesign) -> PhantomModel | None:
    """The model shipped meshed with the package for exactly ``design`` (mesh sizes and element
    order included), else None: :func:`build_model` returns it instead of meshing, so its mesh is
    the same whatever gmsh is installed.

    >>> shipped_model(default_design()).element_order
    2
    >>> shipped_model(BIPDesign()) is None  # the linear 6 mm design is meshed
    True
    """
    d = shipped_model_dir(design)
    return load_model(d) if d is not None else None


def shipped_model_dir(design: BIPDesign) -> Path | None:
    """The directory of the model shipped for exactly ``design`` (:func:`shipped_model`), else None."""
    want = design_to_dict(design)
    for d in sorted(SHIPPED_MODELS.iterdir()) if SHIPPED_MODELS.is_dir() else ():
        if (d / "design.toml").is_file() and design_to_dict(load_design(d / "design.toml")) == want:
            return d
    return None


def check_meshed_volumes(model: PhantomModel, tolerance: float = CAVITY_VOLUME_TOLERANCE) -> None:
    """MeshError if a cavity or the bulb is meshed more than ``tolerance`` (relative) off its design volume."""
    s = model_summary(model, quality=False)
    for name in (*model.design.cavity_volumes_mm3(), "bulb"):
        want, got = s[f"{name}_design_mm3"], s[f"{name}_mesh_mm3"]
        err = got / want - 1
        if abs(err) > tolerance:
            mp = model.design.mesh
            if name == "bulb":
                fix = f"mesh.size_mm = {mp.size_mm:.4g} mm: a finer --mesh-size-mm or mesh.surface_size_mm, or --force"
            else:  # a cavity wall has 2πr / cavity_segments elements around: its volume error goes as 1/segments²
                more = min(MAX_CAVITY_SEGMENTS, math.ceil(mp.cavity_segments * math.sqrt(abs(err) / (0.25 * tolerance))))
                fix = (f"mesh.cavity_segments = {mp.cavity_segments:.4g} elements around each cavity wall: raise it, "
                       f"e.g. to {more:g}, or --force")
            raise MeshError(f"meshed {name} volume {got:.4g} mm³ is {100 * err:+.1f} % off the design's "
                            f"{want:.4g} mm³ (tolerance {100 * tolerance:.0f} %; {fix})")


# --- files -------------------------------------------------------------------------------------

def _to_meshio(model: PhantomModel):
    import meshio

    # quadratic models are written with their 10-node / 6-node cells (meshio converts the node order
    # to gmsh's in .msh; VTK_QUADRATIC_TETRA's order is ours)
    q = model.element_order == 2
    tet_t, tri_t = ("tetra10", "triangle6") if q else ("tetra", "triangle")
    tets = model.tets10 if q else model.tets
    cavs = model.cavities6 if q else model.cavities
    cells, phys, geom = [], [], []
    for rname, rid in model.regions.items():
        sel = tets[model.tet_region == rid]
        cells.append((tet_t, sel))
        phys.append(np.full(len(sel), rid, dtype=np.int64))
    cavity_ids = cavity_group_ids(model.design.arm_names, model.design.internal_cavity_names)
    for cname, gid in cavity_ids.items():
        cells.append((tri_t, cavs[cname]))
        phys.append(np.full(len(cavs[cname]), gid, dtype=np.int64))
    faces = ((model.fixed_faces6, FIXED_GROUP_ID), (model.outer_faces6, OUTER_GROUP_ID)) if q else (
        (model.fixed_faces, FIXED_GROUP_ID), (model.outer_faces, OUTER_GROUP_ID))
    for tris, gid in faces:
        cells.append((tri_t, tris))
        phys.append(np.full(len(tris), gid, dtype=np.int64))
    geom = [p.copy() for p in phys]
    field_data = {name: np.array([rid, 3]) for name, rid in model.regions.items()}
    field_data.update({f"cavity_{n}": np.array([g, 2]) for n, g in cavity_ids.items()})
    field_data["fixed"] = np.array([FIXED_GROUP_ID, 2])
    field_data["outer"] = np.array([OUTER_GROUP_ID, 2])
    return meshio.Mesh(
        np.asarray(model.nodes),
        cells,
        cell_data={"gmsh:physical": phys, "gmsh:geometrical": geom},
        field_data=field_data,
    )


def save_model(model: PhantomModel, directory: str | Path, *, mesh_files: bool = True) -> Path:
    """Write ``model.msh``, ``model.vtu`` (unless not ``mesh_files``: what :func:`load_model`
    reads is the rest), ``design.toml`` and ``model.npz`` into ``directory``."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    if mesh_files:
        import meshio

        m = _to_meshio(model)
        meshio.write(out / "model.msh", m, file_format="gmsh22", binary=False)
        vtu = meshio.Mesh(
            m.points,
            m.cells,
            cell_data={"region": [np.asarray(p, dtype=np.int32) for p in m.cell_data["gmsh:physical"]]},
        )
        meshio.write(out / "model.vtu", vtu, binary=True, compression=None)
    save_design(model.design, out / "design.toml")
    arrays = {
        "nodes": model.nodes,
        "tets": model.tets,
        "tet_region": model.tet_region,
        "fixed_faces": model.fixed_faces,
        "fixed_nodes": model.fixed_nodes,
        "outer_faces": model.outer_faces,
        **{f"cavity__{k}": v for k, v in model.cavities.items()},
        **{f"marker__{k}": v for k, v in model.markers.items()},
        **{f"target__{k}": v for k, v in model.targets.items()},
        **{f"pext__{k}": v for k, v in model.p_ext.items()},
    }
    if model.element_order == 2:
        arrays.update(
            tets10=model.tets10, fixed_faces6=model.fixed_faces6, outer_faces6=model.outer_faces6,
            **{f"cavity6__{k}": v for k, v in model.cavities6.items()},
        )
    meta = {
        "npz_version": NPZ_VERSION,
        "regions": model.regions,
        "n_corner_nodes": model.n_corner_nodes,
        "order": {
            "cavity": list(model.cavities),
            "marker": list(model.markers),
            "target": list(model.targets),
            "pext": list(model.p_ext),
        },
        "design": design_to_dict(model.design),
    }
    arrays["meta_json"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    np.savez(out / "model.npz", **arrays)
    return out


def load_model(directory: str | Path) -> PhantomModel:
    """Read a model written by :func:`save_model` (``model.npz``, with ``design.toml``)."""
    d = Path(directory)
    npz = d / "model.npz"
    if not npz.is_file():
        raise FileFormatError(f"{npz}: no such file (expected a directory written by `softphantom design`)")
    try:
        with np.load(npz, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise FileFormatError(f"{npz}: not a readable npz archive ({exc})") from None
    try:
        meta = json.loads(bytes(data.pop("meta_json")).decode())
    except KeyError:
        raise FileFormatError(f"{npz}: missing key 'meta_json'") from None
    if meta.get("npz_version") != NPZ_VERSION:
        raise FileFormatError(f"{npz}: npz_version {meta.get('npz_version')!r}, this softphantom reads {NPZ_VERSION}")
    toml = d / "design.toml"
    design = load_design(toml) if toml.is_file() else design_from_dict(meta["design"])
    # a model saved before a design field existed stored no value for it: compare with defaults filled
    if design_to_dict(design) != design_to_dict(design_from_dict(meta["design"])):
        raise FileFormatError(f"{toml}: does not match the design stored in {npz.name}")
    try:
        named = {
            pref: {k: data[f"{pref}__{k}"] for k in meta["order"][pref]}
            for pref in ("cavity", "marker", "target", "pext")
        }
        quad = {}
        if "tets10" in data:  # a quadratic model (files without these keys are linear)
            quad = dict(
                tets10=data["tets10"], fixed_faces6=data["fixed_faces6"], outer_faces6=data["outer_faces6"],
                cavities6={k: data[f"cavity6__{k}"] for k in meta["order"]["cavity"]},
                n_corner_nodes=int(meta["n_corner_nodes"]),
            )
        return PhantomModel(
            design=design,
            nodes=data["nodes"],
            tets=data["tets"],
            tet_region=data["tet_region"],
            regions={k: int(v) for k, v in meta["regions"].items()},
            cavities=named["cavity"],
            fixed_faces=data["fixed_faces"],
            fixed_nodes=data["fixed_nodes"],
            outer_faces=data["outer_faces"],
            markers=named["marker"],
            targets=named["target"],
            p_ext=named["pext"],
            **quad,
        )
    except KeyError as exc:
        raise FileFormatError(f"{npz}: missing array {exc.args[0]!r}") from None


def model_summary(model: PhantomModel, quality: bool = True) -> dict[str, float]:
    """Design vs meshed volumes (mm³) and counts (and the smallest dihedral angle with ``quality``)."""
    out: dict[str, float] = {
        "nodes": len(model.nodes),
        "tets": len(model.tets),
        "bulb_design_mm3": model.design.bulb.volume_mm3,
        "bulb_mesh_mm3": model.bulb_volume() / MM**3,
        "junction_mesh_mm3": model.junction_volume() / MM**3,
    }
    if quality:
        out["min_dihedral_deg"] = model.min_dihedral_deg()
    for name, v in model.design.cavity_volumes_mm3().items():
        out[f"{name}_design_mm3"] = v
        out[f"{name}_mesh_mm3"] = model.cavity_volume(name) / MM**3
    return out

