"""The Blender scene of one space, built from trimesh arrays (never re-imported with Blender's importers).

The mesh is given in the world frame (metres, +Z up) with the planner's vertex and face order; it is copied
into one Blender mesh with foreach_set, so Blender face i is trimesh face i and world coordinates are
identical (the triangle index pass is exact). Colour, in order of preference: the texture image of
mesh.visual.material (UVs per vertex), vertex or face colours, the material's main colour, else a constant
grey (sRGB 128).

bpy holds one scene per process: building a BlenderScene resets Blender (factory settings, empty), and close()
resets it again so the mesh, textures and Cycles' persistent data are freed when the space changes.
"""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
import time
from typing import Any

import bpy
import numpy as np
import trimesh
from PIL import Image

from services.core.temp_dirs import owned_prefix, sweep_orphans
from services.worker.blender import readback
from services.worker.blender.decode import unit_face_normals
from services.worker.blender.render import (
    AOV_CLASS,
    AOV_FACE,
    AOV_FACE_HI,
    AOV_FACE_LO,
    AOV_INSTANCE,
    AOV_K1,
    AOV_K2,
    RenderOptions,
    configure_floor_scene,
    configure_scene,
    pass_aovs,
    render_floor,
    render_passes,
)
from services.worker.passes import RENDER_PASSES, ViewGeometry, ViewPasses

log = logging.getLogger(__name__)

ATTR_FACE = "omni_face"  # FACE domain float3: ((i+1) // 65536, (i+1) % 65536, i+1), the last exact below 2^24
ATTR_LABEL = "omni_label"  # FACE domain float3: (class, instance, 0)
ATTR_CURV = "omni_curv"  # POINT domain float3: (k1, k2, 0)
ATTR_COLOR = "omni_color"  # POINT or FACE domain float colour, scene-linear
GREY_SRGB = 128
MAX_FACES = 2**32 - 2  # the face index pass holds i + 1 in two exact 16-bit halves; uint32 max means "none"

