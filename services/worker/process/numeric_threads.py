"""One thread for the numeric libraries (BLAS, OpenMP) of a worker process, whatever its render threads.

Set before numpy loads. With several BLAS threads the segmentations' eigenvectors and matrix products round
differently, so labels would depend on the machine's cores and the worker's settings; at these sizes the
threads also cost more than they save (an eigenproblem of 100 nodes took 16 ms instead of 0.2 ms). Cycles
sizes its own thread pool (services.worker.blender.threads), and the derivation kernels are single-threaded.
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

NUMERIC_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")

_pinned_before_numpy = False  # this process's numeric libraries loaded pinned (what a forked worker inherits)


def pin_numeric_threads(environ: MutableMapping[str, str] = os.environ) -> None:
    """Set every numeric library's thread count to 1 in `environ` (a user's own setting included: outputs must
    not depend on it)."""
    global _pinned_before_numpy
    for var in NUMERIC_THREAD_VARS:
        environ[var] = "1"
    if environ is os.environ and "numpy" not in sys.modules:
        _pinned_before_numpy = True


def numeric_threads_pinned() -> bool:
    """True when this process pinned its numeric libraries before numpy loaded them: a child forked from it
    runs them on one thread too."""
    return _pinned_before_numpy
