"""An atlas of converged equilibria over the load envelope, and the estimator that inverts it.

Offline (:func:`build_atlas`, in parallel through :mod:`softphantom.parallel`): converged forward
solves (:class:`~softphantom.estimation.forward.ForwardModel`) on a tensor grid of Chebyshev–Lobatto
points over the envelope box ``f_i ∈ [f_min,i, f_max,i]`` (N), ``p_u ∈ [p_min, p_max]`` (Pa). Each output —
the 4 arm-cavity volume changes, the tracked points (markers, targets) and the coefficients of the
displacement field in its POD basis — becomes a tensor Chebyshev polynomial in the 4 loads, exact
at the grid points and spectrally accurate between them for this smooth map. Where a corner of the
box is unreachable for the model (a solve that does not converge), the build records it, does not
try the points beyond it, fills them by extrapolation from converged neighbours and marks the
cells around them as outside the envelope (:func:`build_atlas`). The first axis may instead be the
contact patch's work-conjugate x-displacement, mapped onto the f_x range (``AtlasConfig.x_control
= "displacement"``): where the arm pair steps, f_x barely moves while the state moves across, and
the map is smooth in the displacement where it is nearly a jump in f_x; f_x is then one more
output (:meth:`Atlas.forces`).

Online (:class:`AtlasEstimator`): per sample, a Gauss–Newton iteration in the 3 force components
(the urethra pressure is measured) on the polynomial volumes, each step the bounded QP of
:func:`~softphantom.estimation.qp.solve_volume_qp` with the polynomial's Jacobian; the points and
the full field come from the same polynomials at the solution. No refresh and no thread: the step
is compiled (:mod:`~softphantom.estimation.atlas.kernels`), tens of microseconds a sample. Outside the envelope the loads are clamped to it and the
estimate carries ``in_envelope=False`` (the CSV's ``in_envelope`` column); so does an estimate in a
cell the build could not solve.

Catalogue (:mod:`~softphantom.estimation.atlas.catalogue`): :func:`find_or_build` looks an atlas
up in the model directory, then among the package's shipped files, else builds it there, under a
key made from its inputs only (:func:`atlas_key`: the stored mesh, the law as written, the contact,
the tracked points, the settings; the same on every CPU). A file whose content hash does not match,
of another format or built for another model is refused with one line and never overwritten unless
asked (``softphantom atlas build --rebuild``); :func:`verify_atlas` checks a file's numbers against
the model.

Where each job lives (this module re-exports their public names):

- :mod:`~softphantom.estimation.atlas.config`: the settings, :class:`AtlasConfig`, :func:`default_atlas_config`;
- :mod:`~softphantom.estimation.atlas.basis`: the Chebyshev maths (grids, interpolation, evaluation);
- :mod:`~softphantom.estimation.atlas.map`: :class:`Atlas`, :class:`AtlasPatches`, :class:`AtlasStack` (the polynomials);
- :mod:`~softphantom.estimation.atlas.build`: the grid sweeps on Dask, :func:`build_atlas`;
- :mod:`~softphantom.estimation.atlas.store`: the file format, describe;
- :mod:`~softphantom.estimation.atlas.catalogue`: the key, the lookup (model directory, shipped, built), verify / install;
- :mod:`~softphantom.estimation.atlas.estimator`: :class:`AtlasEstimator`;
- :mod:`~softphantom.estimation.atlas.kernels`: the compiled per-sample step.
"""

from softphantom.estimation.atlas.basis import cheb_basis, cheb_points, to_chebyshev
from softphantom.estimation.atlas.build import NODE_TOL, build_atlas, fill_weights, provenance, x_patch
from softphantom.estimation.atlas.catalogue import (Found, atlas_key, find_or_build, install_atlas, load_or_build,
                                                    verify_atlas)
from softphantom.estimation.atlas.config import P2_F_Y_SPLITS_N, X_CONTROLS, AtlasConfig, default_atlas_config
from softphantom.estimation.atlas.estimator import AtlasEstimator
from softphantom.estimation.atlas.map import Atlas, AtlasPatches, AtlasStack, KernelView
from softphantom.estimation.atlas.store import (
    FORMAT, AtlasCorrupt, AtlasMismatch, atlas_path, load_atlas, save_atlas,
)

__all__ = ["FORMAT", "NODE_TOL", "P2_F_Y_SPLITS_N", "X_CONTROLS", "Atlas", "AtlasConfig", "AtlasCorrupt",
           "AtlasEstimator", "AtlasMismatch", "AtlasPatches", "AtlasStack", "Found", "KernelView", "atlas_key",
           "atlas_path", "build_atlas", "cheb_basis", "cheb_points", "default_atlas_config", "fill_weights",
           "find_or_build", "install_atlas", "load_atlas", "load_or_build", "verify_atlas",
           "provenance", "save_atlas", "to_chebyshev", "x_patch"]
