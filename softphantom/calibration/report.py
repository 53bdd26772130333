"""The calibration's files: ``parameters.csv``, ``calibration.json``, ``report.html`` with its PNGs
(objective along the iterations, residuals before/after per keyframe, per-DoF errors on fitting
and held-out data, parameter correlations)."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from softphantom.calibration.run import Calibration, HeldOut, rmse_ratio, rmse_ratio_interval


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_objective(cal: Calibration, path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.4), constrained_layout=True)
    h = np.asarray(cal.fit.history)
    ax.semilogy(np.arange(len(h)), h, "o-", color="#1f4e79")
    ax.set_xlabel("Levenberg–Marquardt iteration")
    ax.set_ylabel("objective ½‖r‖² (weighted)")
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title(f"{cal.fit.solves} forward solves, {cal.fit.seconds:.0f} s", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_errors(held: HeldOut, path: Path, title: str) -> Path:
    """Per-DoF pose error at each keyframe, nominal (open) vs calibrated (filled)."""
    plt = _plt()
    fig, axes = plt.subplots(2, 3, figsize=(12, 5.6), sharex=True, constrained_layout=True)
    order = np.argsort(held.t)
    for k, ax in enumerate(axes.flat):
        ax.plot(held.t[order], held.err_nominal[order, k], "o", mfc="none", color="#c0392b", label="nominal model")
        ax.plot(held.t[order], held.err_calibrated[order, k], "o", color="#1f4e79", label="calibrated model")
        ax.axhline(0, color="k", lw=0.6)
        rn, rc = held.rmse("nominal")[k], held.rmse("calibrated")[k]
        ax.set_title(f"{held.names[k]}: RMSE {rn:.3g} → {rc:.3g}", fontsize=10)
        ax.grid(True, alpha=0.3)
        if k >= 3:
            ax.set_xlabel("keyframe time (s)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_correlation(cal: Calibration, path: Path) -> Path:
    plt = _plt()
    f = cal.fit
    idx = np.flatnonzero(f.free)
    C = f.correlation[np.ix_(idx, idx)]
    fig, ax = plt.subplots(figsize=(8, 7), constrained_layout=True)
    im = ax.imshow(C, vmin=-1, vmax=1, cmap="RdBu_r")
    names = [f.names[i] for i in idx]
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    fig.colorbar(im, ax=ax, shrink=0.8, label="correlation")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def parameter_rows(cal: Calibration) -> list[dict]:
    f = cal.fit
    rows = []
    for i, n in enumerate(f.names):
        rows.append(dict(parameter=n, nominal=float(f.nominal[i]), value=float(f.value[i]),
                         ci95_low=float(f.ci95[i, 0]), ci95_high=float(f.ci95[i, 1]),
                         fitted=bool(f.free[i]), identifiable=bool(f.identifiable[i]),
                         spread_vs_prior=float(f.sd[i] / f.prior_sd[i])))
    return rows


def write_parameters_csv(cal: Calibration, path: Path) -> Path:
    rows = parameter_rows(cal)
    keys = list(rows[0])
    lines = [",".join(keys)] + [",".join(f"{r[k]:.6g}" if isinstance(r[k], float) else str(r[k]) for k in keys)
                                for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _table(headers, rows) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in headers)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>"


def _rmse_table(held: HeldOut) -> str:
    rn, rc = held.rmse("nominal"), held.rmse("calibrated")
    rows = [[n, f"{a:.3f}", f"{b:.3f}", f"{a / b:.2f}×" if b > 0 else "–"] for n, a, b in zip(held.names, rn, rc)]
    fn, fc = held.force_rmse("nominal"), held.force_rmse("calibrated")
    if np.isfinite(fn):
        rows.append(["force_N (known loads)", f"{fn:.3f}", f"{fc:.3f}", f"{fn / fc:.2f}×" if fc > 0 else "–"])
    return _table(["DoF", "RMSE nominal", "RMSE calibrated", "ratio"], rows)


def _ratio_spread(held: HeldOut) -> str:
    lo, hi = rmse_ratio_interval(held)
    k = int(np.sum(np.isfinite(held.err_calibrated).any(axis=1)))
    return f"{lo:.2f}–{hi:.2f} over the {k} keyframes resampled, 90 %"


def _law_line(cal: Calibration) -> str:
    law = cal.meta.get("law") or {}
    if not law or law.get("design") == law.get("fitted"):
        return ""
    return html.escape(f"Fitted under the {', '.join(law['fitted'])} law; the design's (the nominal model's) is "
                       f"{', '.join(law['design'])}. ")


def _cavities_line(cal: Calibration) -> str:
    """The internal cavities whose recorded pressures loaded the keyframe solves, with the largest."""
    fr = cal.frames
    if not fr.cavity_names:
        return "No internal cavity. "
    peak = np.max(np.abs(fr.cavity_pressures_Pa), axis=0) / 1e3 if len(fr) else np.zeros(len(fr.cavity_names))
    return html.escape("Internal cavity pressures in the keyframe solves (largest): "
                       + ", ".join(f"{n} {p:.3g} kPa" for n, p in zip(fr.cavity_names, peak)) + ". ")


def write_report(cal: Calibration, out: Path) -> Path:
    """``report.html`` and its figures in ``out``."""
    fig = out / "figures"
    fig.mkdir(parents=True, exist_ok=True)
    plot_objective(cal, fig / "objective.png")
    plot_errors(cal.fitting, fig / "errors_fitting.png", "fitting data: pose error (forces from the pressures alone)")
    if cal.held_out is not None:
        plot_errors(cal.held_out, fig / "errors_held_out.png", "held-out data: pose error (forces from the pressures alone)")
    plot_correlation(cal, fig / "correlation.png")
    prow = [[r["parameter"], f"{r['nominal']:.4g}", f"{r['value']:.4g}",
             f"[{r['ci95_low']:.4g}, {r['ci95_high']:.4g}]" if r["fitted"] else "fixed",
             ("yes" if r["identifiable"] else "NO") if r["fitted"] else "–", f"{r['spread_vs_prior']:.0%}"]
            for r in parameter_rows(cal)]
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in cal.fit.warnings) or "<li>none</li>"
    held = ""
    if cal.held_out is not None:
        held = (f"<h2>Held-out data ({html.escape(', '.join(cal.meta.get('held_out', [])))})</h2>"
                f"<p>Pose RMSE ratio nominal/calibrated: <b>{rmse_ratio(cal.held_out):.2f}</b> "
                f"({_ratio_spread(cal.held_out)})</p>"
                + _rmse_table(cal.held_out) + '<img src="figures/errors_held_out.png" width="100%">')
    body = f"""<!doctype html><html><head><meta charset="utf-8"><title>softphantom calibration</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #bbb;padding:3px 8px;text-align:right}}th{{background:#eee}}</style></head><body>
