"""Real Cycles renders (bpy) checked against an independent embree ray cast of the same K / world_to_camera.

One render per scene (module-scoped, small resolutions): a textured scan (ycb_banana), an untextured scan
(stanford_bunny) and a labelled synthetic room with face colours and a sphere of known radius.
OMNIDATA_TEST_RENDER_DEVICE (cpu, cuda, optix; default cpu) renders them on that device: on a GPU machine the
same oracles check the GPU path, and a run that fell back to the CPU fails instead of passing as a GPU check.
"""

from __future__ import annotations

import io
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from services.core.domain.camera import camera_center
from services.core.domain.cues import CATALOG, default_cues
from services.core.domain.jobspec import CueParams
from services.core.domain.plan import CameraPose, PlannedView, PointOfInterest, SpacePlan
from services.core.ingest.loading import load_space
from services.worker.context import SemanticsUnavailableError, ViewContext
from services.worker.cues.encoding import decode_exr_rgb
from services.worker.executor import make_context, produce, render_view_cues
from services.worker.inputs.space_cache import SpaceCache, SpaceContext, rss_bytes
from services.worker.passes import ViewGeometry, ViewPasses
from tests.fixtures.png import png_header
from tests.fixtures.raycast import (
    ROOM_CLASSES,
    SPHERE_RADIUS,
    Cast,
    cast_normals_cam,
    make_room,
    object_view,
    raycast,
    room_view,
    smooth_mask,
)

SCENES = ("banana", "bunny", "room")
RENDER_DEVICE = os.environ.get("OMNIDATA_TEST_RENDER_DEVICE", "cpu")

pytestmark = pytest.mark.bpy  # every test renders with Cycles


@dataclass
class Rendered:
    name: str
    mesh: trimesh.Trimesh
    space: SpaceContext
    view: PlannedView
    geometry: ViewGeometry
    ctx: ViewContext
    files: dict[str, bytes]
    cast: Cast
    renders: int
    face_class: np.ndarray | None = None
    face_instance: np.ndarray | None = None

    def png(self, cue: str) -> np.ndarray:
        return np.array(Image.open(io.BytesIO(self.files[cue])))


def plan_for(name: str, g: ViewGeometry, target: np.ndarray) -> tuple[SpacePlan, PlannedView]:
    """A one-view plan fixated on `target`, so plan cues go through services.core.domain.plan."""
    cam = CameraPose(0, camera_center(g.world_to_camera), "provided", f"{name}-cam")
    point = PointOfInterest(0, target, np.array([0.0, 0.0, 1.0]), f"{name}-pt", (0,))
    view = PlannedView(0, 0, 0, g.world_to_camera, g.fov, 0.0, g.resolution, 0.5, True)
    return SpacePlan(name, (cam,), (point,), (view,)), view


def render_scene(name: str, mesh: trimesh.Trimesh, g: ViewGeometry, face_class: np.ndarray | None = None,
                 face_instance: np.ndarray | None = None) -> Rendered:
    space = SpaceContext(key=name, mesh=mesh, face_class=face_class, face_instance=face_instance,
                         device=RENDER_DEVICE)
    plan, view = plan_for(name, g, mesh.bounds.mean(axis=0))
    cues = ["passes", *default_cues(space.has_semantics)]
    ctx = make_context(space, view, cues, plan=plan)
    files = {c: produce(c, ctx) for c in cues}
    renders = space.scene().renders
    return Rendered(name, mesh, space, view, ViewGeometry.of(view), ctx, files, raycast(mesh, g), renders,
                    face_class, face_instance)


@pytest.fixture(scope="module")
def rendered(banana_path: Path, bunny_path: Path) -> dict[str, Rendered]:
    out = {}
    banana = load_space(banana_path).mesh
    out["banana"] = render_scene("banana", banana, object_view(banana, [0.3, -0.5, 1.0], 96))
    bunny = load_space(bunny_path).mesh
    out["bunny"] = render_scene("bunny", bunny, object_view(bunny, [0.6, -1.0, 0.5], 96))
    room, cls, inst = make_room()
    out["room"] = render_scene("room", room, room_view(128), cls, inst)
    return out


@pytest.fixture(params=SCENES)
def r(request: pytest.FixtureRequest, rendered: dict[str, Rendered]) -> Rendered:
    return rendered[request.param]


def test_one_render_per_view(r: Rendered) -> None:
    assert r.renders == 1
    assert r.ctx.timings["render"] > 0


def test_renders_on_the_requested_device(r: Rendered) -> None:
    assert r.space.scene().device == RENDER_DEVICE


