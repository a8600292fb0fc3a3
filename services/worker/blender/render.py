"""Cycles set-up and the one render per view: every pass copied out of the render result in memory
(readback.py), or, where configure_scene is not told `memory`, written to a multilayer float32 EXR and read
back.

Camera: Blender's camera looks down its local -Z with +Y up; from an OpenCV world_to_camera W (metres),
matrix_world = inverse(W) @ diag(1, -1, -1, 1) (services.core.domain.camera.blender_matrix_world). sensor_fit
HORIZONTAL and `angle` = the horizontal fov (radians) give f = (W/2)/tan(fov/2) pixels; square images, zero
shift, so the principal point is the image centre and pixel (u, v) is sampled at its centre (u + 0.5, v +
0.5): one sample per pixel with a 0.01 px box filter, fixed seed, no denoising, 0 light bounces.

Passes read back (linear float32, row 0 = top):
- Combined: the emission shader = unlit colour (scene-linear; sRGB-encoded here so that 8-bit output
  reproduces the texture's 8-bit values: the same as view transform Standard, look None, exposure 0, gamma 1,
  display sRGB);
- Depth: Cycles' Z pass is the distance along the camera's optical axis (planar z), 1e10 where nothing is hit;
- normals are not rendered: faces are flat-shaded, so Cycles' Normal pass is the seen triangle's geometric
  normal, turned towards the incoming ray for back-facing hits; the decode gives that from the face index, to
  float32 rounding and the same on every device (decode.facing_normals; the pass cost 3 EXR channels and 4-7%
  of the passes task's CPU: README, round 13's A/B);
- AOVs (float32, exact integers below 2^24): face index + 1 in one AOV when the mesh has fewer than 2^24
  faces, else split into two 16-bit halves (exact for any mesh below 2^32 - 1 faces, so no ray-cast fallback
  is needed), curvature k1 and k2 (per-vertex values interpolated barycentrically over the triangle). Class
  and instance ids are per face: looked up from the face index (the same values the class/instance AOVs give,
  which the material still offers; each AOV costs render time and EXR channels, see
  bench/results/passes_cost.json).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import bpy
import numpy as np
from mathutils import Matrix

from services.core.domain.camera import blender_matrix_world
from services.core.gpu_devices import nvidia_gpus
from services.worker.blender import readback
from services.worker.blender.calls import in_blender
from services.worker.blender.decode import (  # srgb_encode: the reference formula, imported from here before
    curvature_pair,
    faces_hit,
    facing_normals,
    srgb_encode,  # noqa: F401
    srgb_masked,
)
from services.worker.blender.exr import read_channels
from services.worker.passes import NO_FACE, NO_LABEL, RENDER_PASSES, ViewGeometry, ViewPasses

log = logging.getLogger(__name__)

Device = Literal["auto", "cpu", "cuda", "optix"]
DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda", "optix")

# AOV names (view-layer passes) filled by the material in scene.py.
AOV_FACE = "omni_face"
AOV_FACE_HI = "omni_face_hi"
AOV_FACE_LO = "omni_face_lo"
AOV_CLASS = "omni_class"
AOV_INSTANCE = "omni_instance"
AOV_K1 = "omni_k1"
AOV_K2 = "omni_k2"
# what the material writes
AOVS = (AOV_FACE, AOV_FACE_HI, AOV_FACE_LO, AOV_CLASS, AOV_INSTANCE, AOV_K1, AOV_K2)
EXACT_FACES = 2**24 - 1  # face index + 1 is an exact float32 integer up to 2^24: one AOV holds it


def pass_aovs(faces: int) -> tuple[str, ...]:
    """The AOVs a pass render of a mesh with `faces` faces needs (class and instance come from the face
    index)."""
    return ((AOV_FACE,) if faces <= EXACT_FACES else (AOV_FACE_HI, AOV_FACE_LO)) + (AOV_K1, AOV_K2)

_MEMORY_READBACK = "omnidata_memory_readback"  # scene property: configure_scene's choice of readback
CLIP_START_M = 1e-4
CLIP_END_M = 1e6
_MISS_DEPTH = 1e9  # Cycles writes 1e10 where a ray hits nothing


@dataclass(frozen=True)
class RenderOptions:
    """How to run Cycles: device ("auto" tries OptiX then CUDA, else CPU) and CPU threads (None: this
    process's CPU affinity, so `taskset -c 0` gives one thread)."""

    device: Device = "cpu"
    threads: int | None = None

    def __post_init__(self) -> None:
        if self.device not in DEVICES:
            raise ValueError(f"render device {self.device!r} is not one of {', '.join(DEVICES)}")


def configure_device(scene: bpy.types.Scene, device: str) -> str:
    """Select the Cycles device; returns the one in use ("cpu", "cuda" or "optix"), falling back to the
    CPU."""
    scene.cycles.device = "CPU"
    if device == "cpu":
        return "cpu"
    prefs = bpy.context.preferences.addons["cycles"].preferences
    kinds = ["OPTIX", "CUDA"] if device == "auto" else [device.upper()]
    for kind in kinds:
        try:
            prefs.compute_device_type = kind
            prefs.refresh_devices()
        except (TypeError, ValueError, RuntimeError):  # backend not compiled into this bpy build
            continue
        gpus = [d for d in prefs.devices if d.type == kind]
        if gpus:
            for d in prefs.devices:
                d.use = d.type == kind
            scene.cycles.device = "GPU"
            log.info("Cycles renders on %s: %s", kind, ", ".join(d.name for d in gpus))
            return kind.lower()
    prefs.compute_device_type = "NONE"
    # "auto" on a machine without a GPU is the expected CPU render; with one (whose presence also made
    # `generate` give fewer workers the renders) it is a driver Cycles cannot use, and worth a warning.
    present = nvidia_gpus()
    level = logging.INFO if device == "auto" and not present else logging.WARNING
    log.log(level, "render device %r requested but no %s device found%s: rendering on the CPU", device,
            "/".join(kinds), f" (an NVIDIA GPU is present: {', '.join(present)})" if present else "")
    return "cpu"


def configure_scene(scene: bpy.types.Scene, options: RenderOptions, output_path: str,
                    aovs: tuple[str, ...] = AOVS, *, memory: bool = False) -> str:
    """Cycles settings for pixel-centre, noise-free pass rendering with the AOVs `aovs`; returns the device in
    use. render_passes reads the passes from memory with `memory` (readback.py), else from a multilayer EXR
    written to `output_path` (where the Cycles engine cannot be wrapped)."""
    _configure_cycles(scene, options)
    if memory and not readback.install():
        raise RuntimeError("the Cycles engine cannot be wrapped to read passes from memory")
    scene[_MEMORY_READBACK] = memory
    r = scene.render
    r.use_file_extension = False
    r.filepath = output_path
    im = r.image_settings
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"  # float: the index AOVs must stay exact
    im.exr_codec = "NONE"  # the file lives for milliseconds in a temp dir: do not spend time compressing
    # The AOVs stay the same for every view: Cycles' persistent session compiles its shaders for the AOVs
    # present at the first render and writes zeros into AOVs added later. A view's cues choose what is read
    # back.
    layer = scene.view_layers[0]
    layer.use_pass_normal = False  # derived from the face index (module docstring)
    for name in aovs:
        if name not in [a.name for a in layer.aovs]:
            aov = layer.aovs.add()
            aov.name = name
            aov.type = "VALUE"
    return configure_device(scene, options.device)


def configure_floor_scene(scene: bpy.types.Scene, options: RenderOptions) -> str:
    """The same Cycles settings with Image, Depth and Normal passes (no AOVs): the bare render of the
    benchmarks."""
    _configure_cycles(scene, options)
    return configure_device(scene, options.device)


def _configure_cycles(scene: bpy.types.Scene, options: RenderOptions) -> None:
    """Engine, sampling, threads, colour management and the Combined, Depth and Normal passes."""
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.samples = 1
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    cy.seed = 0
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 0.01
    for attr in ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces",
                 "volume_bounces", "transparent_max_bounces"):
        setattr(cy, attr, 0)
    cy.caustics_reflective = False
    cy.caustics_refractive = False
    cy.use_auto_tile = False
    r = scene.render
    r.use_persistent_data = True  # keep the BVH and textures between the views of a space
    r.film_transparent = True
    r.use_compositing = False
    r.use_sequencer = False
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.threads_mode = "FIXED"
    r.threads = options.threads or len(os.sched_getaffinity(0))
    vs = scene.view_settings
    for attr, value in (("view_transform", "Standard"), ("look", "None")):
        try:
            setattr(vs, attr, value)
        except TypeError:  # some bpy builds ship a reduced OCIO config; we encode sRGB ourselves anyway
            log.debug("view setting %s=%s unavailable", attr, value)
    vs.exposure = 0.0
    vs.gamma = 1.0
    with contextlib.suppress(TypeError):
        scene.display_settings.display_device = "sRGB"
    layer = scene.view_layers[0]
    layer.use_pass_combined = True
    layer.use_pass_z = True
    layer.use_pass_normal = True


