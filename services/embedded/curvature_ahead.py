"""The spaces' curvature, computed by `generate` itself while its workers start, when several workers would
wait on it.

Every worker needs its space's per-vertex curvature at its first render. The first to get there computes it
(shared_curvature: 0.35 CPU-s on the ICL living room, 0.9 on the 7-Scenes kitchen) under a file lock while the
others wait on the lock, so on N cores N - 1 of them sat idle for that long at the start of every run.
`generate` holds the validated spaces already: a thread of it computes their curvature into the workers'
shared folder while they import and load their scenes, and a worker then reads the file. With one worker there
is nothing to overlap: that worker computes it as before, and `generate` does not import the compiled kernels.

The file is named by a digest of the mesh arrays (services.worker.inputs.shared_curvature): the thread works
on a mesh built from the same arrays the workers rebuild from the run's loaded-space cache, so a worker finds
it (in the user's curvature cache, which a later run on the same scan reads too); were the digests ever to
differ, the worker would compute its own, as without this.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from pathlib import Path

import trimesh

from services.core.domain.cues import OUTPUT_CUES, closure
from services.core.domain.jobspec import JobSpec

log = logging.getLogger(__name__)

# The cues whose render reads the curvature pass (the worker registry's passes={"curvature"}; a test keeps
# them equal).
CURVATURE_CUES = frozenset({"principal_curvature"})


def needs_curvature(spec: JobSpec) -> bool:
    """Whether the job's renders read the curvature pass (its cues, or what they are made from)."""
    return bool(CURVATURE_CUES.intersection(closure(spec.cues if spec.cues is not None else OUTPUT_CUES)))


def curvature_ahead(meshes: Iterable[trimesh.Trimesh], spec: JobSpec, folder: Path,
                    workers: int) -> threading.Thread | None:
    """Start computing the curvature of `meshes` (the loaded spaces, world frame) into `folder` (the workers'
    curvature folder) on a thread, when `workers` > 1 and the job needs it; the thread (join it before
    exiting), else None."""
    meshes = list(meshes)
    if workers < 2 or not meshes or not needs_curvature(spec):
        return None
    radius = spec.params.curvature_radius_m
    # A mesh of its own (the same arrays, no copy): trimesh's caches are not shared with the planner's thread.
    own = [trimesh.Trimesh(vertices=m.vertices, faces=m.faces, process=False, validate=False) for m in meshes]

    def compute() -> None:
        from services.worker.inputs.shared_curvature import shared_curvature

        for mesh in own:
            try:
                shared_curvature(mesh, radius, folder)
            except Exception:  # the workers compute it themselves
                log.warning("curvature ahead of the workers failed", exc_info=True)

    thread = threading.Thread(target=compute, name="curvature-ahead", daemon=True)
    thread.start()
    return thread
