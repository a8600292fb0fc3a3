"""A worker process reuses the memory it frees (services.worker.process.heap): the same arrays allocated view
after view fault in no fresh pages. With glibc's defaults every such array came back from the kernel zeroed
again."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

# Faults per allocation of a 24 MB array (a pass set's size) once one was freed, with and without the tuning.
PROBE = r"""
import json, resource, sys
import numpy as np
from services.worker.process.heap import keep_freed_memory
tuned = keep_freed_memory() if sys.argv[1] == "tuned" else None
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(3 << 20); del a
f0 = faults()
for _ in range(20):
    a = np.ones(3 << 20); a[::512] = 2.0; del a
print(json.dumps({"tuned": tuned, "faults": (faults() - f0) / 20}))
"""


def _faults_per_allocation(mode: str) -> dict:
    run = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, cwd=ROOT, check=True
    )
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_array_is_reused_not_faulted_in_again() -> None:
    tuned, plain = _faults_per_allocation("tuned"), _faults_per_allocation("plain")
    assert tuned["tuned"] is True
    # glibc's defaults: the 24 MB block went back to the kernel and comes back zeroed
    assert plain["faults"] >= 10
    assert tuned["faults"] < 1
