"""Shared session fixtures.

``default_model`` (the default BIP at its default mesh size, ~6 000 nodes) and ``coarse_model``
(the same design at ``COARSE_MESH_SIZE_MM``, ~1 600 nodes, for fast FEM tests). Each is meshed
once per test run: the first worker to need it builds and saves it under the run's shared temp
directory (a file lock serialises pytest-xdist workers); the others load it. Both are read-only
:class:`~softphantom.design.model.PhantomModel` values.
"""

from __future__ import annotations

import fcntl
from pathlib import Path

import pytest

COARSE_MESH_SIZE_MM = 12.0


def _cached_model(tmp_path_factory, key: str, mesh_size_mm: float | None):
    from softphantom.design import BIPDesign, build_model, load_model, save_model

    root = Path(tmp_path_factory.getbasetemp())
    # under xdist every worker has its own basetemp below one shared parent
    shared = root.parent if root.name.startswith("popen-gw") else root
    target = shared / f"softphantom_model_{key}"
    with open(shared / f"softphantom_model_{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if (target / "model.npz").is_file():
                return load_model(target)
            model = build_model(BIPDesign(), mesh_size_mm)
            save_model(model, target)
            return model
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def default_model(tmp_path_factory):
    """The default BIP design meshed at its default size (a PhantomModel, SI units)."""
    return _cached_model(tmp_path_factory, "default", None)


@pytest.fixture(scope="session")
def coarse_model(tmp_path_factory):
    """The default BIP design meshed coarsely (``COARSE_MESH_SIZE_MM``) for fast tests."""
    return _cached_model(tmp_path_factory, "coarse", COARSE_MESH_SIZE_MM)
