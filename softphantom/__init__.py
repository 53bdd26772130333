"""softphantom: sensorized, actuated soft organ phantoms (bio-inspired prostate phantom, BIP).

Data flow, one direction (see docs/architecture.md):
design -> fem -> sensing -> estimation -> pose -> tracking -> evaluation; plus virtual, viz, cli.
SI units inside (m, N, Pa, s); user-facing names carry their unit (``y_mm``, ``p_kPa``).
"""

import os as _os

# Before numpy loads its OpenBLAS (and scikit-sparse the system's, for CHOLMOD): one BLAS thread per
# process. Both pools spin between calls; on two shared cores their threads steal the CPU the solver
# needs (an atlas plane of 20 solves: 40 CPU-s with numpy's default pool, 18 with one thread;
# docs/performance.md). Parallel work goes through Dask processes instead. A user's setting wins.
# CHOLMOD's supernodal factorization asks OpenMP for a team of 4 whatever OMP_NUM_THREADS says (a
# num_threads clause): only OMP_THREAD_LIMIT caps it. The 3 extra threads spin and sleep on futexes
# around every factorization (an atlas plane: 480 k context switches, 11 % system time, 1.16× CPU).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_THREAD_LIMIT"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
