"""An atlas's identity and what it records of its model: the key made from inputs only
(:func:`atlas_key`), and the rest-state quantities that catch a stale atlas by numbers
(:func:`rest_checks`). Used by the build (:mod:`~softphantom.estimation.atlas.build`) and the
catalogue (:mod:`~softphantom.estimation.atlas.catalogue`)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from softphantom.estimation.atlas.config import AtlasConfig
from softphantom.estimation.atlas.map import Atlas
from softphantom.estimation.config import EstimatorConfig

# what the key hashes: bump when the build changes the meaning of the numbers (3: stretched axes;
# 4: x_control, cFx; 5: inputs only, as stored or as written)
KEY_FORMAT = 5

# Staleness checks (verify_atlas): the stated tolerances. The rest state and volumes are the
# model's own arrays and sums (same inputs, last bits of a sum may differ by CPU); the zero-load
# error is the atlas's own interpolation error at zero load, recorded when it was built, and must
# come out the same from this model.
REST_TOL = {
    "rest nodes": (1e-12, "m"),               # |x_rest - model nodes|, the atlas's rest state
    "rest cavity volumes": (1e-9, "rel"),     # each cavity's volume at rest, relative
    "contact patch force sums": (1e-9, "N/N"),  # each column of the contact's actuator sums to 1 N
    "zero load: tracked points": (1e-6, "mm"),  # |atlas points(0) - rest points| as recorded
    "zero load: cavity volumes": (1e-6, "mm³"),  # |atlas volumes(0)| as recorded
}


# -- the key ---------------------------------------------------------------------------------------

def _code_constants() -> dict:
    """The build's constants that change an atlas's numbers (a change gives new keys)."""
    from softphantom.estimation.atlas import config

    return {"FIELD_RTOL": config.FIELD_RTOL, "FIELD_MAX_MODES": config.FIELD_MAX_MODES, "NODE_TOL": config.NODE_TOL}


def _contact_m(model, contact) -> list[float]:
    from softphantom.estimation.forward import contact_point

    return [float(v) for v in contact_point(model, contact)]


def key_inputs(model, config: EstimatorConfig, acfg: AtlasConfig) -> tuple[dict, dict[str, np.ndarray]]:
    """What :func:`atlas_key` hashes: (the settings as JSON-able values, the model's arrays as
    stored). Every float here is an input (read from a file or given), never computed here."""
    from softphantom.fem.model import material_specs, mesh_arrays

    nodes, elements, fixed, cavities = mesh_arrays(model)
    arrays = {"nodes": np.asarray(nodes, "<f8"), "elements": np.asarray(elements, "<i8"),
              "fixed_nodes": np.asarray(fixed, "<i8"), "element_region": np.asarray(model.tet_region, "<i8")}
    for name, faces in cavities.items():
        arrays[f"cavity:{name}"] = np.asarray(faces, "<i8")
    design = getattr(model, "design", None)
    atlas = acfg.as_dict()
    if not acfg.linear_pressure:
        del atlas["linear_pressure"]
    meta = {
        "format": KEY_FORMAT,
        "element_order": int(getattr(model, "element_order", 1)),
        "regions": {k: int(v) for k, v in model.regions.items()},
        "materials": {r: [law, [list(kv) for kv in values]]
                      for r, (law, values) in material_specs(design, model.regions).items()},
        "cavities": list(cavities),
        "loads": list(getattr(design, "pressure_names", ("urethra",)) if design is not None else ("urethra",)),
        "contact_m": _contact_m(model, config.contact),
        "contact_radius_m": float(config.contact_radius_m),
        "markers": [[k, [float(v) for v in model.markers[k]]] for k in model.markers],
        "targets": [[k, [float(v) for v in model.targets[k]]] for k in model.targets],
        "atlas": atlas,
        "tol": float(config.tol),
        "constants": _code_constants(),
    }
    if design is not None:
        meta["sensing"] = list(design.sensing_names)
    return meta, arrays


def atlas_key(model, config: EstimatorConfig, acfg: AtlasConfig) -> str:
    """SHA-256 (hex) of :func:`key_inputs`: the key of ``model``'s atlas ``acfg`` at the contact
    and tolerance of ``config``. The same on every machine for the same files and settings.

    >>> from softphantom.design import load_model
    >>> from softphantom.design.model import SHIPPED_MODELS
    >>> m = load_model(SHIPPED_MODELS / "bip_p2")
    >>> a = atlas_key(m, EstimatorConfig(), AtlasConfig())
    >>> a == atlas_key(m, EstimatorConfig(), AtlasConfig()), a == atlas_key(m, EstimatorConfig(contact="off-centre"), AtlasConfig())
    (True, False)
    """
    meta, arrays = key_inputs(model, config, acfg)
    h = hashlib.sha256()
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        h.update(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
        h.update(a.tobytes())
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()


def piece_keys(model, config: EstimatorConfig, acfg: AtlasConfig) -> tuple[str, ...]:
    """The key of each piece of ``acfg`` (:meth:`AtlasConfig.pieces`), in order."""
    return tuple(atlas_key(model, config, sub) for sub in acfg.pieces())


@dataclass(frozen=True)
class Check:
    """One quantity of :func:`verify_atlas`: ``quantity`` (a key of :data:`REST_TOL`), the largest
    ``difference`` found, the ``tolerance`` and its ``unit``."""

    quantity: str
    difference: float
    tolerance: float
    unit: str

    @property
    def ok(self) -> bool:
        return bool(self.difference <= self.tolerance)


def _rest_quantities(at: Atlas, model, fem=None, fwd=None) -> dict:
    """The quantities an atlas records of its model at rest (see :data:`REST_TOL`): cavity volumes
    (mm³), the contact patch (nodes, force sums per axis) and the atlas's error at zero load.
    ``fwd``: the ForwardModel the atlas was built with (its FEM, actuator and probe reused)."""
    from softphantom.estimation.forward import contact_point
    from softphantom.fem import probe_matrix
    from softphantom.fem.actuators import cavity_volume, force_actuator
    from softphantom.fem.model import fem_from_phantom, mesh_arrays

    nodes, _, _, cavities = mesh_arrays(model)
    out = {"cavity_volumes_mm3": {k: cavity_volume(np.asarray(nodes, float).reshape(-1), f) * 1e9
                                  for k, f in cavities.items()}}
    prov = at.provenance or {}
    if fwd is not None:
        fem = fwd.fem
    fem = fem if fem is not None else fem_from_phantom(model)
    H = fwd.H_f if fwd is not None else force_actuator(fem, contact_point(model, _contact_of(prov)),
                                                       float(prov["contact_radius_m"]))
    out["contact_patch"] = {"nodes": int(len(np.unique(H.nonzero()[0] // 3))),
                            "force_sums": [float(v) for v in np.asarray(H.sum(axis=0)).ravel()]}
    lam = np.zeros(4)
    held = tuple(at.config.held_kPa)
    if all(lo <= 0.0 <= hi for lo, hi in zip(at.config.lower, at.config.upper)) and not any(held):
        pts = [model.markers[k] for k in model.markers] + [model.targets[k] for k in model.targets]
        probe = fwd.probe if fwd is not None else probe_matrix(fem, pts)
        rest = probe @ fem.x_rest.reshape(-1, 3)
        out["zero_load"] = {"points_mm": float(np.abs(at.points(lam) - rest).max() * 1e3),
                            "volumes_mm3": float(np.abs(at.volumes(lam)[0]).max() * 1e9)}
    return out


def _contact_of(prov: dict):
    c = prov["contact"]
    return c if isinstance(c, str) else tuple(c)


def rest_record(at: Atlas, model, fwd=None) -> dict:
    """What a new atlas records of its model at rest, for :func:`verify_atlas` (provenance
    ``rest``)."""
    return _rest_quantities(at, model, fwd=fwd)


def rest_checks(at: Atlas, model, fem=None) -> list[Check]:
    """The staleness checks of atlas ``at`` against ``model``: what it recorded at rest, recomputed
    from the model (:data:`REST_TOL`). An atlas recording nothing is checked on its rest nodes only."""
    from softphantom.fem.model import mesh_arrays

    nodes = np.asarray(mesh_arrays(model)[0], float).reshape(-1)
    checks = [Check("rest nodes", float(np.abs(at.x_rest - nodes).max()) if at.x_rest.shape == nodes.shape
                    else float("inf"), *REST_TOL["rest nodes"])]
    rec = (at.provenance or {}).get("rest")
    if not rec:
        return checks
    now = _rest_quantities(at, model, fem)
    v0, v1 = rec["cavity_volumes_mm3"], now["cavity_volumes_mm3"]
    rel = max((abs(v1[k] - v0[k]) / abs(v0[k]) if k in v1 else float("inf")) for k in v0) if v0 else 0.0
    checks.append(Check("rest cavity volumes", rel if set(v0) == set(v1) else float("inf"),
                        *REST_TOL["rest cavity volumes"]))
    p0, p1 = rec["contact_patch"], now["contact_patch"]
    d = max(abs(a - b) for a, b in zip(p0["force_sums"], p1["force_sums"]))
    checks.append(Check("contact patch force sums", d if p0["nodes"] == p1["nodes"] else float("inf"),
                        *REST_TOL["contact patch force sums"]))
    if "zero_load" in rec and "zero_load" in now:
        for name, k in (("zero load: tracked points", "points_mm"), ("zero load: cavity volumes", "volumes_mm3")):
            checks.append(Check(name, abs(now["zero_load"][k] - rec["zero_load"][k]), *REST_TOL[name]))
    return checks
