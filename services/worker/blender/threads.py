"""Import bpy with Blender's thread pool sized to the render thread budget, so an idle worker does not spin.

Cycles limits TBB with `tbb::global_control(max_allowed_parallelism, threads)` while its (persistent) session
lives. When that limit is below the pool TBB already started (its default: one thread per CPU of the process's
affinity), the surplus TBB workers keep spinning in sched_yield (oneTBB issue 1417): a worker started with
`--render-threads 1` on a multi-core host burnt a whole core while idle. TBB fixes its default concurrency
from the calling thread's CPU affinity when Blender initialises it during `import bpy`, so the import runs
with the affinity narrowed to `threads` CPUs and the affinity is restored right after: the pool then never
exceeds the budget, and the OS still schedules the render threads on any CPU.

Blender also starts OpenEXR's global thread pool with a thread per CPU. A pass EXR (the readback where Cycles'
engine cannot be wrapped: render.configure_scene) is written uncompressed, so its 512 scanline blocks have
nothing worth a thread, yet each wakes one: ~800 context switches a view, 3% of the render task's CPU on one
core. The pool is set to 0 threads after the import (OpenEXR then writes in the
calling thread; the same bytes).
"""

from __future__ import annotations

import ctypes
import logging
import os
import shutil
import sys
from pathlib import Path

from services.worker.blender.calls import in_blender

log = logging.getLogger(__name__)


def import_bpy(threads: int | None) -> None:
    """Import bpy (once per process) with a TBB pool of at most `threads` threads (None: every allowed
    CPU)."""
    if "bpy" in sys.modules:
        return
    _drop_inherited_script_dirs()
    cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
    with in_blender():  # Blender's start-up runs its Python scripts from C (services.worker.blender.calls)
        if not threads or threads >= len(cpus):
            import bpy  # noqa: F401
        else:
            os.sched_setaffinity(0, set(sorted(cpus)[:threads]))
            try:
                import bpy  # noqa: F401, F811
            finally:
                os.sched_setaffinity(0, cpus)
            log.info("bpy imported with a thread pool of %d of this process's %d CPUs", threads, len(cpus))
    set_exr_threads(0)


def remove_session_temp_dir() -> None:
    """Remove Blender's session temp folder ($TMPDIR/blender_XXXXXX, made by `import bpy`), for a process that
    leaves through os._exit: Blender removes it only in its own exit, so every worker left one behind (an
    empty folder in /tmp per worker and run). Nothing when this process never imported bpy."""
    bpy = sys.modules.get("bpy")
    if bpy is None:
        return
    session = Path(bpy.app.tempdir)
    if session.name.startswith("blender_"):  # the session folder, never the base temp dir a user configured
        shutil.rmtree(session, ignore_errors=True)


# OpenEXR's C++ namespace carries its version (Imf_3_3 in bpy 4.5): the mangled setter, tried newest first
_EXR_NAMESPACES = ("Imf_3_4", "Imf_3_3", "Imf_3_2")


def blender_openexr() -> ctypes.CDLL | None:
    """The OpenEXR library Blender loaded (under bpy's folder; not the OpenEXR wheel's copy), or None."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "libOpenEXR.so" in line and "/bpy/" in line}
    except OSError:  # not Linux
        return None
    return ctypes.CDLL(sorted(paths)[0]) if paths else None


def set_exr_threads(n: int) -> int | None:
    """Set Blender's OpenEXR global thread count; returns the count now in force, or None where the library
    or its setter is not found (nothing changed: only a cost)."""
    lib = blender_openexr()
    for ns in _EXR_NAMESPACES if lib is not None else ():
        try:
            setter = getattr(lib, f"_ZN{len(ns)}{ns}20setGlobalThreadCountEi")
            getter = getattr(lib, f"_ZN{len(ns)}{ns}17globalThreadCountEv")
        except AttributeError:
            continue
        setter(ctypes.c_int(n))
        return int(getter())
    log.debug("Blender's OpenEXR thread pool not found: EXR writes keep its threads")
    return None


def _drop_inherited_script_dirs() -> None:
    """Blender's script folders on sys.path before bpy is imported came from a parent that had imported it (a
    spawned child inherits its sys.path): their pure-Python `bpy` package would shadow the module itself
    ("No module named '_bpy'"). bpy puts them back when it loads."""
    def inherited(entry: str) -> bool:
        parts = Path(entry).parts
        return "bpy" in parts and "scripts" in parts[parts.index("bpy"):]

    sys.path[:] = [p for p in sys.path if not inherited(p)]
