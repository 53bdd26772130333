"""Writing a deformed state for ParaView."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softphantom.fem.corotational import cauchy_stress, von_mises
from softphantom.fem.model import FemModel


def write_deformed_vtu(path, fem: FemModel, x: np.ndarray, tet_region: np.ndarray | None = None) -> Path:
    """Write the deformed mesh as .vtu: points at the deformed positions (m, model frame, like
    ``model.vtu``), point data ``displacement_mm``, cell data ``von_mises_kPa`` (of each element's
    mean Cauchy stress, any law) and, if given, ``region``. Quadratic models are written as
    VTK_QUADRATIC_TETRA cells (our node order is VTK's)."""
    import meshio

    X = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    cell_data = {"von_mises_kPa": [von_mises(cauchy_stress(fem, X)) * 1e-3]}
    if tet_region is not None:
        cell_data["region"] = [np.asarray(tet_region, dtype=np.int32)]
    mesh = meshio.Mesh(
        X,
        [("tetra" if fem.order == 1 else "tetra10", np.asarray(fem.tets))],
        point_data={"displacement_mm": (X - fem.nodes) * 1e3},
        cell_data=cell_data,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.write(path, mesh, binary=True)
    return path
