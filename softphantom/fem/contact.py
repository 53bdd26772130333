"""One contact model: a force spread as a uniform traction over a disc-like patch of the outer
surface (DESIGN.md §5: a force at a single point is singular in 3-D)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.sparse as sp

from softphantom.errors import UserError
from softphantom.fem.elements import tri_rule, tri_shape
from softphantom.fem.model import FemModel

#: m, the one default patch radius: 4 mm, the patch of the converged reference of DESIGN.md §5
#: (its figures are for 4 mm patches); it lies between a needle tip (1.3 mm) and a
#: finger (8 mm) and spans about two surface elements of the default mesh (4 mm on the bulb), so
#: the loaded area is resolved on every mesh we use.
DEFAULT_CONTACT_RADIUS_M = 4.0e-3


@dataclass(frozen=True)
class ContactPatch:
    """A contact force spread uniformly over the outer surface within ``radius_m`` of ``center_m``.

    :meth:`load_matrix` gives the (3N,3) sparse H with ``H @ F`` the consistent nodal loads of the
    uniform traction t = F / A (A the patch's area): f_a = ∫_patch N_a dA · F / A, integrated with
    the surface shape functions of the element order (linear or quadratic triangles; for 6-node
    triangles corners and mid-edge nodes get their own, different shares, as a uniform traction
    requires). The patch is the part of the outer surface (cavity walls excluded) at straight-line
    distance <= ``radius_m`` from ``center_m``, sampled on a sub-triangle grid fine against the
    radius. Column j applies 1 N along world axis j; the columns sum to exactly 1 N.

    Presets (``ContactPatch.preset("needle", c)``): ``needle`` 1.3 mm (needle tip), ``finger`` 8 mm;
    default radius :data:`DEFAULT_CONTACT_RADIUS_M` (4 mm).

    >>> import numpy as np
    >>> from softphantom.fem.meshes import box_mesh
    >>> from softphantom.fem.model import build_fem
    >>> X, T = box_mesh((0.02, 0.02, 0.02), (4, 4, 4))
    >>> H = ContactPatch((0.01, 0.01, 0.02), 0.004).load_matrix(build_fem(X, T))
    >>> H.shape, round(float(H.sum(axis=0)[0, 2]), 12)
    ((375, 3), 1.0)
    """

    center_m: tuple[float, float, float]
    radius_m: float = DEFAULT_CONTACT_RADIUS_M

    PRESETS: ClassVar[dict[str, float]] = {"needle": 1.3e-3, "finger": 8.0e-3, "default": DEFAULT_CONTACT_RADIUS_M}

    def __post_init__(self) -> None:
        c = np.asarray(self.center_m, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise UserError(f"contact patch centre must be 3 finite numbers (m), got {self.center_m!r}")
        object.__setattr__(self, "center_m", tuple(float(v) for v in c))
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise UserError(f"contact patch radius_m = {self.radius_m!r} must be > 0")

    @classmethod
    def preset(cls, name: str, center_m) -> ContactPatch:
        """A patch of a named radius: ``needle`` (1.3 mm), ``finger`` (8 mm), ``default`` (4 mm)."""
        if name not in cls.PRESETS:
            raise UserError(f"contact preset {name!r} unknown (known: {', '.join(cls.PRESETS)})")
        return cls(center_m, cls.PRESETS[name])

    def load_matrix(self, fem: FemModel, x: np.ndarray | None = None) -> sp.csr_matrix:
        """(3N,3) H of this patch on ``fem``'s outer surface at positions ``x`` (default rest)."""
        xyz = (fem.nodes if x is None else np.asarray(x, dtype=np.float64)).reshape(-1, 3)
        faces = outer_surface(fem)
        c, r = np.asarray(self.center_m), self.radius_m
        fp = xyz[faces]  # (B,k,3)
        size = np.linalg.norm(fp[:, :3] - fp[:, [1, 2, 0]], axis=2).max(axis=1)
        near = np.flatnonzero(np.linalg.norm(fp - c, axis=2).min(axis=1) <= r + size)
        if near.size == 0:
            raise UserError(
                f"no outer surface within {r * 1e3:.3g} mm of the contact point "
                f"{np.round(c * 1e3, 3).tolist()} mm"
            )
        order = 1 if faces.shape[1] == 3 else 2
        level = int(min(32, max(4, math.ceil(3.0 * size[near].max() / r))))
        pts, w = _subgrid(level)
        N, dN = tri_shape(order, pts)  # (P,k), (P,k,2)
        p = fp[near]
        xq = np.einsum("qa,fai->fqi", N, p)
        xs = np.einsum("qa,fai->fqi", dN[:, :, 0], p)
        xt = np.einsum("qa,fai->fqi", dN[:, :, 1], p)
        dA = np.linalg.norm(np.cross(xs, xt), axis=2) * w  # (F,P)
        dA = dA * (np.linalg.norm(xq - c, axis=2) <= r)
        area = dA.sum()
        if not area > 0:
            raise UserError(
                f"no outer surface within {r * 1e3:.3g} mm of the contact point "
                f"{np.round(c * 1e3, 3).tolist()} mm"
            )
        share = np.einsum("fq,qa->fa", dA, N) / area  # (F,k), sums to 1
        nodes = faces[near].reshape(-1)
        wn = np.bincount(nodes, weights=share.reshape(-1), minlength=fem.n_nodes)
        idx = np.flatnonzero(wn)
        rows = (3 * idx[:, None] + np.arange(3)).reshape(-1)
        cols = np.tile(np.arange(3), idx.size)
        return sp.csr_matrix((np.repeat(wn[idx], 3), (rows, cols)), shape=(fem.n_dof, 3))


def _subgrid(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and weights of the 6-point degree-4 rule on each of the level² sub-triangles of the
    reference triangle: exact for the shape functions (and their products with the area element of
    a flat face) on faces wholly inside the patch; the patch's rim is resolved to 1/level."""
    qp, qw = tri_rule()
    i, j = np.meshgrid(np.arange(level), np.arange(level), indexing="ij")
    up = (i + j) <= level - 1
    dn = (i + j) <= level - 2
    v0 = np.concatenate([np.column_stack([i[up], j[up]]), np.column_stack([i[dn] + 1, j[dn] + 1])]) / level
    e1 = np.concatenate([np.tile([1.0, 0.0], (up.sum(), 1)), np.tile([-1.0, 0.0], (dn.sum(), 1))]) / level
    e2 = np.concatenate([np.tile([0.0, 1.0], (up.sum(), 1)), np.tile([0.0, -1.0], (dn.sum(), 1))]) / level
    pts = v0[:, None] + qp[None, :, :1] * e1[:, None] + qp[None, :, 1:] * e2[:, None]
    return pts.reshape(-1, 2), np.tile(qw / level**2, len(v0))


def outer_surface(fem: FemModel) -> np.ndarray:
    """Boundary triangles of ``fem`` that are not cavity walls ((B,3) or (B,6))."""
    faces = fem.boundary_faces
    if not fem.cavities:
        return faces
    cav = np.concatenate([np.asarray(v)[:, :3] for v in fem.cavities.values()])
    n = fem.n_nodes
    key = lambda t: np.sort(t[:, :3], axis=1) @ np.array([n * n, n, 1], dtype=np.int64)  # noqa: E731
    return faces[~np.isin(key(faces), key(cav))]
