"""Compile every kernel of the worker into numba's on-disk cache ahead of the first job (`omnidata
compile-kernels`).

A worker compiles its ~70 kernels (services.worker.cues, curvature, the pass decode) the first time it uses
them, into numba's cache: ~40 CPU-s before its first view, in every process that finds the cache cold, at
once. That is every new worker pod of an image (its cache is the container's), and `generate` on a fresh
install with all of its workers compiling the same kernels side by side. Compiled once when the image is built
(or by `make venv`) for the x86-64 levels of kernel_target, every later process on a machine of such a level
only loads them.

The warm-up runs the worker's own code on a small synthetic room, so each kernel is compiled with the argument
types a job passes (numba keys cached code by them, read-only and non-contiguous arrays included): one view
rendered by Cycles with every pass and read back as a worker reads it, every cue a space without labels or
photos can give derived and encoded from it, and the curvature estimator on both of its search paths.
"""

from __future__ import annotations

import importlib
import pkgutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

import services.worker
from services.core.domain.camera import look_at
from services.core.domain.cues import CATALOG
from services.core.domain.jobspec import CueParams

# types, not sizes, pick a kernel's compiled version; keypoints3d's wide scales need this many px
RESOLUTION = 128
ROOM_M = (4.0, 3.0, 2.6)
PHOTO_CUES = ("mask_photo",)  # needs rgb from photos (JobSpec.uses_photos); numpy only, no kernel


@dataclass(frozen=True)
class WarmUpReport:
    kernels: int  # compiled functions of the worker's modules
    # their versions in the cache for this CPU target (a kernel called with other types has several)
    versions: int
    missed: tuple[str, ...]  # kernels with none (module.name): a job would compile them
    seconds: float


def warm_up_cues() -> list[str]:
    """The cues a view of a space without labels, photos or a plan gives: every one with a kernel behind
    it."""
    return [c.name for c in CATALOG.values() if c.source != "plan" and not c.needs_semantics
            and "point_info" not in c.inputs and c.name not in PHOTO_CUES]


def synthetic_room(rng: np.random.Generator) -> trimesh.Trimesh:
    """A box room (normals inward) with a window (pixels with no surface: the segmentations' background fill)
    holding a table-sized box and a sphere, with random vertex colours (so the colour segmentation does not
    take its one-colour shortcut), in metres, +Z up."""
    room = trimesh.creation.box(extents=ROOM_M).subdivide().subdivide()
    room.invert()
    c = room.triangles_center
    window = (c[:, 0] < -ROOM_M[0] / 2 + 1e-6) & (np.abs(c[:, 1]) < 0.8) & (np.abs(c[:, 2]) < 0.7)
    room.update_faces(~window)
    table = trimesh.creation.box(extents=(1.2, 0.8, 0.75))
    table.apply_translation((0.6, 0.3, -ROOM_M[2] / 2 + 0.375))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    ball.apply_translation((-0.8, -0.5, -ROOM_M[2] / 2 + 0.3))
    mesh = trimesh.util.concatenate([room, table, ball])
    mesh.apply_translation(np.array(ROOM_M) / 2)  # floor at z = 0
    mesh.visual.vertex_colors = rng.integers(0, 256, (len(mesh.vertices), 4), dtype=np.uint8)
    mesh.visual.vertex_colors[:, 3] = 255
    return mesh


def compile_kernels(resolution: int = RESOLUTION) -> WarmUpReport:
    """Run every kernel of the worker once with a job's argument types (compiling into numba's cache those it
    does not find there); the report says which kernels it reached."""
    from services.core.ingest.loading import load_space
    from services.worker.executor import make_context, produce
    from services.worker.inputs.curvature import principal_curvatures
    from services.worker.inputs.space_cache import SpaceContext
    from services.worker.passes import ViewGeometry

    t0 = time.perf_counter()
    params = CueParams()
    with tempfile.TemporaryDirectory(prefix="omnidata-kernels-") as tmp:
        path = Path(tmp) / "room.ply"
        synthetic_room(np.random.default_rng(0)).export(path)
        loaded = load_space(path, up_axis="+z", unit_scale=1.0)
        space = SpaceContext.from_loaded(loaded, key="kernel-warm-up")
        try:
            # From a corner, so the view holds walls, the table, the ball and a crease of every orientation.
            view = ViewGeometry(
                look_at(np.array([3.6, 2.6, 1.6]), np.array([1.0, 0.8, 0.5])), np.radians(90.0), resolution
            )
            cues = warm_up_cues()
            ctx = make_context(space, view, cues, params)
            for cue in cues:
                produce(cue, ctx)
        finally:
            space.close()
    # Dense meshes (more vertices than surface samples) take the curvature's k-d tree search, not its grid.
    principal_curvatures(trimesh.creation.icosphere(subdivisions=5, radius=0.2), params.curvature_radius_m)
    versions = {name: cached_versions(k) for name, k in worker_kernels().items()}
    return WarmUpReport(kernels=len(versions), versions=sum(versions.values()),
                        missed=tuple(sorted(name for name, n in versions.items() if n == 0)),
                        seconds=time.perf_counter() - t0)


def cached_versions(kernel: object) -> int:
    """How many compiled versions of `kernel` numba's cache holds for this process's CPU target, fresh for its
    source. From the cache's index (numba's own structure: {(signature, codegen magic tuple, code hashes):
    file}): a kernel only ever called from other kernels is compiled into them when they load from the cache,
    so its own dispatcher shows no signature then, though the cache has it."""
    from numba.core.registry import cpu_target

    magic = cpu_target.target_context.codegen().magic_tuple()
    index = kernel._cache._cache_file._load_index()  # type: ignore[attr-defined]  # {} when stale or absent
    return sum(1 for key in index if key[1] == magic)


def worker_kernels() -> dict[str, object]:
    """module.name -> numba dispatcher of every compiled function defined in the worker's modules (all
    imported here), those inlined into their callers left out."""
    from numba.core.dispatcher import Dispatcher

    found: dict[str, object] = {}
    for info in pkgutil.walk_packages(services.worker.__path__, prefix="services.worker."):
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if (
                isinstance(obj, Dispatcher)
                and obj.py_func.__module__ == module.__name__
                and obj.targetoptions.get("inline") != "always"
            ):  # inlined: compiled inside its callers only
                found[f"{module.__name__}.{name}"] = obj
    return found
