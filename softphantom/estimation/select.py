"""One place that picks the estimator (``--estimator atlas|refresh``) for the CLI, live view and demo."""

from __future__ import annotations

from softphantom.errors import UserError
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.types import StateEstimator

ESTIMATORS = ("atlas", "refresh")
DEFAULT_ESTIMATOR = "atlas"


def check_estimator_kind(kind: str) -> str:
    """``kind`` if known, else a one-line :class:`UserError`.

    >>> check_estimator_kind("sync")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --estimator must be atlas or refresh, got 'sync'
    """
    if kind not in ESTIMATORS:
        raise UserError(f"--estimator must be {' or '.join(ESTIMATORS)}, got {kind!r}")
    return kind


def open_estimator(kind: str, model, config: EstimatorConfig | None = None, *, cache_dir=None, atlas=None,
                   scheduler: str | None = None, n_workers: int | None = None,
                   max_build_s: float | None = None, require_full: bool = False,
                   draft: bool = False) -> StateEstimator:
    """The estimator ``kind`` for ``model``: ``"atlas"`` (precomputed, loaded from or built into
    ``cache_dir``, the model directory; ``atlas`` an :class:`~softphantom.estimation.atlas.config.AtlasConfig`
    or a built atlas; a missing atlas whose build would take longer than ``max_build_s`` is refused,
    :class:`~softphantom.estimation.atlas.build.AtlasMissing`; a draft atlas is used where there is no
    full one, unless ``require_full``; ``draft``: where there is neither, the draft is built, its
    error measured) or ``"refresh"``
    (:class:`~softphantom.estimation.Estimator`, its mode from ``config``)."""
    check_estimator_kind(kind)
    if kind == "refresh":
        from softphantom.estimation.estimator import Estimator

        return Estimator(model, config)
    from softphantom.estimation.atlas.config import AtlasConfig
    from softphantom.estimation.atlas.estimator import AtlasEstimator

    if draft and (atlas is None or isinstance(atlas, AtlasConfig)):  # a draft built here is measured first
        from softphantom.estimation.atlas.check import find_or_build_measured

        atlas = find_or_build_measured(model, config or EstimatorConfig(), atlas, model_dir=cache_dir,
                                       scheduler=scheduler, n_workers=n_workers, max_build_s=max_build_s,
                                       require_full=require_full)
    return AtlasEstimator(model, config, atlas, cache_dir=cache_dir, scheduler=scheduler, n_workers=n_workers,
                          max_build_s=max_build_s, require_full=require_full, draft=draft)


def atlas_config_from_options(grid: str | None = None, envelope: str | None = None, x_axis: str | None = None,
                              f_y_splits: str | None = None, base=None):
    """An :class:`~softphantom.estimation.atlas.config.AtlasConfig` from ``--atlas-grid NX,NY,NZ,NP``
    (points per axis), ``--envelope FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX`` (N, kPa),
    ``--atlas-x-axis force|displacement`` (``AtlasConfig.x_control``) and ``--atlas-f-y-split-N
    F[,F...]`` (``AtlasConfig.f_y_splits_N``: the atlas in pieces along f_y, each with this grid;
    an empty string: one piece). What is not given comes from ``base`` (default: ``AtlasConfig()``;
    for a model, :func:`~softphantom.estimation.atlas.config.default_atlas_config` of its element order).

    >>> c = atlas_config_from_options("3,4,3,2", "-1:1,-1:2,-1:1,0:10")
    >>> c.shape, c.force_max_N, c.p_max_kPa
    ((3, 4, 3, 2), (1.0, 2.0, 1.0), 10.0)
    >>> atlas_config_from_options(x_axis="displacement").x_control
    'displacement'
    >>> atlas_config_from_options(x_axis="ux")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --atlas-x-axis: force or displacement, got 'ux'
    >>> atlas_config_from_options(f_y_splits="3.3").f_y_splits_N
    (3.3,)
    >>> atlas_config_from_options(f_y_splits="3.3 N")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --atlas-f-y-split-N: comma-separated forces in N, got '3.3 N'
    >>> from softphantom.estimation.atlas.config import default_atlas_config
    >>> c = atlas_config_from_options("11,9,4,3", base=default_atlas_config(2))
    >>> c.shape, c.x_control, c.f_y_splits_N
    ((11, 9, 4, 3), 'displacement', (3.3,))
    >>> atlas_config_from_options(f_y_splits="", base=default_atlas_config(2)).f_y_splits_N
    ()
    >>> atlas_config_from_options(envelope="-1:1,-1:4,-1:1,0:10", base=default_atlas_config(2)).f_y_splits_N
    (3.3,)
    >>> atlas_config_from_options("3,4")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --atlas-grid: expected 4 integers NX,NY,NZ,NP, got '3,4'
    """
    from dataclasses import replace

    from softphantom.estimation.atlas.config import AtlasConfig

    kw: dict = {}
    if grid is not None:
        try:
            n = [int(v) for v in grid.split(",")]
        except ValueError:
            n = []
        if len(n) != 4:
            raise UserError(f"--atlas-grid: expected 4 integers NX,NY,NZ,NP, got {grid!r}")
        kw.update(n_force=tuple(n[:3]), n_pressure=n[3])
    if envelope is not None:
        try:
            r = [tuple(float(x) for x in part.split(":")) for part in envelope.split(",")]
        except ValueError:
            r = []
        if len(r) != 4 or any(len(x) != 2 for x in r):
            raise UserError(f"--envelope: expected FXMIN:FXMAX,FYMIN:FYMAX,FZMIN:FZMAX,PMIN:PMAX (N, kPa), got {envelope!r}")
        kw.update(force_min_N=tuple(x[0] for x in r[:3]), force_max_N=tuple(x[1] for x in r[:3]),
                  p_min_kPa=r[3][0], p_max_kPa=r[3][1])
    if x_axis is not None:
        if x_axis not in ("force", "displacement"):
            raise UserError(f"--atlas-x-axis: force or displacement, got {x_axis!r}")
        kw["x_control"] = x_axis
    if f_y_splits is not None:
        try:
            kw["f_y_splits_N"] = tuple(float(v) for v in f_y_splits.split(",") if v.strip())
        except ValueError:
            raise UserError(f"--atlas-f-y-split-N: comma-separated forces in N, got {f_y_splits!r}") from None
    base = AtlasConfig() if base is None else base
    if "force_min_N" in kw and "f_y_splits_N" not in kw:  # the base's splits that fall in the new f_y range
        kw["f_y_splits_N"] = tuple(v for v in base.f_y_splits_N if kw["force_min_N"][1] < v < kw["force_max_N"][1])
    return replace(base, **kw)
