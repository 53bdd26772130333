"""Design files: a design as a nested dict, TOML or JSON, and back. Each table's keys are checked
here, naming the table; its values by the part it makes (design/parts.py), the whole by the
design (:func:`~softphantom.design.params.design_from_dict`, :func:`~softphantom.design.params.load_design`).
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import tomli_w

from softphantom.design.checks import _validate_arm_names
from softphantom.design.fabrication import MoldParams
from softphantom.design.parts import (
    _CAVITY_KEYS,
    _CAVITY_NEEDS,
    ArmParams,
    BulbParams,
    CapsuleCavity,
    EllipsoidCavity,
    InteractionParams,
    LayersParams,
    LesionParams,
    MaterialSpec,
    MeshParams,
    SensorParams,
    UrethraParams,
    Vec3,
    _contact_points,
    _named_points,
)
from softphantom.errors import DesignError
from softphantom.records.names import ARM_NAMES

if TYPE_CHECKING:
    from softphantom.design.params import BIPDesign


_SUBS = {"bulb": BulbParams, "urethra": UrethraParams, "interaction": InteractionParams, "mesh": MeshParams,
         "molds": MoldParams, "sensors": SensorParams}
_ARM_KEYS = [f.name for f in dataclasses.fields(ArmParams) if f.name != "name"]


def _plain(v: Any) -> Any:
    return [_plain(x) for x in v] if isinstance(v, (tuple, list)) else v


def design_to_dict(design: BIPDesign) -> dict[str, Any]:
    """Plain nested dict (TOML/JSON-ready) of a design (the inverse of
    :func:`~softphantom.design.params.design_from_dict`)."""
    out: dict[str, Any] = {"name": design.name}
    cavs = design.cavities
    for sub in _SUBS:
        if sub == "urethra":  # the BIP's [urethra] table; other cavities under [cavities]
            if isinstance(design.urethra, UrethraParams):
                out[sub] = {k: _plain(v) for k, v in dataclasses.asdict(design.urethra).items()}
            continue
        out[sub] = {k: _plain(v) for k, v in dataclasses.asdict(getattr(design, sub)).items()}
    out["bulb"] = _bulb_to_dict(design.bulb)
    if design.arm_names != ARM_NAMES:  # the BIP's file stays as it was
        out["arm_names"] = list(design.arm_names)
    out["arms"] = {
        a.name: {k: (list(getattr(a, k)) if isinstance(getattr(a, k), tuple) else getattr(a, k)) for k in _ARM_KEYS}
        for a in design.arms
    }
    if not (len(cavs) == 1 and isinstance(cavs[0], UrethraParams)):  # the BIP's file stays as it was
        out["cavities"] = {c.name: {k: _plain(v) for k, v in dataclasses.asdict(c).items() if k != "name"}
                           for c in cavs if not isinstance(c, UrethraParams)}
        if cavs and isinstance(design.urethra, UrethraParams) and cavs[0] is not design.urethra:
            out["cavity_names"] = list(design.internal_cavity_names)
    out["markers"] = {k: list(v) for k, v in design.markers}
    out["targets"] = {k: list(v) for k, v in design.targets}
    if design.contacts:  # a file without them stays as it was
        out["contacts"] = {k: list(v) for k, v in design.contacts}
    out["materials"] = {m.name: {"law": m.law, **dict(m.values)} for m in design.materials}
    out["region_materials"] = dict(design.region_materials)
    if not design.layers.is_default:  # a one-material design's file stays as it was
        out["layers"] = {"shell_mm": design.layers.shell_mm,
                         "lesions": {x.name: {"center_mm": list(x.center_mm), "semi_axes_mm": list(x.semi_axes_mm)}
                                     for x in design.layers.lesions}}
    return out


def _bulb_to_dict(bulb: BulbParams) -> dict[str, Any]:
    """The ``[bulb]`` table: an ellipsoid's semi-axes alone (its file stays as it was), a parametric
    shape's parameters (its triangles are derived on loading), an imported surface's triangles."""
    if bulb.is_parametric:
        return {"shape": bulb.shape, "semi_axes_mm": list(bulb.semi_axes_mm), "exponents": list(bulb.exponents),
                "bend_mm": bulb.bend_mm}
    keys = ("semi_axes_mm", "surface_vertices_mm", "surface_faces") if bulb.is_surface else ("semi_axes_mm",)
    return {k: _plain(getattr(bulb, k)) for k in keys}


def _check_keys(path: str, given: dict, allowed) -> None:
    """A table (and with ``allowed``, of those keys; the parameter tables check their own)."""
    if not isinstance(given, dict):
        raise DesignError(f"{path}: expected a table, got {given!r}")
    unknown = sorted(set(given) - set(allowed if allowed is not None else given))
    if unknown:
        raise DesignError(f"{path}: unknown key {unknown[0]!r} (known: {', '.join(sorted(allowed))})")


def _arms_from_dict(data: dict[str, Any], default_arms: tuple[ArmParams, ...], surface: bool) -> tuple[ArmParams, ...]:
    """The arms of a design file: ``arm_names`` (default: the BIP's four) in the sensor order, each
    from its ``[arms.NAME]`` table; a BIP arm's missing keys keep its defaults, another arm gives at
    least ``direction`` and ``cavity_volume_mm3``."""
    given = data.get("arms", {})
    _check_keys("arms", given, None)
    names = data.get("arm_names", [a.name for a in default_arms])
    if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
        raise DesignError(f"arm_names: expected a list of names, got {names!r}")
    _validate_arm_names(tuple(names))
    extra = [n for n in given if n not in names]
    if extra:
        raise DesignError(f"arms.{extra[0]}: not one of the design's arms ({', '.join(names)}); list every arm, in "
                          "the sensor order, in arm_names = [...]")
    by_name = {a.name: a for a in default_arms}
    arms = []
    for n in names:
        over = given.get(n, {})
        _check_keys(f"arms.{n}", over, _ARM_KEYS)
        if n in by_name:
            a = by_name[n]
        else:
            missing = [k for k in ("direction", "cavity_volume_mm3") if k not in over]
            if missing:
                raise DesignError(f"arms.{n}.{missing[0]}: missing (a new arm needs direction and cavity_volume_mm3)")
            a = ArmParams(n, over["direction"], over["cavity_volume_mm3"])
        if surface and "junction_fillet_mm" not in over:
            a = dataclasses.replace(a, junction_fillet_mm=0.0)  # OCC fillets smooth surfaces only
        arms.append(dataclasses.replace(a, **over))
    return tuple(arms)


def _cavities_from_dict(data: dict[str, Any], default: tuple) -> tuple:
    """The internal cavities of a design file: ``[urethra]`` (the BIP's; kept by default) and the
    ``[cavities.NAME]`` tables, in ``cavity_names`` order (default: the urethra, then the tables').
    Giving ``[cavities]`` without ``[urethra]`` leaves the urethra out (``cavities = {}``: none)."""
    given_u, given_c = data.get("urethra"), data.get("cavities")
    if given_u is not None:
        _check_keys("urethra", given_u, None)
        if "role" in given_u:
            raise DesignError(f"urethra.role = {given_u['role']!r}: the [urethra] is actuated (its pressure a known "
                              "load); a measured capsule is a [cavities.NAME] table with role = \"measured\"")
    base_u = next((c for c in default if isinstance(c, UrethraParams)), None) or UrethraParams()
    if given_c is None:
        if given_u is None:
            return default
        return (dataclasses.replace(base_u, **given_u),)
    if not isinstance(given_c, dict):
        raise DesignError(f"cavities: expected tables [cavities.NAME] (shape = capsule or ellipsoid), got {given_c!r}")
    cavs = []
    if given_u is not None:
        if "urethra" in given_c:
            raise DesignError("cavities.urethra: the urethra is also given as [urethra] (keep one)")
        cavs.append(dataclasses.replace(base_u, **given_u))
    for name, spec in given_c.items():
        where = f"cavities.{name}"
        _check_keys(where, spec, None)
        shape = spec.get("shape", "capsule")
        if shape not in _CAVITY_KEYS:
            raise DesignError(f"{where}.shape = {shape!r}: expected capsule or ellipsoid")
        _check_keys(where, spec, _CAVITY_KEYS[shape])
        missing = [k for k in _CAVITY_NEEDS[shape] if k not in spec]
        if missing:
            raise DesignError(f"{where}.{missing[0]}: missing (a {shape} cavity needs {', '.join(_CAVITY_NEEDS[shape])})")
        cls = CapsuleCavity if shape == "capsule" else EllipsoidCavity
        cavs.append(cls(name=str(name), **spec))
    order = data.get("cavity_names")
    if order is not None:
        have = [c.name for c in cavs]
        if not (isinstance(order, list) and all(isinstance(n, str) for n in order)):
            raise DesignError(f"cavity_names: expected a list of names, got {order!r}")
        if sorted(order) != sorted(have):
            raise DesignError(f"cavity_names: {order} must list each internal cavity once ({', '.join(have) or 'none'})")
        cavs = [cavs[have.index(n)] for n in order]
    return tuple(cavs)


def design_kwargs(data: dict[str, Any], default: BIPDesign) -> dict[str, Any]:
    """The arguments of a design (:func:`~softphantom.design.params.design_from_dict`) from a
    nested dict: ``default``'s where ``data`` has no key, ``markers``/``targets``/``contacts``
    replaced when it has; each table's keys checked, naming the table."""
    _check_keys("design", data, ["name", "arm_names", "arms", "cavities", "cavity_names", "markers", "targets",
                                 "contacts", "materials", "region_materials", "layers", "snap_to_surface", *_SUBS])
    snap = data.get("snap_to_surface", False)
    if not isinstance(snap, bool):
        raise DesignError(f"snap_to_surface: expected true or false, got {snap!r}")
    defaults = {f.name: getattr(default, f.name) for f in dataclasses.fields(default)}
    kwargs: dict[str, Any] = dict(defaults)
    if "name" in data:
        kwargs["name"] = data["name"]
    kwargs["cavities"] = _cavities_from_dict(data, defaults["cavities"])
    for sub in _SUBS:
        if sub in data and sub != "urethra":
            _check_keys(sub, data[sub], None)
            if sub == "bulb" and data[sub].get("shape", "ellipsoid") != "ellipsoid":
                given = next((k for k in ("surface_vertices_mm", "surface_faces") if k in data[sub]), None)
                if given:
                    raise DesignError(f"bulb.{given}: not with shape = {data[sub]['shape']!r} (its triangles are "
                                      "derived from semi_axes_mm, exponents and bend_mm)")
            kwargs[sub] = dataclasses.replace(defaults[sub], **data[sub])
    if "layers" in data:
        lay = data["layers"]
        _check_keys("layers", lay, ["shell_mm", "lesions"])
        lesions = lay.get("lesions", {})
        if not isinstance(lesions, dict):
            raise DesignError(f"layers.lesions: expected a table of named lesions, got {lesions!r}")
        les = []
        for name, spec in lesions.items():
            _check_keys(f"layers.lesions.{name}", spec, ["center_mm", "semi_axes_mm"])  # the name is the table's
            les.append(LesionParams(name=str(name), **spec))
        kwargs["layers"] = LayersParams(shell_mm=lay.get("shell_mm", 0.0), lesions=tuple(les))
    kwargs["arms"] = _arms_from_dict(data, defaults["arms"], kwargs["bulb"].is_surface)
    for key in ("markers", "targets", "contacts"):
        if key in data:
            if not isinstance(data[key], dict):
                raise DesignError(f"{key}: expected a table of name = [x, y, z]")
            kwargs[key] = tuple(data[key].items())
    if "materials" in data:
        mats = data["materials"]
        if not isinstance(mats, dict):
            raise DesignError("materials: expected tables [materials.NAME] with law = ... and parameters")
        specs = []
        for name, tbl in mats.items():
            if not isinstance(tbl, dict):
                raise DesignError(f"materials.{name}: expected a table")
            if "law" not in tbl:
                raise DesignError(f"materials.{name}.law: missing (corotational, neo-hookean or yeoh)")
            specs.append(MaterialSpec(name, tbl["law"], tuple((k, v) for k, v in tbl.items() if k != "law")))
        kwargs["materials"] = tuple(specs)
    if "region_materials" in data:
        if not isinstance(data["region_materials"], dict):
            raise DesignError("region_materials: expected a table region = material name")
        kwargs["region_materials"] = tuple(data["region_materials"].items())
    if snap:
        _snap_to_surface(kwargs, data)
    return kwargs


def _snap_to_surface(kwargs: dict[str, Any], data: dict[str, Any]) -> None:
    """``snap_to_surface = true``: the file's markers, contact points and internal cavities' inlets
    moved to the closest point of the body's surface (each move logged); the saved design holds
    the moved points."""
    import logging

    bulb: BulbParams = kwargs["bulb"]
    log = logging.getLogger(__name__)

    def onto(path: str, xyz) -> Vec3:
        q = bulb.closest_surface_point([xyz])[0]
        moved = float(np.linalg.norm(q - np.asarray(xyz, float)))
        if moved > 1e-9:
            log.info("snap_to_surface: %s moved %.3g mm onto the surface, to [%s]", path, moved,
                     ", ".join(f"{x:.4f}" for x in q))
        return tuple(float(x) for x in q)  # type: ignore[return-value]

    for key, check in (("markers", lambda v: _named_points("markers", v)), ("contacts", _contact_points)):
        if key in data:
            kwargs[key] = tuple((n, onto(f"{key}.{n}", xyz)) for n, xyz in check(kwargs[key]))
    if "urethra" in data or "cavities" in data:
        kwargs["cavities"] = tuple(dataclasses.replace(c, inlet_mm=onto(f"{c.path}.inlet_mm", c.inlet_mm))
                                   for c in kwargs["cavities"])


def read_design_file(path: str | Path) -> dict[str, Any]:
    """The nested dict of a ``.toml`` or ``.json`` design file (refused: unreadable, not text, not
    valid, empty)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DesignError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise DesignError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise DesignError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'} ({exc})") from None
    if not data:  # a blank file would silently be the default design
        raise DesignError(f"{path}: empty design file (no key and no table); leave the file out for the default design")
    return data


def design_to_toml(design: BIPDesign) -> str:
    """The design as TOML text (tomli-w): one table per part, one line per scalar and per vector
    component, so a changed value is a one-line diff.

    >>> from softphantom.design.params import BIPDesign
    >>> print(design_to_toml(BIPDesign()).splitlines()[2])
    [bulb]
    """
    return tomli_w.dumps(design_to_dict(design))


def save_design(design: BIPDesign, path: str | Path) -> Path:
    """Write ``design`` as TOML (or JSON for a ``.json`` suffix); floats round-trip exactly."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(design_to_dict(design), indent=2) + "\n", encoding="utf-8")
    else:
        path.write_text(design_to_toml(design), encoding="utf-8")
    return path
