"""A worker keeps the memory it frees for its next view instead of handing it back to the kernel.

glibc returns a freed block of 128 KB or more to the kernel at once (it was mmapped), and trims the heap's
free top past 128 KB; the next allocation of that size then faults in fresh, zeroed pages. A worker allocates
the same arrays every view (pass sets, derivations' intermediates, Cycles' per-render state), so a 66-view job
of the 7-Scenes kitchen took 221k page faults with glibc's defaults, and 630k-1,030k once the space was no
light source to Cycles (which then allocates its render state afresh each view); 182-190k with these
thresholds. Blocks up to MMAP_THRESHOLD now come from the heap, and up to TRIM_THRESHOLD of free heap is kept:
the pages are reused. Larger blocks (a point cloud's arrays) still go straight back. glibc only (mallopt);
elsewhere nothing changes.
"""

from __future__ import annotations

import ctypes
import logging

log = logging.getLogger(__name__)

MMAP_THRESHOLD = 32 << 20  # glibc's largest allowed value on 64-bit
TRIM_THRESHOLD = 512 << 20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # malloc.h


def keep_freed_memory() -> bool:
    """Set this process's malloc thresholds (see the module docstring); False where there is no glibc
    mallopt."""
    try:
        # the process's own symbols (libc's among them): ctypes.util.find_library would run ldconfig in a
        # child process at every worker start
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    if not ok:
        log.warning("mallopt refused the worker's heap thresholds; freed memory goes back to the kernel")
    return ok
