"""Worker processes run the numeric libraries on one thread, whatever the render threads or the user's
setting: the segmentations' labels must not depend on the machine (with several BLAS threads their
eigenvectors round differently)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from services.worker.process.numeric_threads import NUMERIC_THREAD_VARS, pin_numeric_threads

ROOT = Path(__file__).resolve().parents[3]


def test_pinning_overrides_a_users_setting():
    env = {"OMP_NUM_THREADS": "8", "OPENBLAS_NUM_THREADS": "16", "PATH": "/bin"}
    pin_numeric_threads(env)
    assert {v: env[v] for v in NUMERIC_THREAD_VARS} == dict.fromkeys(NUMERIC_THREAD_VARS, "1")
    assert env["PATH"] == "/bin"


def test_pinned_before_numpy_loads_openblas_runs_one_thread():
    # What the worker entry points (the embedded pool's worker body, `omnidata worker`, the Celery app) do
    # first, in a process whose user asked for 8 threads: numpy's OpenBLAS, loaded afterwards, runs one.
    probe = (
        "from services.worker.process.numeric_threads import pin_numeric_threads\npin_numeric_threads()\n"
        "import ctypes, numpy\n"
        "lib = next(line.split()[-1] for line in open('/proc/self/maps') if 'openblas' in line)\n"
        "blas = ctypes.CDLL(lib)\n"
        "get = getattr(blas, 'openblas_get_num_threads64_', None) or blas.openblas_get_num_threads\n"
        "print(get())\n"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "8", "OPENBLAS_NUM_THREADS": "8", "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1"
    # the probe can tell: without the pin, 8 (or the cores)
    unpinned = probe.replace("pin_numeric_threads()\n", "")
    out = subprocess.run(
        [sys.executable, "-c", unpinned], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() != "1" or os.cpu_count() == 1