_active: BlenderScene | None = None


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """8-bit sRGB values (0..255) -> scene-linear floats (IEC 61966-2-1)."""
    x = np.asarray(c, dtype=np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _temp_root() -> str | None:
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


class BlenderScene:
    """The loaded space in Blender plus a camera; render(view) gives its ViewPasses."""

    def __init__(self, mesh: trimesh.Trimesh, *, face_class: np.ndarray | None = None,
                 face_instance: np.ndarray | None = None, options: RenderOptions | None = None):
        global _active
        if _active is not None and not _active.closed:
            _active.close()
        t0 = time.perf_counter()
        self.options = options or RenderOptions()
        self.closed: bool = False
        self._textured: bool = False
        self.renders = 0
        self._floor: bpy.types.Scene | None = None
        self.has_curvature = False
        self.labelled = face_class is not None or face_instance is not None
        self.labels: tuple[np.ndarray, np.ndarray] | None = None  # int32 class, instance per face (labelled)
        # folders of workers killed mid-render (kill -9 skips atexit)
        sweep_orphans(("render", "exr"), (_temp_root(),))
        self._tmp = tempfile.mkdtemp(prefix=owned_prefix("render"), dir=_temp_root())
        atexit.register(shutil.rmtree, self._tmp, True)  # also when the process dies without close()
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self.mesh_data = self._build_mesh(mesh, face_class, face_instance)
        self.object = bpy.data.objects.new("space", self.mesh_data)
        self.scene.collection.objects.link(self.object)
        self.mesh_data.materials.append(self._build_material(mesh))
        cam_data = bpy.data.cameras.new("camera")
        self.camera = bpy.data.objects.new("camera", cam_data)
        self.scene.collection.objects.link(self.camera)
        self.scene.camera = self.camera
        # passes read from memory; an EXR only where Cycles' engine cannot be wrapped (render.configure_scene)
        self.device = configure_scene(self.scene, self.options, os.path.join(self._tmp, "passes.exr"),
                                      pass_aovs(len(mesh.faces)), memory=readback.install())
        self.build_s = time.perf_counter() - t0
        _active = self
        log.info("Blender scene: %d faces, textured=%s, labelled=%s, device=%s, built in %.2f s",
                 len(mesh.faces), self._textured, self.labelled, self.device, self.build_s)

    # ----------------------------------------------------------------------------------------------- build
    def _build_mesh(self, mesh: trimesh.Trimesh, face_class: np.ndarray | None,
                    face_instance: np.ndarray | None) -> bpy.types.Mesh:
        verts = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
        nf = len(faces)
        if nf > MAX_FACES:
            raise ValueError(f"mesh has {nf} faces; the face index pass supports at most {MAX_FACES}")
        self.face_normals = unit_face_normals(verts, faces)  # of the vertices Cycles renders (float32)
        me = bpy.data.meshes.new("space")
        me.vertices.add(len(verts))
        me.vertices.foreach_set("co", verts.ravel())
        me.loops.add(faces.size)
        me.loops.foreach_set("vertex_index", faces.ravel())
        me.polygons.add(nf)
        me.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
        # No me.validate(): it may drop degenerate faces and shift every later face index.
        me.update(calc_edges=True)
        # Flat shading: a pixel's normal is its triangle's geometric normal, faithful to the scanned mesh (and
        # derived from the face index: decode.facing_normals).
        me.polygons.foreach_set("use_smooth", np.zeros(nf, dtype=bool))
        idx1 = np.arange(1, nf + 1, dtype=np.int64)
        self._set_attr(me, ATTR_FACE, "FACE", np.stack([idx1 // 65536, idx1 % 65536, idx1], axis=1))
        if self.labelled:
            cls = self._labels(face_class, nf, "face_class")
            inst = self._labels(face_instance, nf, "face_instance")
            self._set_attr(me, ATTR_LABEL, "FACE", np.stack([cls, inst, np.zeros(nf)], axis=1))
            # What the class and instance AOVs give at a pixel: the float32 attribute, rounded.
            self.labels = (
                cls.astype(np.float32).round().astype(np.int32),
                inst.astype(np.float32).round().astype(np.int32),
            )
        visual: Any = mesh.visual
        uv = getattr(visual, "uv", None)
        if self._texture_image(mesh) is not None and uv is not None and len(uv) == len(verts):
            layer = me.uv_layers.new(name="UVMap")
            layer.data.foreach_set("uv", np.asarray(uv, dtype=np.float32)[faces].ravel())
            self._textured = True
        elif getattr(visual, "kind", None) in ("vertex", "face"):
            # Colour attributes live on points or face corners; face colours become equal colours on the
            # three corners of each face.
            if visual.kind == "vertex":
                domain, rgba = "POINT", np.asarray(visual.vertex_colors)
            else:
                domain, rgba = "CORNER", np.repeat(np.asarray(visual.face_colors), 3, axis=0)
            lin = np.concatenate([srgb_to_linear(rgba[:, :3]), np.ones((len(rgba), 1))], axis=1)
            attr = me.color_attributes.new(ATTR_COLOR, "FLOAT_COLOR", domain)
            attr.data.foreach_set("color", lin.astype(np.float32).ravel())
        me.update()
        return me

    @staticmethod
    def _labels(values: np.ndarray | None, nf: int, name: str) -> np.ndarray:
        """Per-face ids as floats for the AOVs (exact below 2^24); range checks belong to the cues'
        encodings."""
        if values is None:
            return np.zeros(nf)
        v = np.asarray(values).reshape(-1)
        if len(v) != nf:
            raise ValueError(f"{name} has {len(v)} entries for {nf} faces")
        if len(v) and np.abs(v).max() >= 2**24:
            raise ValueError(f"{name} ids must lie within +-2^24 to pass through the renderer exactly")
        return v.astype(np.float64)

    @staticmethod
    def _set_attr(me: bpy.types.Mesh, name: str, domain: str, values: np.ndarray) -> None:
        attr = me.attributes.get(name) or me.attributes.new(name, "FLOAT_VECTOR", domain)
        attr.data.foreach_set("vector", np.ascontiguousarray(values, dtype=np.float32).ravel())

    @staticmethod
    def _texture_image(mesh: trimesh.Trimesh) -> Image.Image | None:
        mat = getattr(mesh.visual, "material", None)
        if mat is None:
            return None
        img = getattr(mat, "image", None)
        if img is None:
            img = getattr(mat, "baseColorTexture", None)
        return img if isinstance(img, Image.Image) else None

    @staticmethod
    def _base_color_factor(mesh: trimesh.Trimesh) -> np.ndarray | None:
        """A glTF material's linear RGB baseColorFactor when it is not white, else None."""
        factor = getattr(getattr(mesh.visual, "material", None), "baseColorFactor", None)
        if factor is None:
            return None
        a = np.asarray(factor)
        f = a[:3].astype(np.float64) / (255.0 if a.dtype == np.uint8 else 1.0)
        return None if np.allclose(f, 1.0) else f

    def _build_material(self, mesh: trimesh.Trimesh) -> bpy.types.Material:
        mat = bpy.data.materials.new("space")
        # No light source: the camera sees the emission directly (no bounces). Cycles' automatic emission
        # sampling evaluated the shader on every coloured or textured triangle at each sync to build its light
        # tree.
        mat.cycles.emission_sampling = "NONE"
        mat.use_nodes = True
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        emit = nt.nodes.new("ShaderNodeEmission")
        emit.inputs["Strength"].default_value = 1.0
        nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
        if self._textured:
            tex = nt.nodes.new("ShaderNodeTexImage")
            image = self._texture_image(mesh)
            assert image is not None  # _textured implies it
            tex.image = self._load_image(image)
            tex.interpolation = "Linear"
            tex.extension = "REPEAT"
            f = self._base_color_factor(mesh)
            if f is not None:  # glTF multiplies the base colour texture by a linear factor
                mul = nt.nodes.new("ShaderNodeVectorMath")
                mul.operation = "MULTIPLY"
                mul.inputs[1].default_value = f.tolist()
                nt.links.new(tex.outputs["Color"], mul.inputs[0])
                nt.links.new(mul.outputs["Vector"], emit.inputs["Color"])
            else:
                nt.links.new(tex.outputs["Color"], emit.inputs["Color"])
        elif ATTR_COLOR in self.mesh_data.color_attributes:
            col = nt.nodes.new("ShaderNodeAttribute")
            col.attribute_type = "GEOMETRY"
            col.attribute_name = ATTR_COLOR
            nt.links.new(col.outputs["Color"], emit.inputs["Color"])
        else:
            srgb = np.full(3, GREY_SRGB)
            main = getattr(getattr(mesh.visual, "material", None), "main_color", None)
            if main is not None and getattr(mesh.visual, "kind", None) == "texture":
                srgb = np.asarray(main)[:3]
            emit.inputs["Color"].default_value = (*srgb_to_linear(srgb).tolist(), 1.0)
        # Every AOV the scene may give; a scene's view layer chooses which are rendered (render.pass_aovs).
        for attr_name, outputs in ((ATTR_FACE, (AOV_FACE_HI, AOV_FACE_LO, AOV_FACE)),
                                   (ATTR_LABEL, (AOV_CLASS, AOV_INSTANCE)), (ATTR_CURV, (AOV_K1, AOV_K2))):
            node = nt.nodes.new("ShaderNodeAttribute")
            node.attribute_type = "GEOMETRY"
            node.attribute_name = attr_name
            sep = nt.nodes.new("ShaderNodeSeparateXYZ")
            nt.links.new(node.outputs["Vector"], sep.inputs["Vector"])
            for axis, aov_name in zip(("X", "Y", "Z"), outputs, strict=False):
                aov = nt.nodes.new("ShaderNodeOutputAOV")
                aov.aov_name = aov_name
                nt.links.new(sep.outputs[axis], aov.inputs["Value"])
        return mat

    def _load_image(self, img: Image.Image) -> bpy.types.Image:
        if img.mode not in ("RGB", "RGBA"):
            img = img.convert("RGBA" if "A" in img.getbands() else "RGB")
        path = os.path.join(self._tmp, "texture.png")
        img.save(path, compress_level=1)
        bimg = bpy.data.images.load(path)
        bimg.colorspace_settings.name = "sRGB"
        bimg.pack()  # keep the pixels inside Blender so the temp file can go now
        os.remove(path)
        return bimg

    # ---------------------------------------------------------------------------------------------- use
    def set_curvature(self, k: np.ndarray) -> None:
        """Store per-vertex principal curvatures (V x 2, 1/m) for the curvature AOVs."""
        self._check_open()
        k = np.asarray(k, dtype=np.float32)
        if k.shape != (len(self.mesh_data.vertices), 2):
            raise ValueError(f"curvature must be V x 2 = {len(self.mesh_data.vertices)} x 2, got {k.shape}")
        self._set_attr(self.mesh_data, ATTR_CURV, "POINT", np.concatenate([k, np.zeros((len(k), 1))], axis=1))
        self.mesh_data.update()
        self.has_curvature = True

    def render(self, view: ViewGeometry, passes: frozenset[str] = RENDER_PASSES) -> ViewPasses:
        """Render one view (one Cycles render): colour, depth and the optional `passes` this scene can
        give."""
        self._check_open()
        t0 = time.perf_counter()
        wanted = set(passes)
        if not self.labelled:
            wanted.discard("labels")
        if not self.has_curvature:
            wanted.discard("curvature")
        out = render_passes(self.scene, self.camera, view, frozenset(wanted), self.labels, self.face_normals)
        out.meta["render_s"] = time.perf_counter() - t0
        self.renders += 1
        return out

    def render_floor(self, view: ViewGeometry) -> float:
        """Seconds of one bare render of `view` (the benchmarks' floor): same mesh, camera, samples and
        threads, Image, Depth and Normal passes only, no AOVs, nothing written or read back. A scene of its
        own, so its Cycles persistent data does not disturb the pass scene's."""
        self._check_open()
        if self._floor is None:
            self._floor = bpy.data.scenes.new("floor")
            self._floor.collection.objects.link(self.object)
            self._floor.collection.objects.link(self.camera)
            self._floor.camera = self.camera
            configure_floor_scene(self._floor, self.options)
        return render_floor(self._floor, self.camera, view)

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("this Blender scene was closed (another space was loaded since)")

    def close(self) -> None:
        """Free the scene: Blender data, textures, Cycles' persistent session and the temp dir."""
        global _active
        if self.closed:
            return
        self.closed = True
        bpy.ops.wm.read_factory_settings(use_empty=True)
        shutil.rmtree(self._tmp, ignore_errors=True)
        if _active is self:
            _active = None
