"""The HTML report of a study: Pareto front of force resolution against range, sensitivity of
each output to each parameter (Spearman rank correlation), the best and the failed variants.
PNGs (matplotlib) are embedded, so the report is one self-contained file."""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

#: Outputs shown in the sensitivity map (lower is better except range and obs_sv_min_mm3).
OUTPUTS = ("res_force_worst_N", "range_min_N", "cond_W", "cond_W_loaded_max", "obs_sv_min_mm3", "res_target_worst_mm",
           "res_yaw_deg", "res_pitch_deg", "silicone_mL", "mesh_min_dihedral_deg", "total_s")


def pareto_front(res: np.ndarray, rng: np.ndarray) -> np.ndarray:
    """Indices of the non-dominated points (lower ``res``, higher ``rng`` is better), by ``res``.

    >>> pareto_front(np.array([1.0, 2.0, 0.5, 3.0]), np.array([5.0, 6.0, 1.0, 4.0])).tolist()
    [2, 0, 1]
    """
    order = np.lexsort((-rng, res))
    front, best = [], -math.inf
    for i in order:
        if rng[i] > best:
            front.append(int(i))
            best = rng[i]
    return np.array(front, dtype=int)


def _numeric(rows: Sequence[dict], col: str) -> np.ndarray:
    out = []
    for r in rows:
        v = r.get(col)
        out.append(float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None else np.nan)
    return np.array(out)


def sensitivity(rows: Sequence[dict], params: Sequence[str], outputs: Sequence[str]) -> np.ndarray:
    """(outputs, params) Spearman rank correlation over the ok variants (NaN where undefined)."""
    from scipy.stats import spearmanr

    ok = [r for r in rows if r.get("status") == "ok"]
    S = np.full((len(outputs), len(params)), np.nan)
    for j, p in enumerate(params):
        x = _numeric(ok, p)
        for i, o in enumerate(outputs):
            y = _numeric(ok, o)
            m = np.isfinite(x) & np.isfinite(y)
            if m.sum() >= 3 and np.ptp(x[m]) > 0 and np.ptp(y[m]) > 0:
                S[i, j] = spearmanr(x[m], y[m]).statistic
    return S


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def write_report(rows: Sequence[dict], path: Path, title: str, note: str = "") -> Path:
    """Write the report of ``rows`` (as in results.parquet) to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.get("status") == "ok"]
    params = [c for c in dict.fromkeys(k for r in rows for k in r) if c.startswith("p.")]
    num_params = [p for p in params if np.isfinite(_numeric(ok, p)).any()]
    parts = [f"<h1>{html.escape(title)}</h1>",
             f"<p>{len(rows)} variants: {len(ok)} ok, {len(rows) - len(ok)} invalid or failed. {html.escape(note)}</p>"]

    if ok:
        res, rng = _numeric(ok, "res_force_worst_N"), _numeric(ok, "range_min_N")
        m = np.isfinite(res) & np.isfinite(rng)
        idx = np.flatnonzero(m)
        front = idx[pareto_front(res[m], rng[m])] if m.any() else np.array([], int)
        fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
        ax.scatter(rng[m], res[m], s=18, c="0.6", label="variants")
        ax.plot(rng[front], res[front], "C3o-", label="Pareto front")
        for i in front:
            ax.annotate(str(ok[i]["variant"]), (rng[i], res[i]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel("range: smallest force that saturates a transducer (N)")
        ax.set_ylabel("worst-axis force resolution (N per count)")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        parts.append("<h2>Resolution against range</h2>")
        parts.append(f'<img src="data:image/png;base64,{_png(fig)}">')
        parts.append("<p>Lower is finer, right is more range; the red line, the Pareto front, joins the variants no other beats on both (listed below).</p>")
        cols = ["variant", *params, "res_force_worst_N", "range_min_N", "cond_W", "obs_sv_min_mm3", "res_target_worst_mm"]
        parts.append(_table([ok[i] for i in front], cols))

        if num_params:
            outs = [o for o in OUTPUTS if np.isfinite(_numeric(ok, o)).any()]
            S = sensitivity(rows, num_params, outs)
            fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(num_params), 0.9 + 0.45 * len(outs)),
                                   constrained_layout=True)
            im = ax.imshow(S, cmap="coolwarm", vmin=-1, vmax=1, aspect="auto")
            ax.set_xticks(range(len(num_params)), [p[2:] for p in num_params], rotation=30, ha="right", fontsize=8)
            ax.set_yticks(range(len(outs)), outs, fontsize=8)
            for i in range(len(outs)):
                for j in range(len(num_params)):
                    if np.isfinite(S[i, j]):
                        ax.text(j, i, f"{S[i, j]:+.2f}", ha="center", va="center", fontsize=7)
            fig.colorbar(im, ax=ax, label="Spearman rank correlation")
            parts.append("<h2>Sensitivity of each output to each parameter</h2>")
            parts.append(f'<img src="data:image/png;base64,{_png(fig)}">')
            parts.append("<p>+1: the output grows with the parameter in every variant (monotone); 0: no "
                         "monotone relation over this sample; blank: the parameter or output did not vary.</p>")
            n = len(num_params)
            fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.0), constrained_layout=True, squeeze=False)
            for ax, p in zip(axes[0], num_params):
                ax.scatter(_numeric(ok, p), res, s=12)
                ax.set_xlabel(p[2:], fontsize=8)
                ax.set_yscale("log")
                ax.grid(True, alpha=0.3)
            axes[0][0].set_ylabel("worst-axis force resolution (N/count)")
            parts.append(f'<img src="data:image/png;base64,{_png(fig)}">')

    bad = [r for r in rows if r.get("status") != "ok"]
    if bad:
        parts.append("<h2>Invalid or failed variants</h2>")
        parts.append(_table(bad, ["variant", *params, "status", "error"]))
    body = "\n".join(parts)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
                    "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
                    "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px}"
                    f"</style></head><body>{body}</body></html>\n", encoding="utf-8")
    tmp.replace(path)  # a report is whole or absent
    return path


def _table(rows: Sequence[dict], cols: Sequence[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"
