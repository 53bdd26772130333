"""Geometry (gmsh, OpenCASCADE kernel) and the conforming linear-tetra mesh of a :class:`BIPDesign`.

Construction: the bulb is a unit sphere dilated to the ellipsoid; each arm is a cylinder from
``start_mm`` (inside the bulb) to ``end_mm``; each cavity is a capsule (cylinder fused with two
spheres). One ``fragment`` of the bulb with all arms and cavities makes the pieces share their
faces (a conforming mesh); the cavity pieces are then removed non-recursively so their faces stay
as holes in the silicone. The part of an arm inside the bulb belongs to the ``bulb`` region.

Sizing: one background field, the minimum of a threshold per cavity on the distance to its
surface (``2πr / cavity_segments`` on the wall, growing about 1:1 to ``size_mm``), a threshold on
the distance to the bulb's outer surface (``surface_size_mm`` there), a constant ``arm_size_mm``
inside the arm volumes and ``size_mm`` elsewhere. The meshed volume of a convex wall is that of
an inscribed polyhedron, so it errs low by about (2π/n)²/6 with n segments around: −1.6 % for
the default 22. Deterministic: one thread, a fixed random seed, the
Delaunay 3-D algorithm; headless (``General.Terminal = 0``) and callable off the main thread
(``interruptible=False``: no signal handler). gmsh is one global library, so calls are
serialised by a lock; it is finalized after each mesh only when this module initialized it.
Where a Ctrl-C would reach the caller (a command line's main thread) gmsh runs in a spawned child
process instead, which the Ctrl-C kills at once (:func:`mesh_design`). Before any of it,
:func:`check_mesh_budget` refuses sizes below a floor, an estimated element count above
:data:`MAX_TETS` and cavity walls too coarse for :data:`CAVITY_VOLUME_TOLERANCE`.

All lengths here are mm; :mod:`softphantom.design.model` converts to SI.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from softphantom.design.occ_shapes import arm_cylinder, bulb_solid, capsule, filleted_body, seam_side
from softphantom.design.params import ARM_NAMES, MAX_CAVITY_SEGMENTS, BIPDesign, MeshParams
from softphantom.errors import DesignError, MeshError

# gmsh's 10-node tet -> VTK/meshio order (its last two edges are (2,3), (1,3); VTK: (1,3), (2,3));
# the same table as softphantom.fem.elements.GMSH_TET10 (design may not import fem)
GMSH_TET10 = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])

ARM_SPLIT_MARGIN_MM = 1.0  # a rounded arm's region starts this far above its fillet (and below its cavity)
_GMSH_LOCK = threading.Lock()  # gmsh holds process-global state; one mesh at a time

SHELL_REGION_ID = 6
URETHRA_GROUP_ID = 15


def region_ids(arm_names=ARM_NAMES) -> dict[str, int]:
    """The physical ids of the bulb and the arms' regions: the bulb 1, the first four arms 2–5
    (the BIP's ids), further arms 100 + their index (clear of the shell's 6 and the lesions' 31…).

    >>> region_ids()
    {'bulb': 1, 'arm_front_zpos': 2, 'arm_front_zneg': 3, 'arm_back_xpos': 4, 'arm_back_xneg': 5}
    """
    return {"bulb": 1, **{f"arm_{n}": (i + 2 if i < 4 else 100 + i) for i, n in enumerate(arm_names)}}


def cavity_group_ids(arm_names=ARM_NAMES, internal=("urethra",)) -> dict[str, int]:
    """The physical ids of the cavities' walls: the first four arms' 11–14 and the urethra's 15
    (the BIP's ids), further arms' 200 + their index, the other internal cavities 300 + theirs.

    >>> cavity_group_ids(("a", "b", "c"))
    {'a': 11, 'b': 12, 'c': 13, 'urethra': 15}
    >>> cavity_group_ids(("a", "b", "c"), ("tumour", "urethra"))
    {'a': 11, 'b': 12, 'c': 13, 'tumour': 300, 'urethra': 15}
    """
    return {**{n: (11 + i if i < 4 else 200 + i) for i, n in enumerate(arm_names)},
            **{n: (URETHRA_GROUP_ID if n == "urethra" else 300 + i) for i, n in enumerate(internal)}}


REGION_IDS: dict[str, int] = region_ids()  # the BIP's
CAVITY_GROUP_IDS: dict[str, int] = cavity_group_ids()
LESION_REGION_ID0 = 31  # lesion k (in the design's order) is 31 + k
FIXED_GROUP_ID = 21
OUTER_GROUP_ID = 22


@dataclass(frozen=True)
class RawMesh:
    """gmsh output in mm, before orientation/SI conversion (internal)."""

    nodes_mm: np.ndarray  # (N,3)
    tets: np.ndarray  # (M,4) 0-based
    tet_region: np.ndarray  # (M,)
    cavities: dict[str, np.ndarray]  # name -> (K,3), unoriented
    fixed_faces: np.ndarray  # (F,3)
    outer_faces: np.ndarray  # (S,3) free outer surface (without the fixed faces)
    seconds: float
    # element_order 2: 10-node tets / 6-node triangles (our VTK node order), corner nodes numbered
    # first (indices < n_corner); empty for order 1
    tets10: np.ndarray = field(default_factory=lambda: np.zeros((0, 10), dtype=np.int64))
    cavities6: dict = field(default_factory=dict)
    fixed_faces6: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), dtype=np.int64))
    outer_faces6: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), dtype=np.int64))
    n_corner: int = -1
    regions: dict = field(default_factory=lambda: dict(REGION_IDS))  # name -> id (shell, lesions beyond the base)


def _elements(dim: int, tag: int, etype: int, nper: int) -> np.ndarray:
    import gmsh

    types, _, node_tags = gmsh.model.mesh.getElements(dim, tag)
    for t, nt in zip(types, node_tags):
        if t == etype:
            return np.asarray(nt, dtype=np.int64).reshape(-1, nper)
    return np.zeros((0, nper), dtype=np.int64)


def _restore_sigpipe() -> None:
    """gmsh.initialize resets SIGPIPE to its default (terminate) behind Python's back; Python runs
    with it ignored so a peer closing a socket or pipe (a live-page client, a stream subscriber)
    gives an EPIPE error instead of killing the process. Put it back, from any thread (libc)."""
    import ctypes
    import signal

    if signal.getsignal(signal.SIGPIPE) == signal.SIG_IGN:
        libc = ctypes.CDLL(None)
        libc.signal.restype = ctypes.c_void_p
        libc.signal(int(signal.SIGPIPE), ctypes.c_void_p(1))  # 1 == SIG_IGN


def _ctrl_c_reaches_here() -> bool:
    """True where Ctrl-C arrives as KeyboardInterrupt: the main thread with Python's SIGINT handler
    (a command line), not a worker thread nor a daemonic worker process (which cannot have children)."""
    import multiprocessing
    import signal

    return (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler
            and not multiprocessing.current_process().daemon)


def mesh_design(design: BIPDesign, mesh: MeshParams | None = None, *, isolate: bool | None = None) -> RawMesh:
    """Mesh ``design`` (sizes from ``mesh`` or ``design.mesh``); raises MeshError if gmsh fails.

    gmsh's C++ does not return to Python until it is done, so a Ctrl-C waits for the whole mesh
    (> 30 s on a fine one). With ``isolate`` it runs in a child process (spawned, ~0.5 s) that a
    Ctrl-C kills at once; by default it is isolated where a Ctrl-C would reach this thread.
    """
    mp = mesh or design.mesh
    if isolate is None:
        isolate = _ctrl_c_reaches_here()
    try:
        return _mesh_in_child(design, mp) if isolate else _mesh_here(design, mp)
    except MeshError as exc:
        raise _name_the_shell(design, mp, exc) from None


def _name_the_shell(design: BIPDesign, mp: MeshParams, exc: MeshError) -> MeshError:
    """A gmsh failure on a shelled design, reworded to name the shell and the mesh size: the thin
    layer is the likeliest cause when the parameter checks passed (docs/fabrication.md)."""
    t = design.layers.shell_mm
    if t <= 0.0 or not str(exc).startswith("gmsh failed"):
        return exc
    return MeshError(f"layers.shell_mm = {t:.4g} mm at mesh.size_mm = {mp.size_mm:.4g} mm (surface "
                     f"{mp.surface_size_mm:.3g} mm): gmsh could not mesh the shell ({str(exc).splitlines()[0]}); "
                     "try another --mesh-size-mm or shell thickness")


def _child(design: BIPDesign, mp: MeshParams, conn) -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent sees the Ctrl-C and ends this process
    try:
        conn.send(("ok", _mesh_here(design, mp)))
    except MeshError as exc:
        conn.send(("error", str(exc)))
    except BaseException as exc:  # noqa: BLE001 — reported to the parent as one line
        conn.send(("error", f"meshing failed on design {design.name!r}: {type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def _mesh_in_child(design: BIPDesign, mp: MeshParams) -> RawMesh:
    import multiprocessing
    import signal

    ctx = multiprocessing.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(design, mp, send), name="softphantom-gmsh", daemon=True)
    try:
        # a Ctrl-C during the start would leave a child half-started (it then dies with a traceback):
        # hold it for the few ms of the start (whichever thread the signal reaches, Python runs its
        # handler on the main thread); it is raised just after, inside this try
        main = threading.current_thread() is threading.main_thread()
        hit: list[int] = []
        old = signal.signal(signal.SIGINT, lambda *_: hit.append(1)) if main else None
        try:
            proc.start()
        finally:
            if main:
                signal.signal(signal.SIGINT, old)
        if hit:
            raise KeyboardInterrupt
        send.close()
        while not recv.poll(0.1):  # wakes for Ctrl-C (KeyboardInterrupt lands here)
            if not proc.is_alive() and not recv.poll(0):
                raise MeshError(f"meshing process for design {design.name!r} ended without a mesh "
                                f"(exit code {proc.exitcode}; out of memory?)")
        kind, value = recv.recv()
    except EOFError:
        raise MeshError(f"meshing process for design {design.name!r} ended without a mesh "
                        f"(exit code {proc.exitcode})") from None
    finally:
        if proc.pid is not None:
            if proc.is_alive():
                proc.kill()  # Ctrl-C or an error here: gmsh stops now, its memory is freed
            proc.join()
        send.close()
        recv.close()
    if kind != "ok":
        raise MeshError(value)
    return value


def gmsh_error_line(exc: Exception) -> str:
    """The first line of a gmsh error (gmsh raises plain Exception with its last error)."""
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


@contextmanager
def gmsh_session(model_name: str, what: str) -> Iterator:
    """One gmsh model in this process, under the module's lock: gmsh initialized if needed (and
    SIGPIPE restored), quiet, the model added; yields the ``gmsh`` module. Any gmsh error becomes a
    :class:`MeshError` naming ``what``; the model is removed (and gmsh finalized if started here)
    whatever happens. Used by the mesher and by the molds' solids."""
    import gmsh

    with _GMSH_LOCK:
        init_here = not gmsh.isInitialized()
        if init_here:
            gmsh.initialize(argv=["softphantom"], readConfigFiles=False, interruptible=False)
            _restore_sigpipe()
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.option.setNumber("General.Verbosity", 1)
            gmsh.option.setNumber("Geometry.ToleranceBoolean", 0.0)  # occ_shapes.junction_fillets raises it
            gmsh.model.add(model_name)
            yield gmsh
        except MeshError:
            raise
        except Exception as exc:  # gmsh raises plain Exception with its last error
            raise MeshError(f"gmsh failed on {what}: {gmsh_error_line(exc)}") from None
        finally:
            try:
                gmsh.model.setCurrent(model_name)
                gmsh.model.remove()
            except Exception:
                pass
            if init_here:
                gmsh.finalize()


def _mesh_here(design: BIPDesign, mp: MeshParams) -> RawMesh:
    with gmsh_session(f"softphantom_{design.name}", f"design {design.name!r}") as gmsh:
        gmsh.logger.start()
        try:
            t0 = time.perf_counter()
            raw = _build(design, mp)
            return RawMesh(**raw, seconds=time.perf_counter() - t0)
        finally:
            gmsh.logger.stop()


def _internal_cavity(occ, cavity) -> int:
    """An internal cavity's solid: a capsule, or a balloon (a unit sphere dilated to its semi-axes)."""
    if cavity.shape == "capsule":
        return capsule(occ, *cavity.segment_mm, cavity.radius_mm)
    a = cavity.semi_axes_mm
    if a[0] == a[1] == a[2]:  # a sphere stays analytic (a dilated one is a B-spline: slower to mesh)
        return occ.addSphere(*cavity.center_mm, a[0])
    tag = occ.addSphere(0.0, 0.0, 0.0, 1.0)
    occ.dilate([(3, tag)], 0.0, 0.0, 0.0, *a)
    occ.translate([(3, tag)], *cavity.center_mm)
    return tag


def _build(design: BIPDesign, mp: MeshParams) -> dict:
    """Mesh ``design`` in the current gmsh session, in three steps: the solids fragmented into
    regions and cavity walls (:func:`_regions`), the physical groups and the element sizes
    (:func:`_groups_and_sizes`), then the mesh and its arrays (:func:`_mesh_arrays`)."""
    import gmsh


    for name, value in (
        ("General.NumThreads", 1),
        ("Mesh.RandomSeed", 1),
        ("Mesh.Algorithm", 6),
        ("Mesh.Algorithm3D", 1),
        ("Mesh.ElementOrder", 1),
        ("Mesh.Optimize", 1),
        ("Mesh.OptimizeNetgen", 0),
        ("Mesh.MeshSizeExtendFromBoundary", 0),
        ("Mesh.MeshSizeFromPoints", 0),
        ("Mesh.MeshSizeFromCurvature", 0),
        ("Mesh.MeshSizeMin", 0.0),
        ("Mesh.MeshSizeMax", max(mp.size_mm, mp.surface_size_mm)),
        ("Geometry.OCCParallel", 0),
        ("Geometry.ToleranceBoolean", 0.0),  # exact booleans (junction_fillets, for the molds, raises it)
    ):
        gmsh.option.setNumber(name, value)
    parts = _regions(gmsh, design)
    fixed, outer = _groups_and_sizes(gmsh, design, mp, parts)
    return _mesh_arrays(gmsh, mp, parts, fixed, outer)


@dataclass
class _Regions:
    """The fragmented geometry: each region's volumes, its physical id, each cavity's wall surfaces."""

    geoms: tuple  # the arms' placement (BIPDesign.arm_geometry)
    region_vols: dict[str, list[int]]
    ids: dict[str, int]
    cav_surfaces: dict[str, list[int]]
    rounded: bool  # junction fillets: bulb and arms one solid


def _regions(gmsh, design: BIPDesign) -> _Regions:
    """The OCC solids (bulb, arms, cavities, layers) fragmented into one conforming set of volumes;
    the cavities removed, their walls kept."""
    occ = gmsh.model.occ
    bulb = bulb_solid(occ, design.bulb)  # an ellipsoid, or an anatomy surface (design/occ_shapes.py)
    geoms = design.arm_geometry()
    arms = [arm_cylinder(occ, g.start_mm, g.end_mm, g.radius_mm, seam_side(design.bulb, g.start_mm, g.end_mm, g.radius_mm))
            for g in geoms]
    cavities = [capsule(occ, *g.cavity_segment_mm, g.cavity_radius_mm) for g in geoms]
    cavities += [_internal_cavity(occ, c) for c in design.cavities]

    # multi-material: the infill (ellipsoid less the shell) and the lesions join the fragment, so
    # every region shares its faces with its neighbours (one conforming mesh)
    lay = design.layers
    layer_tools = []
    if lay.shell_mm > 0.0:
        layer_tools.append(("infill", bulb_solid(occ, dataclasses.replace(
            design.bulb, semi_axes_mm=lay.infill_semi_axes_mm(design.bulb.semi_axes_mm)))))
    for les in lay.lesions:
        tag = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, tag)], 0.0, 0.0, 0.0, *les.semi_axes_mm)
        occ.translate([(3, tag)], *les.center_mm)
        layer_tools.append((les.region, tag))
    drop: set[int] = set()
    rounded = any(g.fillet_mm > 0.0 for g in geoms)
    if rounded:
        # rounded junctions (ArmParams.junction_fillet_mm): the silicone is one solid (bulb, arms and
        # fillets fused and rounded), and each arm region is the part of it inside a tube around the
        # arm beyond a plane across the arm above its fillet (a region boundary along the fillet's
        # tangent line would be a knife edge that no tetrahedron fills: "overlapping facets")
        body, heights = filleted_body(occ, bulb, [(t, g.root_mm, g.end_mm, g.radius_mm) for t, g in zip(arms, geoms)],
                                      [g.fillet_mm for g in geoms], what="arms: junction_fillet_mm")
        occ.remove([(3, t) for t in [bulb, *arms]], recursive=True)
        bulb, arms = body, []
        for g, h in zip(geoms, heights):
            ca, cb = g.cavity_segment_mm
            z_cav = min((ca - g.root_mm) @ g.direction, (cb - g.root_mm) @ g.direction) - g.cavity_radius_mm
            z = min(h + ARM_SPLIT_MARGIN_MM, z_cav - ARM_SPLIT_MARGIN_MM)
            length = float((g.end_mm - g.root_mm) @ g.direction) + 1.0 - z
            arms.append(occ.addCylinder(*(g.root_mm + z * g.direction), *(length * g.direction),
                                        g.radius_mm + ARM_SPLIT_MARGIN_MM))
    tools = [(3, t) for t in arms + cavities] + [(3, t) for _, t in layer_tools]
    _, out_map = occ.fragment([(3, bulb)], tools)
    occ.synchronize()
    pieces = [set(t for d, t in m if d == 3) for m in out_map]
    n_arms = len(design.arms)
    n_cav = n_arms + len(design.cavities)
    bulb_p, arm_p, cav_p = pieces[0], pieces[1:1 + n_arms], pieces[1 + n_arms:1 + n_arms + n_cav]
    layer_p = {k: p for (k, _), p in zip(layer_tools, pieces[1 + n_arms + n_cav:])}
    if rounded:
        # the arm tubes' pieces outside the solid go; inside it they are the arms (not the bulb)
        drop = set().union(*arm_p) - bulb_p
        arm_p = [p & bulb_p for p in arm_p]
        bulb_p = bulb_p - set().union(*arm_p)
    all_cav = set().union(*cav_p) if cav_p else set()
    cav_surfaces: dict[str, list[int]] = {}
    for name, p in zip(design.cavity_names, cav_p):
        if len(p) != 1:
            raise MeshError(f"cavity {name}: fragment gave {len(p)} pieces, expected 1")
        bnd = gmsh.model.getBoundary([(3, t) for t in sorted(p)], combined=True, oriented=False)
        cav_surfaces[name] = sorted(abs(t) for _, t in bnd)
    lesion_p = set().union(*(layer_p[x.region] for x in lay.lesions)) if lay.lesions else set()
    infill_p = layer_p.get("infill", bulb_p)
    region_vols = {"bulb": sorted((bulb_p & infill_p) - all_cav - lesion_p)}
    ids = region_ids(design.arm_names)
    if lay.shell_mm > 0.0:
        region_vols["shell"] = sorted(bulb_p - infill_p - all_cav)
        ids["shell"] = SHELL_REGION_ID
    for k, les in enumerate(lay.lesions):
        region_vols[les.region] = sorted(layer_p[les.region] - all_cav)
        ids[les.region] = LESION_REGION_ID0 + k
    for rname in ids:
        if rname in region_vols and not region_vols[rname]:
            raise MeshError(f"region {rname}: no volume left after the fragment")
    for name, p in zip(design.arm_names, arm_p):
        region_vols[f"arm_{name}"] = sorted(p - all_cav - bulb_p)
        if not region_vols[f"arm_{name}"]:
            raise MeshError(f"arm {name}: no volume outside the bulb after the fragment")
    occ.remove([(3, t) for t in sorted(all_cav | drop)], recursive=False)
    occ.synchronize()
    return _Regions(geoms, region_vols, ids, cav_surfaces, rounded)


