"""``softphantom simulate``: one static FEM solve of a phantom model under a force and a urethra
pressure; writes the deformed mesh (.vtu) and prints cavity volume changes, marker pose, target shifts."""

from __future__ import annotations

import json
import time

import numpy as np
import typer

from softphantom.cli.app import app, console
from softphantom.cli.options import At, ModelDir, Out, Overwrite, check_output, staged_output
from softphantom.errors import SolverError, UserError
from softphantom.fem.contact import DEFAULT_CONTACT_RADIUS_M
from softphantom.records.names import POSE_COLUMNS


#: Loads beyond these are no phantom's (a silicone gland a few cm across): refused before any work.
MAX_FORCE_N = 1000.0
MAX_PRESSURE_KPA = 1000.0


def _vec3(text: str, what: str) -> np.ndarray:
    try:
        v = np.array([float(t) for t in text.split(",")], dtype=np.float64)
    except ValueError:
        raise UserError(f"{what}: expected three comma-separated numbers, got {text!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise UserError(f"{what}: expected three finite comma-separated numbers, got {text!r}")
    return v


def _pressures(items: list[str], cavities, urethra_given: bool, measured=()) -> dict[str, float]:
    """``CAVITY=KPA`` options → {cavity: Pa}, each cavity one of the design's actuated ``cavities``
    (not one of its ``measured`` ones: a sealed cavity read as a volume is never loaded), once."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            p = float(value) if sep else float("nan")
        except ValueError:
            p = float("nan")
        if not np.isfinite(p):
            raise UserError(f"--pressure-kPa: expected CAVITY=KPA (e.g. tumour=20), got {item!r}")
        if name in measured:
            raise UserError(f"--pressure-kPa {name}: a measured cavity (role = \"measured\": read as a volume, "
                            f"never loaded); the actuated ones: {', '.join(cavities) or 'none'}")
        if name not in cavities:
            raise UserError(f"--pressure-kPa {name}: not an internal cavity of this model "
                            f"({', '.join(cavities) or 'it has none'})")
        if name in out or (name == "urethra" and urethra_given):
            raise UserError(f"--pressure-kPa {name}: given twice")
        if abs(p) > MAX_PRESSURE_KPA:
            raise UserError(f"--pressure-kPa {name}: must be within ±{MAX_PRESSURE_KPA:g} kPa, got {p:g}")
        out[name] = p * 1e3
    return out


@app.command("simulate")
def simulate_command(
    model_dir: ModelDir = ...,
    force_N: str = typer.Option("0,0,0", "--force-N", help="Force FX,FY,FZ in N (model frame)."),
    at: At = "on-centre",
    patch_radius_mm: float = typer.Option(
        DEFAULT_CONTACT_RADIUS_M * 1e3, "--patch-radius-mm",
        help="Contact patch radius in mm: a uniform traction on the outer surface within it (0: point force)."
    ),
    urethra_kPa: float = typer.Option(0.0, "--urethra-kPa", help="Urethra cavity gauge pressure in kPa."),
    pressure_kPa: list[str] = typer.Option(None, "--pressure-kPa", help="An internal cavity's gauge pressure, "
                                           "CAVITY=KPA (repeat; e.g. tumour=20; the urethra's is --urethra-kPa)."),
    gravity: bool = typer.Option(False, "--gravity/--no-gravity", help="Include gravity (−z)."),
    out: Out = ...,
    overwrite: Overwrite = False,
) -> None:
    """Solve the FEM statically (the design's laws and element order); write deformed.vtu and result.json
    into the new directory --out, print the results. --at also takes a point X,Y,Z in mm."""
    from softphantom.design import load_model
    from softphantom.fem import (
        cavity_volume,
        fem_from_phantom,
        force_actuator,
        probe_matrix,
        solve_static,
    )
    from softphantom.fem.io import write_deformed_vtu
    from softphantom.pose import pose_of_markers

    check_output(out, overwrite=overwrite, directory=True)
    force = _vec3(force_N, "--force-N")
    if np.abs(force).max() > MAX_FORCE_N:
        raise UserError(f"--force-N: each component must be within ±{MAX_FORCE_N:g} N, got {force_N!r}")
    if abs(urethra_kPa) > MAX_PRESSURE_KPA:
        raise UserError(f"--urethra-kPa: must be within ±{MAX_PRESSURE_KPA:g} kPa, got {urethra_kPa:g}")
    if patch_radius_mm < 0:
        raise UserError(f"--patch-radius-mm must be >= 0, got {patch_radius_mm}")
    model = load_model(model_dir)
    if "," in at:
        point = _vec3(at, "--at") * 1e-3
    else:
        from softphantom.design.params import check_contact

        point = np.asarray(model.p_ext[check_contact(at, list(model.p_ext), "--at", hint="or X,Y,Z in mm")])
    t0 = time.perf_counter()
    fem = fem_from_phantom(model)
    f_ext = force_actuator(fem, point, radius=patch_radius_mm * 1e-3) @ force
    pressures = {"urethra": urethra_kPa * 1e3} if urethra_kPa else {}
    pressures.update(_pressures(pressure_kPa or [], model.design.pressure_names, "urethra" in pressures,
                                model.design.measured_cavity_names))
    with console.status(f"solving ({fem.n_free} DOF) …"):
        sol = solve_static(fem, f_ext, pressures=pressures or None, gravity=gravity)
    if not sol.converged:
        raise SolverError(f"static solve did not converge: {sol.status}")

    # the FEM's own cavities: 6-node (curved) triangles on a P2 model, not the model's 3-node ones
    names = list(fem.cavities)
    dV_mm3 = {k: (cavity_volume(sol.x, fem.cavities[k]) - cavity_volume(fem.nodes, fem.cavities[k])) * 1e9
              for k in names}
    rest_markers = np.array(list(model.markers.values()))
    pose = pose_of_markers(rest_markers, probe_matrix(fem, rest_markers) @ sol.x)
    targets = list(model.targets)
    rest_t = np.array([model.targets[k] for k in targets])
    shift_mm = (probe_matrix(fem, rest_t) @ sol.x - rest_t) * 1e3

    pose_cols = dict(zip(POSE_COLUMNS, pose.to_mm_deg().tolist()))
    result = {
        "force_N": force.tolist(),
        "at_mm": (point * 1e3).tolist(),
        "patch_radius_mm": patch_radius_mm,
        "urethra_kPa": urethra_kPa,
        **({"pressures_kPa": {k: v * 1e-3 for k, v in pressures.items()}} if pressure_kPa else {}),
        "gravity": gravity,
        "newton_iterations": sol.iterations,
        "load_steps": sol.load_steps,
        "relative_residual": sol.residual_norm,
        "dV_mm3": dV_mm3,
        "pose": pose_cols,
        "target_shift_mm": {k: s.tolist() for k, s in zip(targets, shift_mm)},
        "max_displacement_mm": float(np.linalg.norm(sol.u, axis=1).max() * 1e3),
    }
    try:
        text = json.dumps(result, indent=2, allow_nan=False)
    except ValueError:
        raise SolverError("the solve returned non-finite values (NaN or inf); nothing written") from None
    with staged_output(out, overwrite=overwrite, directory=True) as work:
        write_deformed_vtu(work / "deformed.vtu", fem, sol.x, model.tet_region)
        (work / "result.json").write_text(text, encoding="utf-8")

    console.print(
        f"converged: {sol.iterations} Newton iterations, {sol.load_steps} load step(s), "
        f"relative residual {sol.residual_norm:.1e}, {time.perf_counter() - t0:.1f} s",
        highlight=False,
    )
    console.print("cavity volume change (mm³): " + ", ".join(f"dV_{k}_mm3={dV_mm3[k]:+.3f}" for k in names),
                  highlight=False)
    console.print("marker pose: " + ", ".join(f"{k}={v:+.3f}" for k, v in pose_cols.items()), highlight=False)
    for k, s in zip(targets, shift_mm):
        console.print(f"target {k}: dx_mm={s[0]:+.3f}, dy_mm={s[1]:+.3f}, dz_mm={s[2]:+.3f}", highlight=False)
    console.print(f"wrote {out}/deformed.vtu, {out}/result.json", highlight=False)