def set_camera(scene: bpy.types.Scene, cam: bpy.types.Object, g: ViewGeometry) -> None:
    """Pose the camera from an OpenCV world_to_camera and a horizontal fov (radians); square resolution."""
    cam.matrix_world = Matrix(blender_matrix_world(g.world_to_camera).tolist())
    data = cam.data
    data.type = "PERSP"
    data.sensor_fit = "HORIZONTAL"
    data.lens_unit = "FOV"
    data.angle = float(g.fov)
    data.shift_x = data.shift_y = 0.0
    data.clip_start = CLIP_START_M
    data.clip_end = CLIP_END_M
    scene.render.resolution_x = scene.render.resolution_y = int(g.resolution)


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence Blender's per-render progress lines (C-level stdout) so worker logs stay readable."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # stdout replaced by something without a descriptor
        yield
        return
    sys.stdout.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def render_floor(scene: bpy.types.Scene, cam: bpy.types.Object, g: ViewGeometry) -> float:
    """Seconds of one render of `scene` from view `g`, nothing written (the bare-render floor of the
    benchmarks)."""
    set_camera(scene, cam, g)
    t0 = time.perf_counter()
    with in_blender(), _quiet_stdout():
        bpy.ops.render.render(write_still=False, scene=scene.name)
    return time.perf_counter() - t0


