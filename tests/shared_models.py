"""The meshed models the tests share, each built once per test run, and the run's preparation.

``cached_model(shared, key)`` returns the model ``key`` of :data:`MODELS`: the first process to
need it meshes it and saves it under ``shared`` (the run's temp directory, the same for every
pytest-xdist worker); a file lock makes the others wait and load it. ``cached_atlas(shared,
x_control)`` does the same for the small atlas of the coarse model that test_atlas uses
(:func:`atlas_config`). Run as a script
(``python shared_models.py SHARED JOB...``) it does the jobs in order: ``fem`` and ``atlas``
compile the numba kernels into numba's on-disk cache (``warm_up``), a model key builds that model.
"""

from __future__ import annotations

import dataclasses
import fcntl
import sys
from pathlib import Path

COARSE_MESH_SIZE_MM = 12.0


def _default(shared: Path):
    from softphantom.design import BIPDesign, build_model

    return build_model(BIPDesign(), isolate=False)


def _coarse(shared: Path):
    from softphantom.design import BIPDesign, build_model

    return build_model(BIPDesign(), COARSE_MESH_SIZE_MM, isolate=False)


def _coarse_p2(shared: Path):
    from softphantom.design import BIPDesign, MeshParams, build_model

    return build_model(BIPDesign(mesh=dataclasses.replace(MeshParams(), element_order=2)), COARSE_MESH_SIZE_MM,
                       isolate=False)


def _sharp_coarse(shared: Path):
    from softphantom.design import BIPDesign, build_model

    d = BIPDesign()
    sharp = dataclasses.replace(d, arms=tuple(dataclasses.replace(a, junction_fillet_mm=0.0) for a in d.arms))
    return build_model(sharp, COARSE_MESH_SIZE_MM, isolate=False)


def _coarse_truth_p1(shared: Path):
    from softphantom.virtual import TruthConfig, truth_model

    return truth_model(cached_model(shared, "coarse"), TruthConfig(order=1))


def _cavities(which: str):
    """The coarse designs of tests/test_cavities.py: ``two`` internal cavities (the urethra and a
    tumour balloon), or ``none``."""
    def build(shared: Path):
        from softphantom.design import build_model, design_from_dict
        from test_cavities import COARSE, two_cavities

        return build_model(design_from_dict(two_cavities() if which == "two" else {"cavities": {}, "mesh": COARSE}),
                           isolate=False)

    return build


def _five_arms(shared: Path):
    from softphantom.design import build_model, design_from_dict
    from test_arms_generic import FIVE

    return build_model(design_from_dict(FIVE), COARSE_MESH_SIZE_MM, isolate=False)


MODELS = {
    "default": _default,  # the default design at its default size (6 mm)
    "coarse": _coarse,  # the default design at 12 mm
    "coarse_p2": _coarse_p2,  # the same with 10-node tets: its corner mesh is coarse's
    "sharp_coarse": _sharp_coarse,  # the default design without junction fillets, 12 mm
    "coarse_truth_p1": _coarse_truth_p1,  # the virtual phantom's linear truth mesh for coarse (9 mm)
    "two_cavities": _cavities("two"),  # test_cavities' design with a tumour balloon beside the urethra, 12 mm
    "no_cavities": _cavities("none"),  # the same without any internal cavity
    "five_arms": _five_arms,  # tests/test_arms_generic.py's five-arm design, 12 mm
}

def model_dir(shared: Path, key: str) -> Path:
    """The directory ``key`` is saved in (built first if needed). Read only: it is shared."""
    from softphantom.design import save_model

    target = shared / f"softphantom_model_{key}"
    with open(shared / f"softphantom_model_{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not (target / "model.npz").is_file():
                save_model(MODELS[key](shared), target)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return target


_loaded: dict = {}


def cached_model(shared: Path, key: str):
    """The model ``key`` (a read-only PhantomModel), loaded once per process."""
    from softphantom.design import load_model

    if key not in _loaded:
        _loaded[key] = load_model(model_dir(shared, key))
    return _loaded[key]


def atlas_config(x_control: str = "force"):
    """The small atlas envelope and grid of the coarse model's tests (on-centre contact): 3 × 4 × 3 × 2
    points, f_x (or the patch displacement) spanning ±0.5 N."""
    from softphantom.estimation import AtlasConfig

    return AtlasConfig(force_min_N=(-0.5, -0.3, -0.5), force_max_N=(0.5, 1.2, 0.5), p_min_kPa=-1.0, p_max_kPa=4.0,
                       n_force=(3, 4, 3), n_pressure=2, x_control=x_control)


_atlases: dict = {}


def cached_atlas(shared: Path, x_control: str = "force"):
    """:func:`atlas_config`'s atlas of the coarse model built by full solves (an
    :class:`~softphantom.estimation.atlas.map.Atlas`, read only), built once per test run and
    loaded once per process."""
    from softphantom.estimation import EstimatorConfig, build_atlas
    from softphantom.estimation.atlas.store import load_atlas, save_atlas

    if x_control not in _atlases:
        path = shared / f"softphantom_atlas_{x_control}.npz"
        with open(shared / f"softphantom_atlas_{x_control}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                if not path.is_file():
                    at = build_atlas(cached_model(shared, "coarse"), EstimatorConfig(contact="on-centre"),
                                     atlas_config(x_control), n_workers=1, processes=False)
                    save_atlas(at, path)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
        _atlases[x_control] = load_atlas(path)
    return _atlases[x_control]


def main(argv: list[str]) -> None:
    shared, jobs = Path(argv[0]), argv[1:]
    for job in jobs:
        if job == "fem":
            from softphantom.fem import kernels

            kernels.warm_up()
        elif job == "atlas":
            from softphantom.estimation.atlas import kernels as atlas_kernels

            atlas_kernels.warm_up()
        else:
            model_dir(shared, job)


if __name__ == "__main__":
    main(sys.argv[1:])
