"""PNG view of a :class:`~softphantom.design.model.PhantomModel` (matplotlib, headless Agg).

Left: the whole phantom, outer surface translucent and coloured by region, the cavities solid,
with markers, targets and p_ext. Right: a crinkle cut (the tets with centroid at x ≤ 0, seen from
+x), which shows the mesh inside and the cavities in section. Colours and legend are the model's
own regions and cavities (:func:`model_colours`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

REGION_COLOURS = {
    "bulb": "#f2b8a2",
    "arm_front_zpos": "#4c78a8",
    "arm_front_zneg": "#f58518",
    "arm_back_xpos": "#54a24b",
    "arm_back_xneg": "#e45756",
}
CAVITY_COLOURS = {
    "front_zpos": "#1f4e79",
    "front_zneg": "#b35900",
    "back_xpos": "#2d6a27",
    "back_xneg": "#9e1b1b",
    "urethra": "#7b3fa0",
}


#: colours of the other regions and cavities, in the model's order (matplotlib's tab10 and its darker tab20 pair)
_ARM_PALETTE = ("#4c78a8", "#f58518", "#54a24b", "#e45756", "#72b7b2", "#eeca3b", "#b279a2", "#9d755d", "#bab0ac")
_CAVITY_PALETTE = ("#7b3fa0", "#17becf", "#8c564b", "#bcbd22", "#e377c2", "#393b79")
_LAYER_COLOURS = {"shell": "#d9a08b"}


def _darker(colour: str, f: float = 0.6) -> str:
    from matplotlib.colors import to_hex, to_rgb

    return to_hex(tuple(f * c for c in to_rgb(colour)))


def model_colours(model) -> tuple[dict[str, str], dict[str, str]]:
    """(region → colour, cavity → colour) for ``model``'s own regions and cavities: the BIP's
    colours for the BIP's names; another design's arms in palette order, each arm's cavity a darker
    shade of its arm, its internal cavities from a second palette.

    >>> import types
    >>> m = types.SimpleNamespace(regions={"bulb": 1, "arm_upper_pole": 2}, cavities={"upper_pole": 0, "balloon": 0})
    >>> model_colours(m)
    ({'bulb': '#f2b8a2', 'arm_upper_pole': '#4c78a8'}, {'upper_pole': '#2e4865', 'balloon': '#7b3fa0'})
    """
    regions: dict[str, str] = {}
    arms = [r for r in model.regions if r.startswith("arm_")]
    spare = [c for c in _ARM_PALETTE if c not in {REGION_COLOURS.get(a) for a in arms}]
    for r in model.regions:
        if r in REGION_COLOURS:
            regions[r] = REGION_COLOURS[r]
        elif r in _LAYER_COLOURS:
            regions[r] = _LAYER_COLOURS[r]
        elif r.startswith("lesion_"):
            regions[r] = "#c44e52"
        else:
            regions[r] = spare.pop(0) if spare else "#bbbbbb"
    cavities: dict[str, str] = {}
    internal = iter(_CAVITY_PALETTE)
    for c in model.cavities:
        if c in CAVITY_COLOURS:
            cavities[c] = CAVITY_COLOURS[c]
        elif f"arm_{c}" in regions:
            cavities[c] = _darker(regions[f"arm_{c}"])
        else:
            cavities[c] = next(internal, "#555555")
    return regions, cavities


def _boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces of ``tets`` that belong to one tet only, oriented outward, and that tet's index."""
    faces = np.vstack([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    owner = np.tile(np.arange(len(tets)), 4)
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    return faces[once], owner[once]


def _face_colours(model, owner: np.ndarray) -> list[str]:
    colours = model_colours(model)[0]
    by_id = {v: colours[k] for k, v in model.regions.items()}
    return [by_id[int(r)] for r in model.tet_region[owner]]


def _points(ax, model, scale: float) -> None:
    for name, p in model.markers.items():
        ax.scatter(*(p * scale), color="black", s=28, marker="o", depthshade=False)
        ax.text(*(p * scale), f" {name}", fontsize=7)
    for name, p in model.targets.items():
        ax.scatter(*(p * scale), color="#d62728", s=30, marker="x", depthshade=False)
    for name, p in model.p_ext.items():
        ax.scatter(*(p * scale), color="#ffbf00", edgecolor="black", s=90, marker="*", depthshade=False)
        ax.text(*(p * scale), f" {name}", fontsize=7, color="#8a6d00")


def _square(ax, nodes_mm: np.ndarray) -> None:
    lo, hi = nodes_mm.min(axis=0), nodes_mm.max(axis=0)
    c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")


def render_mesh_png(model, path: str | Path, *, title: str | None = None, dpi: int = 110) -> Path:
    """Write the two-panel PNG of ``model`` to ``path`` and return the path."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    scale = 1e3  # m -> mm at the edge
    x = model.nodes * scale
    fig = plt.figure(figsize=(13, 6.5))

    ax = fig.add_subplot(1, 2, 1, projection="3d")
    outer = np.vstack([model.outer_faces, model.fixed_faces])
    _, owner = _owner_of(model, outer)
    ax.add_collection3d(
        Poly3DCollection(x[outer], facecolors=_face_colours(model, owner), edgecolors="none", alpha=0.18)
    )
    region_colours, cavity_colours = model_colours(model)
    for name, tris in model.cavities.items():
        ax.add_collection3d(Poly3DCollection(x[tris], facecolors=cavity_colours[name], edgecolors="none", alpha=0.9))
    _points(ax, model, scale)
    _square(ax, x)
    ax.view_init(elev=22, azim=-60)
    ax.set_title("whole phantom (outer surface translucent, cavities solid)", fontsize=10)

    ax2 = fig.add_subplot(1, 2, 2, projection="3d")
    centroids = x[model.tets].mean(axis=1)
    keep = np.flatnonzero(centroids[:, 0] <= 0.0)
    faces, own = _boundary_faces(model.tets[keep])
    ax2.add_collection3d(
        Poly3DCollection(
            x[faces], facecolors=_face_colours(model, keep[own]), edgecolors=(0, 0, 0, 0.35), linewidths=0.15
        )
    )
    _square(ax2, x)
    ax2.view_init(elev=10, azim=0)
    ax2.set_title("cut at x = 0 (tets with x ≤ 0, seen from +x): mesh and cavities", fontsize=10)

    handles = [Line2D([], [], color=c, lw=6, label=k) for k, c in region_colours.items()]
    handles += [Line2D([], [], color=c, lw=6, label=f"cavity {k}") for k, c in cavity_colours.items()]
    handles += [
        Line2D([], [], color="black", marker="o", lw=0, label="markers"),
        Line2D([], [], color="#d62728", marker="x", lw=0, label="targets"),
        Line2D([], [], color="#ffbf00", markeredgecolor="black", marker="*", markersize=11, lw=0, label="p_ext"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=7, fontsize=8, frameon=False)
    n_nodes, n_tets = len(model.nodes), len(model.tets)
    fig.suptitle(title or f"{model.design.name}: {n_nodes} nodes, {n_tets} tets", fontsize=12)
    fig.subplots_adjust(left=0.0, right=1.0, top=0.92, bottom=0.1, wspace=0.0)
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _owner_of(model, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tet owning each boundary triangle (for its region colour)."""
    faces, owner = _boundary_faces(model.tets)
    n = len(model.nodes)

    def enc(f):
        s = np.sort(f, axis=1).astype(np.int64)
        return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]

    ef, et = enc(faces), enc(tris)
    order = np.argsort(ef)
    idx = np.clip(np.searchsorted(ef[order], et), 0, len(order) - 1)
    return tris, owner[order[idx]]