def test_depth_zbuffer_matches_raycast(r: Rendered) -> None:
    z = r.png("depth_zbuffer").astype(np.float64) / 512.0  # Omnidata loader: depth / 512 = metres
    smooth = smooth_mask(r.cast)
    assert smooth.sum() > 500
    err = np.abs(z[smooth] - r.cast.z[smooth])
    tol = np.maximum(1 / 512, 0.005 * r.cast.z[smooth])
    assert np.mean(err <= tol) >= 0.99
    assert np.median(err) < 1 / 1024 + 1e-6  # only the 1/512 m quantisation is left


def test_depth_euclidean_matches_raycast(r: Rendered) -> None:
    e = r.png("depth_euclidean").astype(np.float64) / 512.0
    smooth = smooth_mask(r.cast)
    err = np.abs(e[smooth] - r.cast.t[smooth])
    assert np.mean(err <= np.maximum(1 / 512, 0.005 * r.cast.t[smooth])) >= 0.99
    assert np.all(e[r.cast.z > 0] >= r.png("depth_zbuffer")[r.cast.z > 0] / 512.0 - 1 / 1024)


def test_mask_valid_matches_ray_hits(r: Rendered) -> None:
    mask = r.png("mask_valid")
    assert set(np.unique(mask)) <= {0, 255}
    assert np.mean((mask == 255) == r.cast.hit) >= 0.995
    np.testing.assert_array_equal(mask == 255, r.png("depth_zbuffer") != 65535)


def test_normals_match_hit_triangles(r: Rendered) -> None:
    px = r.png("normal").astype(np.float64) / 255.0
    n = np.stack([1 - 2 * px[..., 0], 2 * px[..., 1] - 1, 2 * px[..., 2] - 1], axis=-1)  # Omnidata remap
    ref = cast_normals_cam(r.mesh, r.cast, r.geometry)
    smooth = smooth_mask(r.cast)
    cos = np.einsum("nc,nc->n", n[smooth] / np.linalg.norm(n[smooth], axis=-1, keepdims=True), ref[smooth])
    angles = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.median(angles) < 2.0
    # Facing the camera: the normal points back along the pixel's ray (DESIGN axes: x right, y up, z to
    # viewer).
    to_cam = -r.geometry.ray_directions_cam() * np.array([1.0, -1.0, -1.0])
    assert np.all(np.einsum("nc,nc->n", n[smooth], to_cam[smooth]) > -0.02)
    assert np.all(r.png("normal")[~r.cast.hit & (r.png("mask_valid") == 0)] == 128)


def test_fragments_match_raycast_triangles(r: Rendered) -> None:
    frag = np.load(io.BytesIO(r.files["fragments"]))
    assert frag.dtype == np.uint32 and frag.shape == r.cast.tri.shape
    smooth = smooth_mask(r.cast)
    assert np.mean(frag[smooth].astype(np.int64) == r.cast.tri[smooth]) >= 0.99
    assert np.mean((frag == 4294967295) == ~r.cast.hit) >= 0.995


def test_position_matches_raycast(r: Rendered) -> None:
    pos = decode_exr_rgb(r.files["position"])
    assert pos.dtype == np.float32 and pos.shape == (*r.cast.tri.shape, 3)
    smooth = smooth_mask(r.cast)
    err = np.linalg.norm(pos[smooth] - r.cast.loc[smooth], axis=-1)
    assert np.mean(err <= np.maximum(1 / 512, 0.005 * r.cast.t[smooth])) >= 0.99
    assert np.all(np.isnan(pos[r.png("mask_valid") == 0]))


def test_reshading_is_the_analytic_formula(r: Rendered) -> None:
    shade = r.png("reshading").astype(np.float64)
    smooth = smooth_mask(r.cast)
    to_cam = r.geometry.center - r.cast.loc
    to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
    fn = r.mesh.face_normals[np.maximum(r.cast.tri, 0)]
    expect = 255 * CueParams().reshading_albedo * np.abs(np.einsum("hwc,hwc->hw", fn, to_cam))
    err = np.abs(shade[smooth] - expect[smooth])
    assert np.mean(err <= 2) >= 0.99
    assert np.all(shade[r.png("mask_valid") == 0] == 0)


