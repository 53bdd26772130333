"""PNG drawing of the molds and the assembled phantom (matplotlib, headless Agg).

Left: the phantom as assembled in the model frame (cast bulb and arms in its frame). Right: an
exploded view of the bulb mold (halves pulled apart along z, with the cavities' cores and marker
sockets in place) and of each arm mold. Triangles are decimated to keep the file small.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softphantom.viz.mesh_view import _square

_COLOURS = {"mold": "#9ecae1", "core": "#7b3fa0", "insert": "#222222", "frame": "#bdbdbd", "cast": "#f2b8a2"}
_MAX_FACES = 4000


def _draw(ax, mesh, colour: str, offset=(0.0, 0.0, 0.0), alpha: float = 0.5) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    faces = np.asarray(mesh.faces)
    step = max(1, len(faces) // _MAX_FACES)
    tri = np.asarray(mesh.vertices)[faces[::step]] + np.asarray(offset)
    ax.add_collection3d(Poly3DCollection(tri, facecolor=colour, edgecolor="none", alpha=alpha))


def _limits(ax, pts: np.ndarray) -> None:
    _square(ax, pts)
    ax.set_xlabel("x mm")
    ax.set_ylabel("y mm")
    ax.set_zlabel("z mm")


def render_assembly_png(parts, path: str | Path) -> Path:
    """Draw the assembled phantom and the exploded molds into ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 6.5), dpi=110)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    pts = []
    for p in parts:
        if p.group == "phantom":
            _draw(ax, p.mesh, _COLOURS[p.kind], alpha=0.45 if p.kind == "cast" else 0.3)
            pts.append(p.mesh.vertices)
    _limits(ax, np.vstack(pts))
    ax.set_title("assembled phantom: cast bulb and arms in the frame")
    ax2 = fig.add_subplot(1, 2, 2, projection="3d")
    pts = []
    for p in parts:
        if p.group == "bulb":
            dz = {"bulb_mold_upper": 45.0, "bulb_mold_lower": -45.0}.get(p.name, 0.0)
            _draw(ax2, p.mesh, _COLOURS[p.kind], (0.0, 0.0, dz), alpha=0.25 if p.kind == "mold" else 0.9)
            pts.append(p.mesh.vertices + [0.0, 0.0, dz])
        elif p.group.startswith("arm_") and p.kind in ("mold", "core"):
            _draw(ax2, p.mesh, _COLOURS[p.kind], alpha=0.2 if p.kind == "mold" else 0.9)
            pts.append(p.mesh.vertices)
    _limits(ax2, np.vstack(pts))
    ax2.set_title("molds: bulb mold exploded along z (core, marker sockets), arm molds with cores")
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out)
    plt.close(fig)
    return out
