"""Writing a calibration: a new model directory (the calibrated model, readable by ``estimate``,
``live`` and ``demo`` like any other) with ``calibration.json``, ``parameters.csv`` and
``report.html``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from softphantom.calibration.report import calibration_dict, write_parameters_csv, write_report
from softphantom.calibration.run import Calibration
from softphantom.errors import UserError


def calibrated_design(design, factors: dict[str, float], shapes: dict[str, tuple] | None = None):
    """A new design whose regions in each group of ``factors`` (``bulb``, ``arms``) use a copy of
    their material with every modulus (fields in kPa) multiplied by the group's factor, and for a
    group in ``shapes`` (group -> (law class, its ratios), :func:`~softphantom.calibration.fit.fitted_ratios`)
    under that law, the ratios' moduli set (Yeoh: C20 = θ2·C10, C30 = θ3·C10); ν and the
    density stay. The copies are named ``<material>_<group>_calibrated``."""
    from softphantom.calibration.forward import region_group
    from softphantom.design.params import MaterialSpec
    from softphantom.fem.laws.base import design_key

    by_region = design.material_of_regions()
    specs = {m.name: m for m in design.materials}
    new_specs = list(design.materials)
    assign = dict(design.region_materials)
    for group, c in factors.items():
        for region, mname in by_region.items():
            if region_group(region) != group:
                continue
            new = f"{mname}_{group}_calibrated"
            if new not in {m.name for m in new_specs}:
                spec = specs[mname]
                vals = dict((k, v * c if k.endswith("_kPa") else v) for k, v in spec.values)
                if group in (shapes or {}) and shapes[group][0].name == spec.law:
                    for r, v in zip(shapes[group][0].ratios, shapes[group][1]):
                        vals[design_key(r.field)] = v * vals[design_key(r.of)]
                new_specs.append(MaterialSpec(new, spec.law, tuple(vals.items())))
            assign[region] = new
    used = set(assign.values())
    return dataclasses.replace(design, materials=tuple(m for m in new_specs if m.name in used),
                               region_materials=tuple(assign.items()))


def calibrated_model(cal: Calibration):
    """The model of ``cal.model_dir`` with the fitted stiffness applied to its design (the mesh is
    the same: only the materials change), under the law it was fitted with (``--law``)."""
    from softphantom.design import load_model

    from softphantom.calibration.fit import fitted_ratios
    from softphantom.calibration.forward import design_with_law
    from softphantom.design import SensorParams

    model = load_model(cal.model_dir)
    p = cal.parameters()
    factors = {g: p[f"stiffness_{g}_factor"] for g in ("bulb", "arms")}
    shapes = fitted_ratios(p)
    design = calibrated_design(design_with_law(model.design, cal.options.law), factors, shapes)
    # the fitted gains and tube factor are relative to the chain the (first) recording used
    s0 = cal.sessions[0]
    sensors = SensorParams(tuple(float(g0 * p[f"gain_{a}"]) for g0, a in zip(s0.recorded_gains, model.design.sensing_names)),
                           float(s0.recorded_tube_factor * p["tube_volume_factor"]),
                           tuple(getattr(cal, "meta", {}).get("tube_tau", {}).get("tau_ms", ())))
    return dataclasses.replace(model, design=dataclasses.replace(design, sensors=sensors))


def write_calibration(cal: Calibration, out, shown=None) -> dict[str, Path]:
    """Write the calibrated model, ``calibration.json``, ``parameters.csv`` and ``report.html``
    into the directory ``out`` (created; refused if it holds anything). The CLI writes through a
    staged sibling (``softphantom.cli.options.staged_output``), so ``--out`` is never half-written;
    ``shown`` is where the directory ends up, for the messages (default ``out``)."""
    from softphantom.design import save_model

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"--out {out}: exists and is not an empty directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
        model = calibrated_model(cal)
        save_model(model, out)
        p = cal.parameters()
        factors = {g: p[f"stiffness_{g}_factor"] for g in ("bulb", "arms")}
        atlas_note = carry_atlases(cal.model_dir, model, out, factors, cal.options.law is not None, shown=shown)
        (out / "calibration.json").write_text(json.dumps({**calibration_dict(cal), "atlas": atlas_note},
                                                         indent=2) + "\n")
        write_parameters_csv(cal, out / "parameters.csv")
        write_report(cal, out)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot write ({exc.strerror or exc})") from None
    return {"model": out, "report": out / "report.html", "parameters": out / "parameters.csv",
            "calibration": out / "calibration.json", "atlas": atlas_note}


def carry_atlases(base_dir, model, out, factors: dict[str, float], law_changed: bool,
                  rtol: float = 1e-9, shown=None) -> str:
    """The calibrated model's atlas, where it follows from the uncalibrated one's: with every
    stiffness scaled by one factor ``s`` under the same law, each atlas of ``base_dir`` (verified
    against the uncalibrated model) is that model's exactly with the loads scaled by ``s``
    (:meth:`~softphantom.estimation.atlas.map.Atlas.scaled`): written to ``out/atlas/`` with the
    factor (``load_scale.json``, so the estimators ask for the scaled envelope). The atlases the
    package ships for the uncalibrated mesh count as its own. Otherwise nothing is written.
    Returns one line for the user: what was carried over, or the build the model needs and its
    estimated time."""
    from softphantom.design import load_model
    from softphantom.estimation.atlas.build import draft_points, duration_text, estimate_build
    from softphantom.estimation.atlas.config import LOAD_SCALE_FILE, model_atlas_config
    from softphantom.estimation.atlas.catalogue import atlas_key, atlases_of, verify_atlas
    from softphantom.estimation.atlas.store import atlas_path, estimator_config, save_atlas

    out = Path(out)
    vals = list(factors.values())
    s = vals[0]
    uniform = not law_changed and all(abs(v - s) <= rtol * abs(s) for v in vals)
    base = load_model(base_dir) if uniform else None  # only a uniform scale carries atlases over
    files = atlases_of(base_dir, base) if uniform else []
    carried = 0
    if files:
        from softphantom.fem.model import fem_from_phantom

        fem = fem_from_phantom(base)
        for f in files:
            try:
                at = verify_atlas(f, base, fem).atlas
            except UserError:
                continue  # a stale or damaged file of the old model: not carried
            scaled = at.scaled(s, atlas_key(model, estimator_config(at, f), at.config.scaled(s)))
            save_atlas(scaled, atlas_path(out, scaled.key))
            carried += 1
    if carried:
        (out / "atlas" / LOAD_SCALE_FILE).write_text(json.dumps({"factor": s, "from_model": str(base_dir)}) + "\n")
        return (f"{carried} atlas file(s) of {base_dir} carried over with the loads scaled by {s:.4g} (a uniform "
                f"stiffness scale: exact); nothing to build")
    why = ("the law changed" if law_changed else
           "no atlas of the uncalibrated model to scale" if uniform else
           "the stiffness changed unevenly (" + ", ".join(f"{g} x{v:.4g}" for g, v in factors.items()) + ")")
    order, nodes = model.element_order, len(model.nodes)
    full = estimate_build(order, nodes, model_atlas_config(order, out))
    draft = estimate_build(order, nodes, model_atlas_config(order, out, draft=True))
    return (f"the calibrated model needs its own atlas ({why}): softphantom atlas build --model {shown or out} "
            f"(about {duration_text(full.wall_s)} on this machine's {full.workers} cores, ≈ {full.cpu_s:.0f} CPU-s, "
            f"{duration_text(full.critical_path_s)} on a cluster of {full.tasks} workers; resumable), or --draft "
            f"({draft_points(order)} points, its error measured: about {duration_text(draft.wall_s)})")
