"""Shared session fixtures: meshed models (read-only :class:`~softphantom.design.model.PhantomModel`
values, SI units), each meshed once per test run by the first worker to need it (shared_models.py).

- ``default_model``: the default BIP at its default mesh size (6 mm, ~6 000 nodes);
- ``coarse_model``: the same design at 12 mm (``shared_models.COARSE_MESH_SIZE_MM``, 2 170 nodes), for fast FEM
  tests, and ``coarse_model_dir``, the directory it is saved in (shared: never write into it);
- ``coarse_p2_model``: ``coarse_model``'s mesh with 10-node tets (the same corner nodes and tets);
- ``sharp_coarse_model``: the default design without the junction fillets, at 12 mm;
- ``coarse_truth_p1``: the virtual phantom's truth mesh for ``coarse_model`` with linear tets
  (``truth_model(coarse_model, TruthConfig(order=1))``, 9 mm);
- ``two_cavities_model`` and ``no_cavities_model``: tests/test_cavities.py's coarse designs with a
  tumour balloon beside the urethra, and without any internal cavity (three test files read them);
- ``five_arms_model``: tests/test_arms_generic.py's five-arm design at 12 mm, and ``five_arms_model_dir``.

Under pytest-xdist (``make test``) the controller first compiles the numba kernels and meshes the
models most tests use, in parallel processes, before the workers start: a fresh clone has no
numba cache, and each worker, and each process a test starts, would otherwise compile the same
kernels (~25 CPU-s) at their first use.

Order: ``--dist loadfile`` hands out whole files in collection order (xdist's own reordering, by
number of tests, is turned off here): files holding a test marked ``slow`` first, then the others
by number of tests, so the long files start early and short ones fill in at the end on both
workers. Mark a test ``slow`` when it, with the module fixtures it is first to need, takes more
than ~5 CPU-s (``pytest -m "not slow"`` leaves them out).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from shared_models import cached_model, model_dir  # noqa: E402

# No truth cache (softphantom.virtual.truth) unless a test sets one: nothing written to the user's
# cache directory, and no test reads a truth another one solved (the processes a test starts too).
os.environ["SOFTPHANTOM_CACHE_DIR"] = ""

# jobs of the preparation processes (shared_models.main), about equal on a fresh clone
_PREPARE = (["fem"], ["atlas", "default"], ["coarse", "coarse_truth_p1"])
_prepared_s = pytest.StashKey[float]()


def _shared_dir(tmp_path_factory) -> Path:
    root = Path(tmp_path_factory.getbasetemp())
    # under xdist every worker has its own basetemp below one shared parent (the controller's)
    return root.parent if root.name.startswith("popen-gw") else root


def pytest_configure(config):
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False  # the order below (pytest_collection_modifyitems)


def pytest_collection_modifyitems(config, items):
    """Files with a ``slow`` test first, then by number of tests (more first); stable otherwise."""
    def file_of(item):
        return item.nodeid.split("::")[0]

    slow = {file_of(it) for it in items if it.get_closest_marker("slow")}
    count: dict[str, int] = {}
    for it in items:
        count[file_of(it)] = count.get(file_of(it), 0) + 1
    items.sort(key=lambda it: (file_of(it) not in slow, -count[file_of(it)]))


def pytest_sessionstart(session):
    """Under xdist, in the controller, before its workers start: the preparation processes."""
    config = session.config
    if hasattr(config, "workerinput") or config.pluginmanager.getplugin("dsession") is None:
        return
    t0 = time.perf_counter()
    shared = _shared_dir(config._tmp_path_factory)
    script = Path(__file__).resolve().parent / "shared_models.py"
    procs = [subprocess.Popen([sys.executable, str(script), str(shared), *jobs]) for jobs in _PREPARE]
    for p in procs:
        p.wait()  # a failure shows again, as a test error, where a test needs what failed
    config.stash[_prepared_s] = time.perf_counter() - t0


def pytest_terminal_summary(terminalreporter, config):
    if _prepared_s in config.stash:  # before the session's clock started: not in its time
        terminalreporter.write_line(f"numba kernels and shared models prepared in {config.stash[_prepared_s]:.0f} s "
                                    "before the workers started")


@pytest.fixture(scope="session")
def shared_dir(tmp_path_factory) -> Path:
    return _shared_dir(tmp_path_factory)


def _model_fixture(key: str):
    def model(shared_dir):
        return cached_model(shared_dir, key)

    return model


# fixture name -> shared_models.MODELS key (the list in the docstring above)
for _name, _key in {"default_model": "default", "coarse_model": "coarse", "coarse_p2_model": "coarse_p2",
                    "sharp_coarse_model": "sharp_coarse", "coarse_truth_p1": "coarse_truth_p1",
                    "two_cavities_model": "two_cavities", "no_cavities_model": "no_cavities",
                    "five_arms_model": "five_arms"}.items():
    globals()[_name] = pytest.fixture(scope="session", name=_name)(_model_fixture(_key))


@pytest.fixture(scope="session")
def coarse_model_dir(shared_dir) -> Path:
    """The model directory of ``coarse_model`` (read only: other tests read it too)."""
    return model_dir(shared_dir, "coarse")


@pytest.fixture(scope="session")
def five_arms_model_dir(shared_dir) -> Path:
    """The model directory of ``five_arms_model`` (read only)."""
    return model_dir(shared_dir, "five_arms")
