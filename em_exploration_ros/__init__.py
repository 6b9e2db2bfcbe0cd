"""em_exploration_ros: multi-robot exploration under localization uncertainty with EM.

The planners do many small dense linear-algebra operations; a multi-threaded BLAS makes
those much slower on a busy machine (a 150x120 QR took 50 ms instead of 0.4 ms on two
loaded cores). One BLAS thread per process is therefore the default; set
OPENBLAS_NUM_THREADS (or OMP_NUM_THREADS) before starting a tool to override it.
"""
import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
