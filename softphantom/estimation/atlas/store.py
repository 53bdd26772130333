"""Atlas files: the file format, reading and writing, describing one.

An atlas file (``MODEL/atlas/<key>.npz``, :func:`save_atlas`) is named by the start of its key
(:func:`~softphantom.estimation.atlas.catalogue.atlas_key`: the SHA-256 of the inputs it was built
from), and carries the digest of its own arrays and its provenance
(:func:`~softphantom.estimation.atlas.build.provenance`). Where a model's atlas is looked up,
checked against a model and installed: :mod:`~softphantom.estimation.atlas.catalogue`. Every
refusal is one line naming the file and what does not match (:class:`AtlasCorrupt`,
:class:`AtlasMismatch`).
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.atlas.config import AtlasConfig
from softphantom.estimation.atlas.map import Atlas
from softphantom.estimation.config import EstimatorConfig

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


def atlas_path(model_dir, key: str) -> Path:
    """Where the atlas of key ``key`` lives next to a model directory."""
    return Path(model_dir) / "atlas" / f"{key[:32]}.npz"


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


def read_meta(path) -> dict:
    """The metadata of an atlas file (key, settings, provenance) without reading its arrays; a
    one-line :class:`AtlasCorrupt` if the file is unreadable."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return json.loads(str(z["meta"]))
    except Exception as exc:  # noqa: BLE001 - any unreadable file is corrupt
        raise AtlasCorrupt(f"{path}: not a readable atlas file, truncated or not an atlas "
                           f"({type(exc).__name__})") from None


def estimator_config(meta, path) -> EstimatorConfig:
    """The estimator settings an atlas was built with (those its key depends on: contact point,
    patch radius, solver tolerance), from its provenance (an Atlas, a file's metadata or its
    provenance dict); :class:`AtlasMismatch` if it has none."""
    prov = meta.provenance if isinstance(meta, Atlas) else meta.get("provenance", meta)
    prov = prov or {}
    if "contact" not in prov:
        raise AtlasMismatch(f"{path}: the atlas records no provenance (written by an older softphantom), so "
                            f"it cannot be checked against a model: rebuild it (softphantom atlas build)")
    c = prov["contact"]
    return EstimatorConfig(contact=c if isinstance(c, str) else tuple(c),
                           contact_radius_m=float(prov["contact_radius_m"]), tol=float(prov["tol"]))


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