def _groups_and_sizes(gmsh, design: BIPDesign, mp: MeshParams, parts: _Regions) -> tuple[list[int], list[int]]:
    """The physical groups (regions, cavity walls, fixed end faces, free outer surface) and the size
    fields of ``mp``; returns the fixed and the outer surfaces."""
    geoms, region_vols, ids, cav_surfaces = parts.geoms, parts.region_vols, parts.ids, parts.cav_surfaces
    occ = gmsh.model.occ
    lay = design.layers
    # fixed faces: the arm surfaces whose centre of mass is the end-face centre
    fixed: list[int] = []
    for g, name in zip(geoms, design.arm_names):
        bnd = gmsh.model.getBoundary([(3, t) for t in region_vols[f"arm_{name}"]], combined=True, oriented=False)
        hits = [abs(t) for _, t in bnd if gmsh.model.getType(2, abs(t)) == "Plane"
                and np.linalg.norm(np.array(occ.getCenterOfMass(2, abs(t))) - g.end_mm) < 1e-3]
        if len(hits) != 1:
            raise MeshError(f"arm {name}: found {len(hits)} end faces, expected 1")
        fixed.append(hits[0])
    cav_all = set(t for ts in cav_surfaces.values() for t in ts)
    outer = []
    for _, s in gmsh.model.getEntities(2):
        up, _ = gmsh.model.getAdjacencies(2, s)
        if len(up) == 1 and s not in cav_all and s not in fixed:
            outer.append(s)

    for rname, rid in ids.items():
        gmsh.model.addPhysicalGroup(3, region_vols[rname], rid, name=rname)
    for cname, gid in cavity_group_ids(design.arm_names, design.internal_cavity_names).items():
        gmsh.model.addPhysicalGroup(2, cav_surfaces[cname], gid, name=f"cavity_{cname}")
    gmsh.model.addPhysicalGroup(2, fixed, FIXED_GROUP_ID, name="fixed")
    gmsh.model.addPhysicalGroup(2, sorted(outer), OUTER_GROUP_ID, name="outer")

    fld = gmsh.model.mesh.field
    fields = []
    radii = {g.name: g.cavity_radius_mm for g in geoms}
    radii.update((c.name, c.wall_radius_mm) for c in design.cavities)
    for h, names in _walls_by_size({c: mp.cavity_size_mm(radii[c]) for c in design.cavity_names}):
        dist = fld.add("Distance")
        fld.setNumbers(dist, "SurfacesList", [t for n in names for t in cav_surfaces[n]])
        fld.setNumber(dist, "Sampling", 40)
        fields.append(_graded(fld, dist, h, mp.size_mm))
    body = [v for r in ("bulb", "shell") for v in region_vols.get(r, [])]
    bulb_surfs = sorted(
        abs(t) for _, t in gmsh.model.getBoundary([(3, v) for v in body], combined=True, oriented=False)
        if abs(t) in set(outer)
    )
    if "shell" in region_vols:  # the shell-infill interface as finely as the outer surface
        sh = {abs(t) for _, t in gmsh.model.getBoundary([(3, v) for v in region_vols["shell"]], combined=False,
                                                         oriented=False)}
        inf = {abs(t) for _, t in gmsh.model.getBoundary([(3, v) for v in region_vols["bulb"]], combined=False,
                                                          oriented=False)}
        bulb_surfs = sorted(set(bulb_surfs) | (sh & inf))
    for les in lay.lesions:  # a lesion's surface as fine as a cavity wall of its smallest semi-axis
        h_l = min(mp.surface_size_mm, mp.cavity_size_mm(min(les.semi_axes_mm)))
        d_l = fld.add("Distance")
        fld.setNumbers(d_l, "SurfacesList", sorted({abs(t) for _, t in gmsh.model.getBoundary(
            [(3, v) for v in region_vols[les.region]], combined=True, oriented=False)}))
        fld.setNumber(d_l, "Sampling", 40)
        t_l = fld.add("Threshold")
        fld.setNumber(t_l, "InField", d_l)
        fld.setNumber(t_l, "SizeMin", h_l)
        fld.setNumber(t_l, "SizeMax", mp.size_mm)
        fld.setNumber(t_l, "DistMin", 0.5 * h_l)
        fld.setNumber(t_l, "DistMax", 0.5 * h_l + 1.2 * abs(mp.size_mm - h_l))
        fields.append(t_l)
    dist_b = fld.add("Distance")
    fld.setNumbers(dist_b, "SurfacesList", bulb_surfs)
    fld.setNumber(dist_b, "Sampling", 40)
    thr_b = _graded(fld, dist_b, mp.surface_size_mm, mp.size_mm)
    arm_f = fld.add("Constant")
    fld.setNumber(arm_f, "VIn", mp.arm_size_mm)
    fld.setNumber(arm_f, "VOut", mp.size_mm)
    arm_vols = [t for n in design.arm_names for t in region_vols[f"arm_{n}"]]
    fld.setNumbers(arm_f, "VolumesList", arm_vols)
    fld.setNumber(arm_f, "IncludeBoundary", 1)
    fillet_faces = _fillet_faces(design, bulb_surfs) if parts.rounded else []
    fields += _local_refinements(design, mp, bulb_surfs, arm_vols,
                                 fillet_faces)
    fmin = fld.add("Min")
    fld.setNumbers(fmin, "FieldsList", [*fields, thr_b, arm_f])
    fld.setAsBackgroundMesh(fmin)

    for t in fillet_faces:
        # MeshAdapt on the fillet faces: Frontal-Delaunay left slivers there (min dihedral 5.8° vs 7.3° at 6 mm)
        gmsh.model.mesh.setAlgorithm(2, t, 1)
    return fixed, outer


