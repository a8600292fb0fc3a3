"""Keep the current space (mesh, labels, curvature, Blender scene) loaded between tasks; free it on change.

A worker process renders one space at a time: SpaceCache.get(key, loader) returns the loaded SpaceContext when
the key matches, else closes the old one (Blender scene reset, arrays dropped) and loads the new one. The RSS
helpers let the worker recycle itself (exit and be restarted) before memory grows without bound: Blender does
not always hand freed memory back to the OS.
"""

from __future__ import annotations

import gc
import logging
import os
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from services.core.domain.jobspec import CueParams
from services.worker.inputs.shared_curvature import shared_curvature
from services.worker.passes import RENDER_PASSES, ViewGeometry, ViewPasses

if TYPE_CHECKING:
    from services.core.ingest.loading import LoadedSpace
    from services.worker.blender.scene import BlenderScene
    from services.worker.inputs.loaded_cache import CachedSpace
    from services.worker.inputs.photos import PhotoPainter

log = logging.getLogger(__name__)


@dataclass
class SpaceContext:
    """One space ready to render: the world-frame mesh (metres, +Z up, the planner's face order) and its
    labels.

    The Blender scene and the per-vertex curvature are built lazily on first need and kept until close().
    """

    key: str
    mesh: trimesh.Trimesh
    face_class: np.ndarray | None = None
    face_instance: np.ndarray | None = None
    device: str = "cpu"
    threads: int | None = None
    stats: dict[str, float] = field(default_factory=dict)
    photos: PhotoPainter | None = None  # when rgb comes from a capture's photos
    # where this machine's processes share computed curvature (None: not shared)
    curvature_dir: Path | None = None
    _curvature: dict[float, np.ndarray] = field(default_factory=dict, repr=False)
    _scene: BlenderScene | None = field(default=None, repr=False)
    _scene_curvature_radius: float | None = field(default=None, repr=False)

    @classmethod
    def from_loaded(cls, loaded: LoadedSpace | CachedSpace, *, key: str | None = None, device: str = "cpu",
                    threads: int | None = None) -> SpaceContext:
        """Wrap a services.core.ingest.loading.LoadedSpace (mesh in the world frame, optional per-face
        labels), or the same read back from the run's cache (services.worker.inputs.loaded_cache)."""
        fc = getattr(loaded, "face_class", None)
        fi = getattr(loaded, "face_instance", None)
        if fc is not None and fi is None:  # class-only labels: every face its own "stuff" instance 0
            fi = np.zeros_like(fc)
        if fi is not None and fc is None:
            fc = np.zeros_like(fi)
        return cls(key=key or str(getattr(loaded, "checksum", id(loaded))), mesh=loaded.mesh, face_class=fc,
                   face_instance=fi, device=device, threads=threads)

    @property
    def has_semantics(self) -> bool:
        """True when per-face class/instance ids exist."""
        return self.face_class is not None and self.face_instance is not None

    def curvature(self, radius_m: float) -> np.ndarray:
        """Per-vertex (k1, k2) in 1/m for a fitting radius in metres, computed once per radius."""
        r = float(radius_m)
        if r not in self._curvature:
            t0 = time.perf_counter()
            self._curvature[r] = shared_curvature(self.mesh, r, self.curvature_dir)
            self.stats["curvature_s"] = time.perf_counter() - t0
            log.info(
                "space %s: curvature (r=%.3g m) of %d vertices in %.2f s (computed or shared)", self.key, r,
                len(self.mesh.vertices), self.stats["curvature_s"],
            )
        return self._curvature[r]

    def scene(self) -> BlenderScene:
        """The Blender scene of this space (built on first use; this is the only place that loads bpy)."""
        if self._scene is None or self._scene.closed:
            from services.worker.blender.threads import import_bpy

            # before the first `import bpy`: size Blender's thread pool to the budget
            import_bpy(self.threads)
            from services.worker.blender.render import RenderOptions
            from services.worker.blender.scene import BlenderScene

            self._scene = BlenderScene(
                self.mesh, face_class=self.face_class, face_instance=self.face_instance,
                options=RenderOptions(device=self.device, threads=self.threads),  # type: ignore[arg-type]
            )
            self._scene_curvature_radius = None
            self.stats["scene_build_s"] = self._scene.build_s
        return self._scene

    def render(self, view: ViewGeometry, params: CueParams, *,
               passes: frozenset[str] = RENDER_PASSES) -> ViewPasses:
        """One render of `view` with colour, depth and the optional `passes` (the space's curvature only when
        "curvature" is among them)."""
        scene = self.scene()
        if "curvature" in passes and self._scene_curvature_radius != params.curvature_radius_m:
            scene.set_curvature(self.curvature(params.curvature_radius_m))
            self._scene_curvature_radius = params.curvature_radius_m
        out = scene.render(view, passes)
        return self.photos.paint(view, out) if self.photos is not None else out

    def close(self) -> None:
        """Free the Blender scene and cached arrays."""
        if self._scene is not None:
            self._scene.close()
            self._scene = None
        self._curvature.clear()


class SpaceCache:
    """Holds at most one SpaceContext; loading another space frees the previous one first."""

    def __init__(self) -> None:
        self.current: SpaceContext | None = None
        self.loads = 0

    def get(self, key: str, loader: Callable[[], SpaceContext]) -> SpaceContext:
        """The SpaceContext for `key`, loading it with `loader()` (and freeing the previous space) if
        needed."""
        if self.current is not None and self.current.key == key:
            return self.current
        self.clear()
        ctx = loader()
        if ctx.key != key:
            ctx.key = key
        self.current = ctx
        self.loads += 1
        return ctx

    def clear(self) -> None:
        """Free the current space."""
        if self.current is not None:
            log.info("freeing space %s", self.current.key)
            self.current.close()
            self.current = None
            gc.collect()


def rss_bytes() -> int:
    """Current resident set size of this process in bytes (Linux /proc; falls back to the peak)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return peak_rss_bytes()


def peak_rss_bytes() -> int:
    """Peak resident set size of this process in bytes."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def should_recycle(max_rss_mb: int) -> bool:
    """True when this process's RSS exceeds max_rss_mb: finish the task, then exit so a fresh worker
    starts."""
    return rss_bytes() > max_rss_mb * 1024 * 1024
