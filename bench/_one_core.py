"""Import first in a benchmark script: numba, OpenMP and OpenBLAS use one thread (one core)."""

import os

for _name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