def _mesh_arrays(gmsh, mp: MeshParams, parts: _Regions, fixed: list[int], outer: list[int]) -> dict:
    """Generate the mesh (of ``mp.element_order``) and read it back: nodes, tets by region, the
    cavity walls', fixed and outer triangles, as compact 0-based indices."""
    region_vols, ids, cav_surfaces = parts.region_vols, parts.ids, parts.cav_surfaces
    gmsh.model.mesh.generate(3)
    order = int(mp.element_order)
    if order == 2:
        # mid-edge nodes on the CAD surfaces (OCC), so curved walls stay curved
        gmsh.option.setNumber("Mesh.SecondOrderLinear", 0)
        # curving the boundary edges can invert a thin element next to a curved wall (det J <= 0
        # at a quadrature point); gmsh's high-order optimizer untangles them
        gmsh.model.mesh.setOrder(2)
        gmsh.model.mesh.optimize("HighOrder")
    # gmsh element types: 4 = tet4, 11 = tet10; 2 = tri3, 9 = tri6
    ttype, tn, ftype, fn = (4, 4, 2, 3) if order == 1 else (11, 10, 9, 6)

    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = np.asarray(coords, dtype=float).reshape(-1, 3)
    tets, regs = [], []
    for rname, rid in ids.items():
        for v in region_vols[rname]:
            t = _elements(3, v, ttype, tn)
            tets.append(t)
            regs.append(np.full(len(t), rid, dtype=np.int32))
    tet_tags = np.vstack(tets)
    if order == 2:
        tet_tags = tet_tags[:, GMSH_TET10]
    # node tags -> compact 0-based indices: corners first, then mid-edge nodes, each in tag order
    # (deterministic)
    corner = np.unique(tet_tags[:, :4])
    mid = np.setdiff1d(np.unique(tet_tags[:, 4:]), corner) if order == 2 else np.zeros(0, np.int64)
    used = np.concatenate([corner, mid])
    lookup = np.full(int(max(node_tags.max(), used.max())) + 1, -1, dtype=np.int64)
    lookup[used] = np.arange(len(used))
    pos = np.full(len(lookup), -1, dtype=np.int64)
    pos[np.asarray(node_tags, dtype=np.int64)] = np.arange(len(node_tags))
    nodes = coords[pos[used]]

    def tris(surfs):
        t = np.vstack([_elements(2, s, ftype, fn) for s in surfs]) if surfs else np.zeros((0, fn), np.int64)
        out = lookup[t]
        if (out < 0).any():
            raise MeshError("a surface triangle has a node outside the tetra mesh")
        return out

    cav = {n: tris(s) for n, s in cav_surfaces.items()}
    fix, out = tris(fixed), tris(sorted(outer))
    tt = lookup[tet_tags]
    if order == 1:
        return dict(nodes_mm=nodes, tets=tt, tet_region=np.concatenate(regs), cavities=cav,
                    fixed_faces=fix, outer_faces=out, regions=ids)
    return dict(
        nodes_mm=nodes, tets=tt[:, :4], tet_region=np.concatenate(regs),
        cavities={k: v[:, :3] for k, v in cav.items()}, fixed_faces=fix[:, :3], outer_faces=out[:, :3],
        tets10=tt, cavities6=cav, fixed_faces6=fix, outer_faces6=out, n_corner=len(corner), regions=ids,
    )


