"""Import bpy with Blender's thread pool sized to the render thread budget, so an idle worker does not spin.

Cycles limits TBB with `tbb::global_control(max_allowed_parallelism, threads)` while its (persistent) session
lives. When that limit is below the pool TBB already started (its default: one thread per CPU of the process's
affinity), the surplus TBB workers keep spinning in sched_yield (oneTBB issue 1417): a worker started with
`--render-threads 1` on a multi-core host burnt a whole core while idle. TBB fixes its default concurrency from
the calling thread's CPU affinity when Blender initialises it during `import bpy`, so the import runs with the
affinity narrowed to `threads` CPUs and the affinity is restored right after: the pool then never exceeds the
budget, and the OS still schedules the render threads on any CPU.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def import_bpy(threads: int | None) -> None:
    """Import bpy (once per process) with a TBB pool of at most `threads` threads (None: every allowed CPU)."""
    if "bpy" in sys.modules:
        return
    _drop_inherited_script_dirs()
    cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
    if not threads or threads >= len(cpus):
        import bpy  # noqa: F401
        return
    os.sched_setaffinity(0, set(sorted(cpus)[:threads]))
    try:
        import bpy  # noqa: F401, F811
    finally:
        os.sched_setaffinity(0, cpus)
    log.info("bpy imported with a thread pool of %d of this process's %d CPUs", threads, len(cpus))


def _drop_inherited_script_dirs() -> None:
    """Blender's script folders on sys.path before bpy is imported came from a parent that had imported it (a
    spawned child inherits its sys.path): their pure-Python `bpy` package would shadow the module itself
    ("No module named '_bpy'"). bpy puts them back when it loads."""
    def inherited(entry: str) -> bool:
        parts = Path(entry).parts
        return "bpy" in parts and "scripts" in parts[parts.index("bpy"):]

    sys.path[:] = [p for p in sys.path if not inherited(p)]
