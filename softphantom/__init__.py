"""softphantom: sensorized, actuated soft organ phantoms (bio-inspired prostate phantom, BIP).

Data flow, one direction (see docs/architecture.md):
design -> fem -> sensing -> estimation -> pose -> tracking -> evaluation; plus virtual, viz, cli.
SI units inside (m, N, Pa, s); user-facing names carry their unit (``y_mm``, ``p_kPa``).
"""

import os as _os
import sys as _sys

# One BLAS thread per process. Both OpenBLAS pools (numpy's; the system's, behind CHOLMOD) spin
# between calls; on two shared cores their threads steal the CPU the solver needs (an atlas plane of
# 20 solves: 40 CPU-s with numpy's default pool, 18 with one thread; docs/performance/design-fem.md). Parallel
# work goes through Dask processes instead. A user's setting wins.
# The variables reach the libraries loaded after this (numpy, CHOLMOD's BLAS when scikit-sparse is
# imported) and the worker processes, which inherit them; threadpoolctl caps the pools that were
# loaded before softphantom was imported (a script that imports numpy first).
# CHOLMOD's supernodal factorization asks OpenMP for a team of 4 whatever OMP_NUM_THREADS says (a
# num_threads clause): only OMP_THREAD_LIMIT caps it, an OpenMP setting read once when the runtime
# starts, with no call to change it later (so threadpoolctl cannot). The 3 extra threads spin and
# sleep on futexes around every factorization (an atlas plane: 480 k context switches, 11 % system
# time, 1.16x CPU).
_THREAD_VARS = {"blas": ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"), "openmp": ("OMP_NUM_THREADS",)}
_user_set = {v for v in (*_THREAD_VARS["blas"], *_THREAD_VARS["openmp"]) if v in _os.environ}
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_THREAD_LIMIT"):
    _os.environ.setdefault(_var, "1")
# MKL's OpenMP runtime (PARDISO, the pardiso extra) warns on stderr when CHOLMOD asks for its team of
# 4 under that limit: the limit is meant.
_os.environ.setdefault("KMP_WARNINGS", "0")
if "numpy" in _sys.modules:  # pools already loaded, sized before the defaults above
    from threadpoolctl import threadpool_limits as _limits

    for _api, _vars in _THREAD_VARS.items():
        if not _user_set.intersection(_vars):
            _limits(limits=1, user_api=_api)

__version__ = "0.1.0"