def render_passes(scene: bpy.types.Scene, cam: bpy.types.Object, g: ViewGeometry,
                  passes: frozenset[str] = RENDER_PASSES, labels: tuple[np.ndarray, np.ndarray] | None = None,
                  face_normals: np.ndarray | None = None) -> ViewPasses:
    """Render one view and read back colour, depth and the optional `passes` (module docstring: frames,
    units).

    "curvature" needs the scene's curvature attribute, "labels" its label attribute (class and instance AOVs)
    or `labels`: int32 class and instance ids per face, read at the face index; "normal" needs `face_normals`,
    the mesh's decode.unit_face_normals (BlenderScene checks and gives them).
    """
    if "normal" in passes and face_normals is None:
        raise ValueError("the normal pass is derived from the face index: render_passes needs face_normals")
    set_camera(scene, cam, g)
    t0 = time.perf_counter()
    if scene.get(_MEMORY_READBACK):
        with in_blender(), _quiet_stdout(), readback.capture() as channels:
            bpy.ops.render.render(write_still=False, scene=scene.name)
        if not channels:
            raise RuntimeError("the render left no passes to read (was it not Cycles?)")
        t1 = t2 = time.perf_counter()  # the copy out of the render result is part of the render call
    else:
        with in_blender(), _quiet_stdout():
            bpy.ops.render.render(write_still=True, scene=scene.name)
        t1 = time.perf_counter()
        channels = read_channels(scene.render.filepath) or _read_openexr(scene.render.filepath)
        t2 = time.perf_counter()
    out = _decode(channels, scene.view_layers[0].name, g, passes, labels, face_normals)
    out.meta.update(render_call_s=t1 - t0, exr_read_s=t2 - t1, decode_s=time.perf_counter() - t2)
    return out


