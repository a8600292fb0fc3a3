"""Validate an uploaded space in a child process with memory, CPU and wall-clock limits.

A hostile mesh (a header declaring billions of faces, a deflate stream that never ends, a file that sends
the parser into a pathological path) must not take the API down: `load_space_limited` runs `load_space` in
a child process that caps the growth of its address space (RLIMIT_AS) and CPU time (RLIMIT_CPU) and is killed
when it runs past `timeout_s`. The child sends back the LoadedSpace with a slimmed mesh (vertices and faces
only) for `register_space`; every failure becomes a SpaceError whose message names the limit that was hit.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import signal
from collections.abc import Sequence
from multiprocessing.connection import Connection
from pathlib import Path

from services.core.domain.jobspec import SpaceFrame
from services.core.ingest.errors import SpaceError
from services.core.ingest.loading import LoadedSpace
from services.core.temp_dirs import UPLOAD_KINDS, sweep_orphans

# Children fork from a server process that has imported the loading code once: a check starts in
# milliseconds instead of the second a fresh interpreter needs to import trimesh, and the fork happens in a
# single-threaded process (the API's is not).
_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(
    ["services.core.ingest.loading", "services.core.ingest.guard.mesh_checks", "trimesh"])
_RESULT_GRACE_S = 10.0  # for a child to exit once it has sent its result
CHILD_NICENESS = 10  # a reader yields the CPU to the process waiting on it (the API serving other requests)


def load_space_limited(
    path: str | Path,
    *,
    up_axis: str = "auto",
    unit_scale: float | str = "auto",
    max_faces: int,
    memory_mb: int,
    timeout_s: float,
    up: Sequence[float] | None = None,
    source_to_world: Sequence[Sequence[float]] | None = None,
    accept_up_guess: bool = True,
    keep_mesh: bool = True,
) -> LoadedSpace:
    """`load_space(path)` in a child process with limits; SpaceError for an unusable scan or a limit hit.

    An upload accepts detection's guesses (`accept_up_guess`): an ambiguous frame is recorded, and the space
    waits for a person to pick one; a pick (`up`) or a stored frame (`source_to_world`) is loaded as given.
    Without `keep_mesh` the result's mesh is empty: a caller that needs only the frame, bounds and counts is
    not sent the geometry (unpickling it would hold the caller's interpreter).
    """
    name = Path(path).name
    receiver, sender = _CONTEXT.Pipe(duplex=False)
    limits = {"memory_mb": memory_mb, "cpu_s": max(1, int(timeout_s)), "max_faces": max_faces,
              "keep_mesh": int(keep_mesh)}
    frame: SpaceFrame = {
        "up_axis": up_axis, "unit_scale": unit_scale, "up": up, "source_to_world": source_to_world,
        "accept_up_guess": accept_up_guess,
    }
    proc = _CONTEXT.Process(
        target=_child, args=(sender, str(path), frame, limits), name="omnidata-safe-load", daemon=True
    )
    proc.start()
    sender.close()
    try:
        if not receiver.poll(timeout_s):
            raise SpaceError(f"{name}: reading the mesh took longer than the limit of {timeout_s:g} s")
        try:
            kind, value = receiver.recv()
        except EOFError:  # the child died without a word: killed by a limit
            proc.join(5)
            raise SpaceError(_died(name, proc.exitcode, memory_mb, timeout_s)) from None
        proc.join(_RESULT_GRACE_S)  # it has sent its result and is exiting
    finally:
        receiver.close()
        if proc.is_alive():
            proc.kill()
            proc.join()
        if proc.exitcode != 0 and proc.pid is not None:  # killed by a limit: its zip extraction stays behind
            sweep_orphans(UPLOAD_KINDS, only_pid=proc.pid)
    if kind == "ok":
        loaded: LoadedSpace = value
        return loaded
    if kind == "memory":
        raise SpaceError(f"{name}: reading the mesh needs more than the memory limit of {memory_mb} MiB")
    raise SpaceError(str(value))


def _died(name: str, exitcode: int | None, memory_mb: int, timeout_s: float) -> str:
    if exitcode in (-signal.SIGXCPU, -signal.SIGKILL):
        return f"{name}: reading the mesh ran past its CPU limit of {timeout_s:g} s"
    return f"{name}: the mesh reader stopped (exit code {exitcode}; memory limit {memory_mb} MiB)"


def _mapped_bytes() -> int:
    """Virtual memory this process has mapped (VmSize), 0 where /proc is missing."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _child(sender: Connection, path: str, frame: SpaceFrame, limits: dict[str, int]) -> None:
    """Child side: set the limits, load and check the space, send ("ok", slim LoadedSpace) or the error."""
    import resource

    import trimesh

    from services.core.ingest.guard.mesh_checks import check_face_count
    from services.core.ingest.loading import load_space

    # on top of what the process has mapped already (thread arenas and libraries: GBs on many-core hosts)
    memory = _mapped_bytes() + int(limits["memory_mb"]) * 2**20
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CPU, (int(limits["cpu_s"]), int(limits["cpu_s"]) + 1))
    os.nice(CHILD_NICENESS)
    try:
        loaded = load_space(path, **frame)
        check_face_count(Path(path).name, loaded.face_count, int(limits["max_faces"]))
        # register_space reads the counts and transforms, not the visuals or parser metadata: leave those here
        slim = (trimesh.Trimesh(vertices=loaded.mesh.vertices, faces=loaded.mesh.faces, process=False)
                if limits["keep_mesh"] else trimesh.Trimesh())
        result: tuple[str, object] = ("ok", dataclasses.replace(loaded, mesh=slim))
    except SpaceError as e:  # load_space reports a parser's MemoryError as unreadable: name the limit instead
        result = ("memory", None) if "MemoryError" in str(e) else ("space_error", str(e))
    except MemoryError:
        result = ("memory", None)
    except Exception as e:  # a reader's own error (RecursionError, OSError, ...): one line naming the file
        result = ("space_error", f"{Path(path).name}: the reader failed ({type(e).__name__}: {str(e)[:300]})")
    sender.send(result)
    sender.close()