def sample_texture(mesh: trimesh.Trimesh, cast: Cast, mask: np.ndarray) -> np.ndarray:
    """Bilinear sample (in 8-bit sRGB) of the mesh's texture at the UV of each masked ray hit."""
    tri = cast.tri[mask]
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], cast.loc[mask])
    uv = (mesh.visual.uv[mesh.faces[tri]] * bary[..., None]).sum(axis=1)
    mat = mesh.visual.material
    tex = getattr(mat, "image", None) or getattr(mat, "baseColorTexture", None)  # OBJ / glTF
    img = np.asarray(tex.convert("RGB"), dtype=np.float64)
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1 - uv[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def test_rgb_is_the_texture_at_the_hit_uv(rendered: dict[str, Rendered]) -> None:
    r = rendered["banana"]
    rgb = r.png("rgb").astype(np.float64)
    smooth = smooth_mask(r.cast)
    err = np.abs(rgb[smooth] - sample_texture(r.mesh, r.cast, smooth))
    assert np.median(err) <= 2
    assert np.percentile(err, 90) <= 8
    assert rgb[smooth].std(axis=0).max() > 10  # a real texture, not a flat colour


def test_rgb_of_untextured_scan_is_constant_grey(rendered: dict[str, Rendered]) -> None:
    r = rendered["bunny"]
    rgb = r.png("rgb")
    hit = r.png("mask_valid") == 255
    assert np.all(rgb[hit] == 128) and np.all(rgb[~hit] == 0)


def test_rgb_of_face_colours_is_exact(rendered: dict[str, Rendered]) -> None:
    r = rendered["room"]
    rgb = r.png("rgb").astype(np.int64)
    smooth = smooth_mask(r.cast)
    expect = r.mesh.visual.face_colors[r.cast.tri[smooth], :3].astype(np.int64)
    assert np.mean(np.abs(rgb[smooth] - expect).max(axis=1) <= 1) >= 0.99


def test_the_space_is_no_light_source_to_cycles(rendered: dict[str, Rendered]) -> None:
    """The space's emission shader is what the camera sees (no bounces: it lights nothing). Left to Cycles'
    automatic emission sampling, every sync of a coloured or textured mesh evaluated the shader on each
    triangle to build a light tree: 1.0 s of the 7-Scenes kitchen's first render (192k vertex-coloured
    triangles), for
    nothing."""
    scene = rendered["room"].space.scene()
    assert scene.object.active_material.cycles.emission_sampling == "NONE"


def test_semantic_instance_panoptic_match_face_labels(rendered: dict[str, Rendered]) -> None:
    r = rendered["room"]
    assert r.face_class is not None and r.face_instance is not None
    smooth = smooth_mask(r.cast)
    sem, inst, pan = r.png("segment_semantic"), r.png("segment_instance"), r.png("segment_panoptic")
    assert png_header(r.files["segment_semantic"])[2:] == (8, 0)
    assert png_header(r.files["segment_instance"])[2:] == (16, 0)
    assert png_header(r.files["segment_panoptic"])[2:] == (8, 2)
    tri = r.cast.tri[smooth]
    assert np.mean(sem[smooth] == r.face_class[tri]) >= 0.99
    assert np.mean(inst[smooth].astype(np.int64) == r.face_instance[tri]) >= 0.99
    np.testing.assert_array_equal(pan[..., 0], sem)
    np.testing.assert_array_equal(pan[..., 1].astype(np.int64) * 256 + pan[..., 2], inst)
    assert len(np.unique(sem)) >= 4  # floor, walls, boxes, sphere in view


def test_curvature_of_the_room_sphere(rendered: dict[str, Rendered]) -> None:
    r = rendered["room"]
    sphere = (r.png("segment_semantic") == ROOM_CLASSES["sphere"]) & smooth_mask(r.cast)
    assert sphere.sum() > 200
    k = r.ctx.passes.curvature
    assert k is not None
    np.testing.assert_allclose(np.median(k[sphere], axis=0), [1 / SPHERE_RADIUS] * 2, rtol=0.05)
    px = r.png("principal_curvature").astype(np.float64)
    kmax = 1 / CueParams().curvature_clip_m
    decoded = (px[..., :2] / 127.0 - 1.0) * kmax
    np.testing.assert_allclose(np.median(decoded[sphere], axis=0), [1 / SPHERE_RADIUS] * 2, atol=kmax / 127)
    floor = (r.png("segment_semantic") == ROOM_CLASSES["floor"]) & smooth_mask(r.cast)
    assert np.median(px[floor][:, :2]) == 127  # flat
    assert np.all(px[..., 2] == 0)


# Every cue file: type, bit depth, resolution, content.
PNG_FORMAT = {"uint8": {1: (8, 0), 3: (8, 2)}, "uint16": {1: (16, 0)}}


def test_every_cue_file_has_its_format_and_content(r: Rendered) -> None:
    res = r.geometry.resolution
    expected = set(default_cues(r.face_class is not None)) | {"passes"}
    assert set(r.files) == expected
    for cue, data in r.files.items():
        spec = CATALOG[cue]
        assert len(data) > 0, cue
        if spec.ext == "png":
            w, h, depth, ctype = png_header(data)
            assert (w, h) == (res, res), cue
            assert (depth, ctype) == PNG_FORMAT[spec.dtype][spec.channels], cue
            a = r.png(cue)
            if cue == "mask_valid" and r.cast.hit.all():  # the closed room: every pixel sees a surface
                assert np.all(a == 255)
                continue
            # Non-degenerate: not one constant value over the image (the untextured bunny's rgb still has
            # background and grey).
            assert len(np.unique(a.reshape(-1, spec.channels), axis=0)) > 1, cue
        elif spec.ext == "npy":
            a = np.load(io.BytesIO(data))
            assert a.dtype == np.dtype(spec.dtype) and a.shape == (res, res), cue
            assert len(np.unique(a)) > 10, cue
        elif spec.ext == "exr":
            a = decode_exr_rgb(data)
            assert a.shape == (res, res, 3) and np.isfinite(a).any(), cue
        elif spec.ext == "json":
            import json

            obj = json.loads(data)
            assert isinstance(obj, dict) and obj, cue
        elif spec.ext == "npz":
            p = ViewPasses.from_bytes(data)
            assert p.depth_z.shape == (res, res)
    info = __import__("json").loads(r.files["point_info"])
    np.testing.assert_allclose(info["world_to_camera"], r.geometry.world_to_camera)
    assert info["resolution"] == res


def test_segmentations_are_non_trivial(r: Rendered) -> None:
    s2, s25 = r.png("segment_unsup2d"), r.png("segment_unsup25d")
    valid = r.png("mask_valid") == 255
    assert np.all(s25[~valid] == 0) and np.all(s25[valid] > 0)
    assert len(np.unique(s25[valid])) >= 2
    if r.name != "bunny":  # the bunny is one flat grey: one colour segment is right
        assert len(np.unique(s2[valid])) >= 2


def test_cached_passes_reproduce_every_file(r: Rendered) -> None:
    passes = ViewPasses.from_bytes(r.files["passes"])
    ctx = ViewContext(r.view, passes=passes, plan=r.ctx.plan)
    for cue, data in r.files.items():
        assert produce(cue, ctx) == data, cue


def test_semantic_cues_refused_for_unlabelled_space(rendered: dict[str, Rendered]) -> None:
    r = rendered["bunny"]
    with pytest.raises(SemanticsUnavailableError, match="segment_semantic.*unlabelled"):
        render_view_cues(r.space, r.view, ["rgb", "segment_semantic"])
    with pytest.raises(SemanticsUnavailableError):
        produce("segment_panoptic", r.ctx)


def test_space_cache_keeps_and_frees_scenes(rendered: dict[str, Rendered]) -> None:
    cache = SpaceCache()
    tiny = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    g = object_view(tiny, [1.0, 0.2, 0.3], 32)
    a = cache.get("a", lambda: SpaceContext(key="a", mesh=tiny))
    files = render_view_cues(a, g, ["depth_zbuffer", "normal"])
    assert set(files) == {"depth_zbuffer", "normal"}
    scene_a = a.scene()
    assert cache.get("a", lambda: pytest.fail("reloaded")) is a
    render_view_cues(a, g, ["rgb"])
    assert scene_a.renders == 2 and cache.loads == 1
    b = cache.get("b", lambda: SpaceContext(key="b", mesh=tiny.copy()))
    assert scene_a.closed and b is not a and cache.loads == 2
    np.testing.assert_array_equal(
        np.array(Image.open(io.BytesIO(render_view_cues(b, g, ["depth_zbuffer"])["depth_zbuffer"]))),
        np.array(Image.open(io.BytesIO(files["depth_zbuffer"]))),
    )
    cache.clear()
    assert cache.current is None and rss_bytes() > 50 * 1024 * 1024


def test_gpu_request_falls_back_to_cpu(caplog: pytest.LogCaptureFixture,
                                       rendered: dict[str, Rendered]) -> None:
    from services.worker.blender.render import RenderOptions
    from services.worker.blender.scene import BlenderScene

    with pytest.raises(ValueError, match="device"):
        RenderOptions(device="vulkan")  # type: ignore[arg-type]
    with caplog.at_level(logging.INFO):
        scene = BlenderScene(trimesh.creation.box(), options=RenderOptions(device="cuda"))
    try:
        import bpy

        if scene.device == "cpu":
            assert "rendering on the CPU" in caplog.text
            assert bpy.context.scene.cycles.device == "CPU"
        else:  # a machine with a CUDA device
            assert bpy.context.scene.cycles.device == "GPU"
    finally:
        scene.close()


def test_auto_falling_back_beside_an_nvidia_device_file_is_a_warning(
    caplog: pytest.LogCaptureFixture, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    rendered: dict[str, Rendered],
) -> None:
    """A machine whose driver made /dev/nvidia0 but where Cycles finds no device (`generate` gave fewer
    workers the renders there): "auto" rendering on the CPU is a warning naming the device file, not the usual
    info
    line."""
    from services.core import gpu_devices
    from services.worker.blender.render import RenderOptions
    from services.worker.blender.scene import BlenderScene

    (tmp_path / "nvidia0").touch()
    monkeypatch.setattr(gpu_devices, "NVIDIA_DEVICE_NODES", str(tmp_path / "nvidia[0-9]*"))
    with caplog.at_level(logging.INFO, logger="services.worker.blender"):
        scene = BlenderScene(trimesh.creation.box(), options=RenderOptions(device="auto"))
    try:
        if scene.device == "cpu":
            [record] = [r for r in caplog.records if "rendering on the CPU" in r.getMessage()]
            assert record.levelno == logging.WARNING
            assert f"an NVIDIA GPU is present: {tmp_path / 'nvidia0'}" in record.getMessage()
        else:  # a machine with a GPU Cycles can use
            assert "Cycles renders on" in caplog.text
    finally:
        scene.close()


@pytest.mark.parametrize("device", ["auto", "optix"])
def test_worker_device_selection_renders_on_the_cpu_when_no_gpu_is_found(
        device: str, caplog: pytest.LogCaptureFixture, rendered: dict[str, Rendered]) -> None:
    """The worker's path (SpaceContext -> BlenderScene -> configure_device): a GPU request on a machine
    without one logs the fallback naming what was asked and renders the same view as a CPU scene would."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    g = object_view(box, np.array([1.0, 0.7, 0.5]), 32)
    cpu = SpaceContext(key="box-cpu", mesh=box, device="cpu")
    want = cpu.render(g, CueParams(), passes=frozenset())
    cpu.close()
    space = SpaceContext(key=f"box-{device}", mesh=box, device=device)
    with caplog.at_level(logging.INFO, logger="services.worker.blender"):
        got = space.render(g, CueParams(), passes=frozenset())
    try:
        if space.scene().device == "cpu":
            assert f"render device {device!r} requested but no" in caplog.text
            assert "rendering on the CPU" in caplog.text
            np.testing.assert_array_equal(got.depth_z, want.depth_z)
        else:  # a machine with a GPU: the log names it, and the depth agrees to float precision
            assert "Cycles renders on" in caplog.text
            np.testing.assert_allclose(got.depth_z, want.depth_z, rtol=1e-4)
        # passes=frozenset(): colour and depth only
        assert got.normal_world is None and got.face_index is None
        assert got.hit.sum() > 100
    finally:
        space.close()


def test_a_view_renders_only_the_passes_its_cues_need(rendered: dict[str, Rendered]) -> None:
    from services.worker.executor import render_passes_for
    from services.worker.passes import RENDER_PASSES

    assert render_passes_for(["rgb", "depth_zbuffer", "edge_occlusion", "keypoints3d"]) == frozenset()
    assert render_passes_for(["segment_unsup25d", "reshading"]) == {"normal"}
    assert render_passes_for(["segment_panoptic"]) == {"labels"}
    assert render_passes_for(["fragments", "principal_curvature"]) == {"faces", "curvature"}
    assert render_passes_for(["passes"]) == RENDER_PASSES
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.4))
    g = object_view(box, np.array([1.0, 0.7, 0.5]), 48)
    space = SpaceContext(key="box-passes", mesh=box)
    try:
        lean = make_context(space, g, ["rgb", "depth_zbuffer"])
        files = {c: produce(c, lean) for c in ("rgb", "depth_zbuffer")}
        p = lean.passes
        assert p.normal_world is None and p.face_index is None and p.curvature is None
        assert space.stats.get("curvature_s") is None  # the mesh's curvature was never computed
        with pytest.raises(RuntimeError, match="no face_index"):
            produce("fragments", lean)
        full = make_context(space, g, ["passes"])
        assert full.passes.face_index is not None and full.passes.curvature is not None
        assert all(produce(c, full) == data for c, data in files.items())  # same files either way
        np.testing.assert_array_equal(full.passes.hit, p.hit)
        # A pass set without the optional passes survives the worker's cache.
        again = ViewPasses.from_bytes(p.to_bytes())
        assert again.face_index is None and np.array_equal(again.hit, p.hit)
    finally:
        space.close()
