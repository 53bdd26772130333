"""numba for the FEM: ``njit`` (a no-op decorator where numba is missing, ``HAVE_NUMBA`` False) and
:func:`law_kernel`, the decorator of the compiled loops that call the laws' point functions.

numba's disk cache keys a compiled function on its own source file only, so a loop cached in
``kernels.py`` would keep the inlined code of a law after that law's file changed. A
:func:`law_kernel` is cached like ``njit(cache=True)`` but keyed on its file and every file of
:mod:`softphantom.fem.laws` too: editing or adding a law recompiles the loops that inline it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

try:  # numba is a dependency; stay importable without it (numpy fallback)
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    HAVE_NUMBA = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def deco(fn):
            return fn

        return deco

LAWS_DIR = Path(__file__).with_name("laws")


def laws_stamp() -> str:
    """sha256 over the sources of every law file (names and contents)."""
    h = hashlib.sha256()
    for p in sorted(LAWS_DIR.glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


if HAVE_NUMBA:
    from numba.core.caching import CompileResultCacheImpl, FunctionCache

    def _stamped(locator: type) -> type:
        class Stamped(locator):
            def get_source_stamp(self):
                return (super().get_source_stamp(), laws_stamp())

        Stamped.__name__ = f"LawStamped{locator.__name__}"
        return Stamped

    class _LawCacheImpl(CompileResultCacheImpl):
        _locator_classes = [_stamped(c) for c in CompileResultCacheImpl._locator_classes]

    class _LawFunctionCache(FunctionCache):
        _impl_class = _LawCacheImpl


def law_kernel(**options):
    """``njit(cache=True, **options)`` whose cache is also keyed on the law files."""

    def deco(fn):
        d = njit(**options)(fn)
        if HAVE_NUMBA:
            d._cache = _LawFunctionCache(fn)  # what Dispatcher.enable_caching does, with our key
        return d

    return deco
