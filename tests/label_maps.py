"""A synthetic prostate label map like the public zonal data sets' (not a test module itself: the
anatomy tests and benchmarks/bench_anatomy.py import it)."""

from __future__ import annotations

import numpy as np


#: half axes (R-L, A-P, S-I, mm) of :func:`zonal_label_map`'s gland before its scaling: 45.2 mL
ZONAL_SEMI_RAS_MM = (25.0, 18.0, 24.0)


def zonal_label_map(volume_mL: float, tilt_deg: float = 0.0, spacing_mm=(0.6, 0.6, 4.0), fov_mm=None):
    """A synthetic prostate label map as the public zonal data sets publish theirs: an ellipsoidal
    gland of ``volume_mL`` (:data:`ZONAL_SEMI_RAS_MM` scaled) tilted by ``tilt_deg`` about R-L (its
    S-I axis towards anterior), a transition zone (label 2, the concentric ellipsoid of 0.65 × the
    semi-axes) inside a peripheral-zone shell (label 1), no urethra label, thick slices of
    ``spacing_mm``; the field of view ``fov_mm`` (default: the gland plus 8 mm each side), centred
    on the gland. Returns (data int16, affine RAS mm, semi-axes mm, the gland's axes as columns in RAS).

    >>> data, affine, semi, axes = zonal_label_map(47.0)
    >>> sorted(set(data.ravel().tolist())), float(affine[2, 2])
    ([0, 1, 2], 4.0)
    >>> round(float((data > 0).sum() * abs(np.linalg.det(affine[:3, :3]))) / 1e3, 0)  # mL, the voxels'
    47.0
    """
    sp = np.asarray(spacing_mm, float)
    base = np.asarray(ZONAL_SEMI_RAS_MM, float)
    semi = base * (volume_mL * 1e3 / (4.0 / 3.0 * np.pi * np.prod(base))) ** (1.0 / 3.0)
    fov = np.full(3, 2.0 * semi.max() + 16.0) if fov_mm is None else np.asarray(fov_mm, float)
    shape = tuple(int(n) for n in np.ceil(fov / sp))
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    axes = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])  # the tilt turns S-I (column 2) towards A
    affine = np.diag([*sp, 1.0])
    affine[:3, 3] = -0.5 * (np.array(shape) - 1) * sp
    q = (np.indices(shape).transpose(1, 2, 3, 0) * sp + affine[:3, 3]) @ axes  # along the gland's axes
    data = np.zeros(shape, np.int16)
    data[np.linalg.norm(q / semi, axis=-1) < 1.0] = 1
    data[np.linalg.norm(q / (0.65 * semi), axis=-1) < 1.0] = 2
    return data, affine, semi, axes