def _read_openexr(path: str) -> dict[str, np.ndarray]:
    """Channel name -> H x W array with the OpenEXR module (RGBA layers come as one H x W x 4 array:
    split)."""
    import OpenEXR  # the fallback of read_channels only: not loaded otherwise

    out = {}
    for name, ch in OpenEXR.File(path).parts[0].channels.items():
        px = ch.pixels
        out.update({f"{name}.{c}": px[..., i] for i, c in enumerate("RGBA"[:px.shape[-1]])} if px.ndim == 3
                   else {name: px})
    return out


def _decode(channels: dict[str, np.ndarray], layer: str, g: ViewGeometry, passes: frozenset[str],
            labels: tuple[np.ndarray, np.ndarray] | None, face_normals: np.ndarray | None) -> ViewPasses:
    """The pass set from the EXR's channels (`layer`.<pass>[.<channel>])."""
    def ch(name: str) -> np.ndarray:
        return channels[f"{layer}.{name}"]

    def aov(name: str) -> np.ndarray:
        key = f"{layer}.{name}"
        return channels[key] if key in channels else channels[f"{key}.X"]  # value AOVs come as one channel

    def has(name: str) -> bool:
        return f"{layer}.{name}" in channels or f"{layer}.{name}.X" in channels

    depth = ch("Depth.Z") if f"{layer}.Depth.Z" in channels else ch("Depth")
    face_index = None
    if "faces" in passes or "normal" in passes or ("labels" in passes and not has(AOV_CLASS)):
        if has(AOV_FACE):
            face1 = aov(AOV_FACE)  # face index + 1 (exact float32 integers)
        else:
            face1 = aov(AOV_FACE_HI).astype(np.int64) * 65536 + aov(AOV_FACE_LO).astype(np.int64)
        hit, face_index, depth_z = faces_hit(depth, face1, _MISS_DEPTH, int(NO_FACE))
    else:
        hit = depth < _MISS_DEPTH
        depth_z = np.where(hit, depth, np.inf).astype(np.float32)
    normal = None
    if "normal" in passes:
        assert face_index is not None and face_normals is not None  # read above; render_passes checked
        K = g.K
        normal = facing_normals(
            face_index, hit, face_normals, np.ascontiguousarray(g.rotation, dtype=np.float64), float(K[0, 0]),
            float(K[0, 2]), float(K[1, 2]),
        )
    rgb = srgb_masked(ch("Combined.R"), ch("Combined.G"), ch("Combined.B"), hit)
    out = ViewPasses(geometry=g, depth_z=depth_z, normal_world=normal, rgb=rgb,
                     face_index=face_index if "faces" in passes else None)
    if "labels" in passes and has(AOV_CLASS):
        out.face_class = np.where(hit, np.rint(aov(AOV_CLASS)), NO_LABEL).astype(np.int32)
        out.face_instance = np.where(hit, np.rint(aov(AOV_INSTANCE)), NO_LABEL).astype(np.int32)
    elif "labels" in passes and labels is not None and face_index is not None:
        out.face_class, out.face_instance = (np.where(hit, lut[np.where(hit, face_index, 0)], NO_LABEL)
                                             for lut in labels)
    if "curvature" in passes:
        out.curvature = curvature_pair(aov(AOV_K1), aov(AOV_K2), hit)
    return out
