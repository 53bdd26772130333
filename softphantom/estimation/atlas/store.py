"""Atlas files: the cache key, the file format, reading and writing; checking a file against a
model, describing it, installing it in a model directory.

An atlas file (``MODEL/atlas/<key>.npz``, :func:`save_atlas`) is content-addressed: its name is
the start of the SHA-256 of everything it was built from (mesh, law, element, contact patch,
tracked points, envelope, grid, solver tolerance, file format: :func:`atlas_key`), and it carries
the digest of its own arrays and its provenance
(:func:`~softphantom.estimation.atlas.build.provenance`). So a file built on one machine of a lab
can be copied to another: :func:`verify_atlas` recomputes its key from the model there,
:func:`install_atlas` puts it where :func:`~softphantom.estimation.atlas.build.load_or_build`
finds it. Every refusal is one line naming the file and what does not match
(:class:`AtlasCorrupt`, :class:`AtlasMismatch`).
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.atlas.config import AtlasConfig
from softphantom.estimation.atlas.map import Atlas
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.forward import ForwardModel

# what the key hashes: bump when the build changes the meaning of the numbers (3: stretched axes;
# 4: x_control, cFx)
KEY_FORMAT = 4
# the file layout, apart from the key: 5 stores the field compact (below); format 4 files still read
FORMAT = 5
READS = (4, 5)
AXIS_NAMES = ("f_x", "f_y", "f_z", "p_u")
ARRAYS = ("cV", "cP", "cF", "cFx", "q_nodes", "modes", "x_rest", "solved")  # an atlas file's arrays
# The displacement field serves the live view and the report's deformed phantom (the tracked
# markers and targets have polynomials of their own, cP, kept in float64 with the volumes and f_x):
# its POD modes are stored as float16 scaled per mode (≤ 2^-11 of a mode's largest entry:
# measured ≤ 1e-3 of the largest displacement) and their coefficients as float32, which makes a
# quadratic model's atlas 4x smaller.
COMPACT = {"cF": np.float32}


class AtlasCorrupt(UserError):
    """An atlas file that cannot be used (unreadable, or content not matching its digest)."""


class AtlasMismatch(UserError):
    """A readable atlas file that is not for this use (another file format, model or settings)."""


def atlas_key(fwd: ForwardModel, acfg: AtlasConfig) -> str:
    """SHA-256 (hex) of everything the atlas depends on: mesh and fixed DOFs, law and parameters,
    element, cavities, contact patch (its actuator), tracked points (the probe), envelope, grid,
    solver tolerance, format."""
    h = hashlib.sha256()
    fem = fwd.fem

    def add(a) -> None:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())

    add(fem.x_rest)
    add(fem.tets)
    add(fem.free_dofs)
    # the law per element (its id and parameters) and the element (the connectivity's width):
    # whatever the FemModel carries, so a new law or element order changes the key
    for name in ("mu", "lam", "law_id", "params"):
        v = getattr(fem, name, None)
        if v is not None:
            add(np.asarray(v))
    for name in sorted(fem.cavities):
        h.update(name.encode())
        add(np.asarray(fem.cavities[name]))
    for M in (fwd.H_f.tocsr(), fwd.probe.tocsr()):
        M.sort_indices()
        add(M.indptr)
        add(M.indices)
        add(M.data)
    atlas = acfg.as_dict()
    if not acfg.linear_pressure:  # the keys of atlases built before the option stay valid
        del atlas["linear_pressure"]
    meta = {"format": KEY_FORMAT, "atlas": atlas, "tol": fwd.config.tol,
            "markers": fwd.marker_names, "targets": fwd.target_names}
    names = tuple(getattr(fwd, "pressure_names", ()))
    if len(names) > 1:  # which cavities are loads, in λ's order: a stack's levels hold p_2 … p_M
        meta["pressures"] = names
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


def atlas_path(model_dir, key: str) -> Path:
    """Where the atlas of key ``key`` lives next to a model directory."""
    return Path(model_dir) / "atlas" / f"{key[:32]}.npz"


def shipped_atlas(key: str) -> Path | None:
    """The atlas of key ``key`` if the package ships it (``softphantom/data/models/*/atlas/``), else
    None. Found by content: any model directory whose mesh, law and settings give this key uses it.

    >>> shipped_atlas("0" * 64) is None
    True
    """
    from softphantom.design.model import SHIPPED_MODELS

    return next(iter(sorted(SHIPPED_MODELS.glob(f"*/atlas/{key[:32]}.npz"))), None)


def _digest(arrays: dict[str, np.ndarray], keys=None) -> str:
    """SHA-256 of the arrays' bytes, in the order of ``keys`` (default: by name; format 4 files: ``ARRAYS``)."""
    h = hashlib.sha256()
    for k in sorted(arrays) if keys is None else keys:
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def stored_arrays(at: Atlas) -> dict[str, np.ndarray]:
    """The arrays as a file of this :data:`FORMAT` holds them: the field compact (:data:`COMPACT`,
    the modes as float16 of their largest entry, ``modes_scale``)."""
    out = {k: np.asarray(getattr(at, k)) for k in ARRAYS}
    for k, dtype in COMPACT.items():
        out[k] = out[k].astype(dtype)
    modes = np.asarray(at.modes, dtype=np.float64)
    scale = np.abs(modes).max(axis=0)
    scale[scale == 0] = 1.0
    out["modes"] = (modes / scale).astype(np.float16)
    out["modes_scale"] = scale
    return out


def _from_stored(arrays: dict[str, np.ndarray], fmt: int) -> dict[str, np.ndarray]:
    if fmt < 5:
        return {k: arrays[k] for k in ARRAYS}
    out = {k: arrays[k] for k in ARRAYS if k != "modes"}
    out["modes"] = arrays["modes"].astype(np.float32) * arrays["modes_scale"].astype(np.float32)
    return out


def save_atlas(at: Atlas, path) -> Path:
    """Write the atlas ``at`` to ``path`` (compressed npz of :func:`stored_arrays`; written to a
    temporary name, then renamed: never half a file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = stored_arrays(at)
    meta = {"format": FORMAT, "key": at.key, "config": at.config.as_dict(), "build_s": at.build_s,
            "solves": at.solves, "field_rms_m": at.field_rms_m, "build_cpu_s": at.build_cpu_s,
            "digest": _digest(arrays), "provenance": at.provenance or {}}
    buf = io.BytesIO()
    np.savez_compressed(buf, meta=np.array(json.dumps(meta)), **arrays)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buf.getvalue())
    tmp.replace(path)
    return path


def load_atlas(path, key: str | None = None) -> Atlas:
    """Read an atlas. One-line errors naming the file and what is wrong with it:
    :class:`AtlasCorrupt` if it is unreadable (truncated, not an atlas) or its arrays do not
    match the digest it was written with (modified or damaged); :class:`AtlasMismatch` if it
    was written by a softphantom of another file format, or ``key`` is given and differs
    (another model, law, contact, envelope or grid)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            fmt = meta.get("format")
            if fmt not in READS:
                raise AtlasMismatch(f"{path}: atlas file format {fmt}, this softphantom reads formats "
                                    f"{', '.join(map(str, READS))} (written by another version): rebuild it "
                                    f"(softphantom atlas build)")
            stored = {k: z[k] for k in z.files if k != "meta"}
        ok = _digest(stored, None if fmt >= 5 else ARRAYS) == meta["digest"]
        at = Atlas(key=meta["key"], config=AtlasConfig(**meta["config"]), build_s=float(meta["build_s"]),
                   solves=int(meta["solves"]), field_rms_m=float(meta["field_rms_m"]),
                   build_cpu_s=float(meta.get("build_cpu_s", "nan")), provenance=meta.get("provenance") or None,
                   **_from_stored(stored, fmt))
    except AtlasMismatch:
        raise
    except Exception as exc:  # noqa: BLE001 - any unreadable file is corrupt
        raise AtlasCorrupt(f"{path}: not a readable atlas file, truncated or not an atlas "
                           f"({type(exc).__name__})") from None
    if not ok:
        raise AtlasCorrupt(f"{path}: atlas arrays do not match the digest they were written with "
                           f"(modified or damaged)")
    if key is not None and at.key != key:
        raise AtlasMismatch(f"{path}: atlas built for another model, law, contact or envelope "
                            f"(key {at.key[:12]}…, expected {key[:12]}…); rebuild it")
    return at


def estimator_config(at: Atlas, path) -> EstimatorConfig:
    """The estimator settings an atlas was built with (those its key depends on: contact point,
    patch radius, solver tolerance), from its provenance; :class:`AtlasMismatch` if it has none."""
    prov = at.provenance or {}
    if "contact" not in prov:
        raise AtlasMismatch(f"{path}: the atlas records no provenance (written by an older softphantom), so "
                            f"it cannot be checked against a model: rebuild it (softphantom atlas build)")
    c = prov["contact"]
    return EstimatorConfig(contact=c if isinstance(c, str) else tuple(c),
                           contact_radius_m=float(prov["contact_radius_m"]), tol=float(prov["tol"]))


def verify_atlas(path, model, fwd: ForwardModel | None = None) -> Atlas:
    """The atlas in ``path`` if it is intact and was built for ``model`` (its key recomputed from
    the model and the file's own settings); else a one-line :class:`AtlasCorrupt` or
    :class:`AtlasMismatch`. ``fwd``: a forward model of ``model`` to reuse (its contact must be the
    file's)."""
    at = load_atlas(path)
    cfg = estimator_config(at, path)
    if fwd is None or fwd.config.contact != cfg.contact or fwd.config.contact_radius_m != cfg.contact_radius_m \
            or fwd.config.tol != cfg.tol:
        fwd = ForwardModel(model, cfg)
    key = atlas_key(fwd, at.config)
    if key != at.key:
        raise AtlasMismatch(f"{path}: atlas built for another model, law, element or mesh than this one "
                            f"(its key {at.key[:12]}…, this model with its settings gives {key[:12]}…)")
    return at


def describe(at: Atlas) -> list[tuple[str, str]]:
    """Lines (label, value) that tell a user what an atlas is: what ``softphantom atlas info`` prints.

    >>> import numpy as np
    >>> c = AtlasConfig(n_force=(3, 3, 3), n_pressure=2)
    >>> z = np.zeros
    >>> at = Atlas(key="ab" * 32, config=c, cV=z((3, 3, 3, 2, 4)), cP=z((3, 3, 3, 2, 1, 3)), cF=z((3, 3, 3, 2, 1)),
    ...            modes=z((6, 1)), x_rest=z(6), build_s=12.0, solves=54, field_rms_m=0.0, solved=np.ones((3, 3, 3, 2)))
    >>> dict(describe(at))["grid"]
    '3 × 3 × 3 × 2 points (54 solves, all converged), first axis force'
    """
    c = at.config
    prov = at.provenance or {}
    lo, hi = c.force_min_N, c.force_max_N
    contact = prov.get("contact", "?")
    if not isinstance(contact, str):
        contact = "(" + ", ".join(f"{v * 1e3:.1f}" for v in contact) + ") mm"
    unsolved = f", {at.unsolved} unreachable" if at.unsolved else ", all converged"
    rows = [
        ("key", at.key),
        ("model", f"{prov.get('model', '?')}: {prov.get('nodes', '?')} nodes, element order {prov.get('element_order', '?')}"),
        ("contact", f"{contact}, patch radius {prov.get('contact_radius_m', float('nan')) * 1e3:.1f} mm"),
        ("envelope", f"f_x {lo[0]:g}…{hi[0]:g} N, f_y {lo[1]:g}…{hi[1]:g} N, f_z {lo[2]:g}…{hi[2]:g} N, "
                     f"p_u {c.p_min_kPa:g}…{c.p_max_kPa:g} kPa"
                     + (f"; a stack's level: p_2… held at {', '.join(f'{v:g}' for v in c.held_kPa)} kPa"
                        if c.held_kPa else "")),
        ("grid", f"{' × '.join(map(str, c.shape))} points ({at.solves} solves{unsolved}), first axis {c.x_control}"
                 + ("" if c.hermite_axis is None else f", Hermite along {AXIS_NAMES[c.hermite_axis]} "
                    f"({c.coef_shape[c.hermite_axis]} terms)")),
        ("build", f"{at.build_s:.0f} s wall, {at.build_cpu_s:.0f} CPU-s"),
        ("size", f"{at.nbytes / 1e6:.1f} MB of coefficients, {at.field_modes} field modes"),
        ("built", f"{prov.get('built_utc', '?')} by softphantom {prov.get('softphantom', '?')}"),
    ]
    off = prov.get("offline")
    if off:  # a grid solved by the reduced model: its size and its measured error
        rows.insert(5, ("offline", f"reduced model ({off['snapshots']} full snapshot solves, basis {off['basis']}, "
                                   f"{off['elements']} ECSW elements); {off['checks']} full checks: volumes within "
                                   f"{off['check_max_dV_mm3']:.3f} mm³, points {off['check_max_points_mm']:.4f} mm, "
                                   f"f_x {off['check_max_fx_N']:.4f} N"))
    return rows


def install_atlas(path, model, model_dir) -> tuple[Path, str]:
    """Verify the atlas file ``path`` against ``model`` and copy it to where the model directory's
    estimators find it (``MODEL/atlas/<key>.npz``). Returns (destination, what happened: ``"added"``,
    ``"present"`` when an intact copy is already there, ``"replaced"`` when the one there was damaged).
    A file that does not verify is refused (nothing is written)."""
    at = verify_atlas(path, model)
    dest = atlas_path(model_dir, at.key)
    what = "added"
    if dest.is_file():
        try:
            load_atlas(dest, at.key)
            return dest, "present"
        except (AtlasCorrupt, AtlasMismatch):
            what = "replaced"
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.copyfile(path, tmp)
    tmp.replace(dest)
    return dest, what


def model_atlases(model_dir, model=None) -> list[Path]:
    """The atlas files cached in a model directory, by name; with ``model``, then those the package
    ships for a model of the same mesh (:func:`shipped_atlas`)."""
    d = Path(model_dir) / "atlas"
    own = sorted(p for p in d.glob("*.npz") if p.is_file()) if d.is_dir() else []
    return own + ([p for p in _shipped_for(model) if p.name not in {q.name for q in own}] if model is not None else [])


def _shipped_for(model) -> list[Path]:
    from softphantom.design.model import SHIPPED_MODELS, load_model

    for d in sorted(SHIPPED_MODELS.glob("*/atlas")):
        m = load_model(d.parent)
        if m.nodes.shape == model.nodes.shape and np.array_equal(m.nodes, model.nodes) \
                and np.array_equal(m.tets, model.tets):
            return sorted(d.glob("*.npz"))
    return []
