"""Atlas files as artefacts: check one against a model, describe it, install it in a model directory.

An atlas file (``MODEL/atlas/<key>.npz``, :meth:`~softphantom.estimation.atlas.Atlas.save`) is
content-addressed: its name is the start of the SHA-256 of everything it was built from (mesh,
law, element, contact patch, tracked points, envelope, grid, solver tolerance, file format,
:func:`~softphantom.estimation.atlas.atlas_key`), and it carries the digest of its own arrays and
its provenance (:func:`~softphantom.estimation.atlas.provenance`). So a file built on one machine of
a lab can be copied to another: :func:`verify_atlas` recomputes its key from the model there,
:func:`install_atlas` puts it where :func:`~softphantom.estimation.atlas.load_or_build` finds it.
Every refusal is one line naming the file and what does not match
(:class:`~softphantom.estimation.atlas.AtlasCorrupt`, :class:`~softphantom.estimation.atlas.AtlasMismatch`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from softphantom.estimation.atlas import (
    Atlas, AtlasCorrupt, AtlasMismatch, atlas_key, atlas_path,
)
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.forward import ForwardModel


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
    at = Atlas.load(path)
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
    >>> from softphantom.estimation.atlas import AtlasConfig
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
                     f"p_u {c.p_min_kPa:g}…{c.p_max_kPa:g} kPa"),
        ("grid", f"{' × '.join(map(str, c.shape))} points ({at.solves} solves{unsolved}), first axis {c.x_control}"),
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
            Atlas.load(dest, at.key)
            return dest, "present"
        except (AtlasCorrupt, AtlasMismatch):
            what = "replaced"
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.copyfile(path, tmp)
    tmp.replace(dest)
    return dest, what


def model_atlases(model_dir) -> list[Path]:
    """The atlas files cached in a model directory, by name."""
    d = Path(model_dir) / "atlas"
    return sorted(p for p in d.glob("*.npz") if p.is_file()) if d.is_dir() else []
