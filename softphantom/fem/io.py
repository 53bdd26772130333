"""Writing a deformed state for ParaView."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softphantom.fem.corotational import corotated_stress, von_mises
from softphantom.fem.model import FemModel


def write_deformed_vtu(path, fem: FemModel, x: np.ndarray, tet_region: np.ndarray | None = None) -> Path:
    """Write the deformed mesh as .vtu: points at the deformed positions (m, model frame, like
    ``model.vtu``), point data ``displacement_mm``, cell data ``von_mises_kPa`` (of the corotated
    stress) and, if given, ``region``."""
    import meshio

    X = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    cell_data = {"von_mises_kPa": [von_mises(corotated_stress(fem, X)) * 1e-3]}
    if tet_region is not None:
        cell_data["region"] = [np.asarray(tet_region, dtype=np.int32)]
    mesh = meshio.Mesh(
        X,
        [("tetra", np.asarray(fem.tets))],
        point_data={"displacement_mm": (X - fem.nodes) * 1e3},
        cell_data=cell_data,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.write(path, mesh, binary=True)
    return path