# --- guards checked before gmsh runs (milliseconds; docs/robustness.md) ---------------------------

MAX_TETS = 1_000_000
"""Largest estimated element count meshed without ``force`` (~40× the default mesh: a bulb size of ~1.25 mm)."""
CAVITY_VOLUME_TOLERANCE = 0.10
"""Largest relative error of a meshed cavity (or bulb) volume against the design without ``force``."""
_TETS_PER_UNIT = 6.5  # tets per h³ of volume (fitted to the meshes of docs/robustness.md)


def _shell(area: float, h_wall: float, h_far: float) -> float:
    """∫ dV / h³ over the graded layer of a wall (size h_wall at the wall, growing 1:1.2 to h_far),
    minus the same layer at h_far (counted in the volume term)."""
    if h_wall >= h_far:
        return 0.0
    depth = 0.5 * h_wall + 1.2 * (h_far - h_wall)
    inner = 0.5 * h_wall / h_wall**3 + 0.6 * (1 / h_wall**2 - 1 / h_far**2)
    return area * (inner - depth / h_far**3)


def _tube(length: float, h_edge: float, h_far: float) -> float:
    """∫ dV / h³ around an edge of ``length`` meshed at ``h_edge``, the size growing 1:1 with the
    distance to ``h_far``, minus the same tube at h_far."""
    if h_edge >= h_far:
        return 0.0
    a, d = h_edge, h_far - h_edge
    return length * (2 * np.pi * (0.5 / a - 1 / h_far + 0.5 * a / h_far**2) - np.pi * d * d / h_far**3)


