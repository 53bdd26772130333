"""The material laws: one file each (the law object and its numba point function,
:mod:`softphantom.fem.laws.base` says what a law provides), listed once in :data:`REGISTRY`.

A new law: a file here with its :class:`~softphantom.fem.laws.base.Law` subclass, appended to
:data:`REGISTRY` (its position is its ``law_id``, which the compiled kernels dispatch on and
atlases' keys hash: append, do not reorder), and its tests (tests/test_fem_law_registry.py
checks every registered law's energy, stress, tangent and objectivity).
"""

from softphantom.fem.laws.base import N_PARAMS, N_WORK, Law, Ratio
from softphantom.fem.laws.corotational import Corotational
from softphantom.fem.laws.neo_hookean import NeoHookean
from softphantom.fem.laws.yeoh import Yeoh

REGISTRY: tuple[type[Law], ...] = (Corotational, NeoHookean, Yeoh)
for _id, _law in enumerate(REGISTRY):
    _law.law_id = _id

#: law name (the design file's ``law = ...``) -> class
BY_NAME: dict[str, type[Law]] = {c.name: c for c in REGISTRY}

__all__ = ["BY_NAME", "N_PARAMS", "N_WORK", "REGISTRY", "Corotational", "Law", "NeoHookean", "Ratio", "Yeoh"]