<h1>Calibration of {html.escape(str(cal.model_dir))}</h1>
<p>{_law_line(cal)}{len(cal.sessions)} session(s), {len(cal.frames)} keyframes; {_cavities_line(cal)}{cal.fit.solves} forward solves in
{cal.fit.seconds:.0f} s; objective {cal.fit.history[0]:.4g} → {cal.fit.history[-1]:.4g}.</p>
<h2>Parameters</h2>{_table(["parameter", "nominal", "calibrated", "95 % interval", "identifiable", "spread / prior"], prow)}
<h2>Warnings</h2><ul>{warn}</ul>
<h2>Objective</h2><img src="figures/objective.png">
<h2>Fitting data</h2>{_rmse_table(cal.fitting)}<img src="figures/errors_fitting.png" width="100%">
{held}
<h2>Correlations</h2><img src="figures/correlation.png" width="70%">
</body></html>"""
    path = out / "report.html"
    path.write_text(body)
    return path


def shape_dict(cal: Calibration) -> dict:
    """``{"<law>_shape": {group: {ratio: value}}}`` of the ratios fitted (e.g. ``yeoh_shape``)."""
    from softphantom.calibration.fit import fitted_ratios

    out: dict = {}
    for g, (law, values) in fitted_ratios(cal.parameters()).items():
        out.setdefault(f"{law.name.replace('-', '_')}_shape", {})[g] = {r.name: v for r, v in zip(law.ratios, values)}
    return out


def calibration_dict(cal: Calibration) -> dict:
    """The calibrated sensor and registration parameters (``calibration.json``)."""
    from softphantom import __version__
    from softphantom.calibration.fit import gain_arms

    p = cal.parameters()
    arms = list(gain_arms(p))  # the model's arms, in the sensor order
    out = {
        "softphantom": __version__,
        "kind": "softphantom-calibration",
        "law": cal.meta.get("law", {}),
        "stiffness_factor": {g: p[f"stiffness_{g}_factor"] for g in ("bulb", "arms")},
        "internal_cavities": list(cal.frames.cavity_names),  # their recorded pressures loaded the solves
        **shape_dict(cal),
        "sensor": {"arms": arms, "gain": [p[f"gain_{a}"] for a in arms],
                   "offset_Pa": [p[f"offset_{a}_Pa"] for a in arms],
                   "tube_volume_factor": p["tube_volume_factor"],
                   **({"tube_tau_ms": cal.meta["tube_tau"]["tau_ms"], "tube_tau_sd_ms": cal.meta["tube_tau"]["sd_ms"]}
                      if "tube_tau" in cal.meta else {})},
        "registration": {"rotation_deg": [p[f"registration_rot_{a}_deg"] for a in "xyz"],
                         "pivot_mm": [p[f"pivot_{a}_mm"] for a in "xyz"]},
        "lag_ms": {n[4:-3]: v for n, v in p.items() if n.startswith("lag_")},
        "drift_Pa_per_s": {n[6:-9]: v for n, v in p.items() if n.startswith("drift_")},
        "contact_radius_mm": cal.options.radius_m * 1e3,
        "sessions": cal.meta.get("sessions", []),
        "held_out": cal.meta.get("held_out", []),
        "warnings": list(cal.fit.warnings),
        "parameters": parameter_rows(cal),
    }
    if cal.held_out is not None:
        out["held_out_rmse_ratio"] = rmse_ratio(cal.held_out)
        out["held_out_rmse_ratio_90"] = list(rmse_ratio_interval(cal.held_out))
    return json.loads(json.dumps(out))