def _walls_by_size(sizes: dict[str, float]) -> list[tuple[float, list[str]]]:
    """The cavities grouped by the element size on their walls, each group meshed with one distance
    field over all its walls: the graded size (:func:`_graded`) grows with the distance, so the
    smallest over the group's cavities is the size at its nearest wall, the same value (the same
    mesh) for fewer field evaluations. gmsh evaluates the size field ~2e5 times meshing the curves
    of the default design, whose four arm cavities share one size (docs/performance/design-fem.md).

    >>> _walls_by_size({"a": 1.0, "b": 0.5, "c": 1.0})
    [(1.0, ['a', 'c']), (0.5, ['b'])]
    """
    groups: dict[float, list[str]] = {}
    for name, h in sizes.items():
        groups.setdefault(h, []).append(name)
    return list(groups.items())


def _graded(fld, dist: int, h: float, far: float) -> int:
    """A Threshold field on the distance field ``dist``: ``h`` at it, growing about 1:1 to ``far``."""
    thr = fld.add("Threshold")
    fld.setNumber(thr, "InField", dist)
    fld.setNumber(thr, "SizeMin", h)
    fld.setNumber(thr, "SizeMax", far)
    fld.setNumber(thr, "DistMin", 0.5 * h)
    fld.setNumber(thr, "DistMax", 0.5 * h + 1.2 * abs(far - h))
    return thr


def _fillet_faces(design: BIPDesign, outer_surfs: list[int]) -> list[int]:
    """The fillet faces among the bulb region's outer faces: on neither the bulb's surface nor an
    arm's side (tested at each face's parametric mid-point)."""
    import gmsh

    out = []
    for s in outer_surfs:
        lo, hi = gmsh.model.getParametrizationBounds(2, s)
        p = np.array(gmsh.model.getValue(2, s, [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])]))
        on_arm = any(abs(np.linalg.norm(np.cross(p - g.root_mm, g.direction)) - g.radius_mm) < 1e-6
                     for g in design.arm_geometry())
        if not on_arm and abs(float(design.bulb.signed_distance([p])[0])) > 1e-4:
            out.append(s)
    return out


def _junction_size_mm(design: BIPDesign, mp: MeshParams) -> float:
    """Element size along the arm–bulb edges (0: not refined): ``junction_size_mm``, and at most the
    smallest fillet radius. A fillet face meets the bulb's surface tangentially: facets much coarser
    than its radius cross there ("overlapping facets" at 9 mm with a 2 mm fillet)."""
    fillets = [g.fillet_mm for g in design.arm_geometry() if g.fillet_mm > 0]
    return min([mp.junction_size_mm] * (mp.junction_size_mm > 0) + fillets, default=0.0)


def _local_refinements(design: BIPDesign, mp: MeshParams, bulb_surfs: list[int], arm_vols: list[int],
                       fillet_faces: list[int] = ()) -> list[int]:
    """Size fields of the local refinements: MeshParams ``contact_size_mm`` near the interaction
    points, ``junction_size_mm`` along the arm–bulb edges (along the edges of the ``fillet_faces``
    when the junctions are rounded, then at most the smallest fillet radius, even with
    ``junction_size_mm`` 0); [] when none applies."""
    import gmsh

    fld = gmsh.model.mesh.field
    out = []
    if mp.contact_size_mm > 0:
        h, r = mp.contact_size_mm, mp.contact_zone_mm
        for p in design.p_ext_mm().values():
            # h within r of the point, then growing 1:1 (MathEval: no geometry to add)
            d = f"sqrt((x-({p[0]:.9g}))^2+(y-({p[1]:.9g}))^2+(z-({p[2]:.9g}))^2)"
            f = fld.add("MathEval")
            fld.setString(f, "F", f"{h:.9g}+max(0,{d}-{r:.9g})")
            out.append(f)
    h_junction = _junction_size_mm(design, mp)
    if h_junction > 0:
        if fillet_faces:
            junction = sorted({abs(c) for _, c in gmsh.model.getBoundary([(2, t) for t in fillet_faces], combined=False,
                                                                         oriented=False)})
        else:
            bulb_curves = {abs(c) for _, c in gmsh.model.getBoundary([(2, t) for t in bulb_surfs], combined=False,
                                                                     oriented=False)}
            arm_surfs = gmsh.model.getBoundary([(3, v) for v in arm_vols], combined=False, oriented=False)
            arm_curves = {abs(c) for _, c in gmsh.model.getBoundary(arm_surfs, combined=False, oriented=False)}
            junction = sorted(bulb_curves & arm_curves)
        if not junction:
            raise MeshError("mesh.junction_size_mm: found no edge where the arms meet the bulb")
        dist = fld.add("Distance")
        fld.setNumbers(dist, "CurvesList", junction)
        fld.setNumber(dist, "Sampling", 200)
        out.append(_graded(fld, dist, h_junction, mp.size_mm))
    return out


def estimate_tets(design: BIPDesign, mesh: MeshParams | None = None) -> int:
    """Tetra count gmsh will make for ``design`` at ``mesh`` sizes, from the size field alone
    (``∫ dV / h³`` over the volume and the graded wall layers): 0.84 of the count at 6 mm, 1.12 at
    2.2 mm, low at coarse sizes where the geometry sets the count (docs/robustness.md).

    >>> from softphantom.design import BIPDesign
    >>> 15_000 < estimate_tets(BIPDesign()) < 40_000   # 24 986 when meshed
    True
    """
    from softphantom.design.geometry import capsule_volume

    mp = mesh or design.mesh
    h, hs, ha = mp.size_mm, mp.surface_size_mm, mp.arm_size_mm
    cav = [(g.cavity_radius_mm, g.cavity_volume_mm3, ha) for g in design.arm_geometry()]
    cav += [(c.wall_radius_mm, c.volume_mm3, h) for c in design.cavities]
    bulb = design.bulb.volume_mm3 - sum(c.volume_mm3 for c in design.cavities)
    arms = sum(np.pi * a.radius_mm**2 * a.length_mm - a.cavity_volume_mm3 for a in design.arms)
    total = bulb / h**3 + arms / ha**3 + _shell(design.bulb.area_mm2, hs, h)
    for r, v, far in cav:
        length = max(0.0, v - capsule_volume(r, 0.0)) / (np.pi * r * r)  # a balloon: its volume's capsule
        area = 2 * np.pi * r * length + 4 * np.pi * r * r
        total += _shell(area, mp.cavity_size_mm(r), far)
    h_j = _junction_size_mm(design, mp)
    for g in design.arm_geometry() if h_j > 0 else ():  # a fillet's two edges, or the sharp edge
        edges = 2 * np.pi * (2 * g.radius_mm + g.fillet_mm) if g.fillet_mm > 0 else 2 * np.pi * g.radius_mm
        total += _tube(edges, h_j, min(hs, ha))
    return int(round(_TETS_PER_UNIT * total))


def mesh_size_floor_mm(design: BIPDesign) -> float:
    """The smallest element size worth asking for: the wall size of the design's smallest cavity
    at the most segments allowed (:data:`~softphantom.design.params.MAX_CAVITY_SEGMENTS`)."""
    radii = [a.cavity_radius_mm for a in design.arms] + [c.wall_radius_mm for c in design.cavities]
    return 2 * np.pi * min(radii) / MAX_CAVITY_SEGMENTS


def predicted_cavity_error(mesh: MeshParams) -> float:
    """Relative volume deficit of a cavity wall meshed with ``cavity_segments`` around: an
    inscribed polygon, (2π/n)²/6 (−1.6 % at 22; measured −1.6 % to −1.4 %)."""
    return (2 * np.pi / mesh.cavity_segments) ** 2 / 6


def check_mesh_budget(design: BIPDesign, mesh: MeshParams | None = None, *, force: bool = False) -> int:
    """Refuse, before gmsh runs, sizes below :func:`mesh_size_floor_mm` (always), and without
    ``force`` an estimated element count above :data:`MAX_TETS` or cavity walls too coarse for
    :data:`CAVITY_VOLUME_TOLERANCE`. Returns the estimate. Raises DesignError naming the field."""
    mp = mesh or design.mesh
    n = estimate_tets(design, mp)
    if n > MAX_TETS and not force:
        raise DesignError(f"mesh.size_mm = {mp.size_mm:.4g} mm: about {n:,} tets estimated, above the limit of "
                          f"{MAX_TETS:,} (a coarser --mesh-size-mm, or --force)")
    t = design.layers.shell_mm
    if 0.0 < t < 0.5 * mp.surface_size_mm:
        raise DesignError(f"layers.shell_mm = {t:.4g} mm is thinner than the mesh resolves (at least half of "
                          f"mesh.surface_size_mm = {mp.surface_size_mm:.4g} mm: a finer --mesh-size-mm or a thicker shell)")
    floor = mesh_size_floor_mm(design)
    for name in ("size_mm", "surface_size_mm", "arm_size_mm", "contact_size_mm", "junction_size_mm"):
        v = getattr(mp, name)
        if v < floor and not (v == 0 and name in ("contact_size_mm", "junction_size_mm")):  # 0: off
            raise DesignError(f"mesh.{name} = {v:.4g} mm is below the floor of {floor:.3g} mm (the smallest cavity "
                              f"wall at {MAX_CAVITY_SEGMENTS:g} segments)")
    err = predicted_cavity_error(mp)
    if err > CAVITY_VOLUME_TOLERANCE and not force:
        raise DesignError(f"mesh.cavity_segments = {mp.cavity_segments:.4g} (mesh.size_mm = {mp.size_mm:.4g} mm): "
                          f"cavity volumes would be about {100 * err:.0f} % low, beyond the "
                          f"{100 * CAVITY_VOLUME_TOLERANCE:.0f} % tolerance (raise mesh.cavity_segments, the elements "
                          "around each cavity wall; a finer --mesh-size-mm raises it too; or --force)")
    return n
