"""Other source formats through the real loader: a .glb (PBR base colour texture), a vertex-coloured .ply,
a point cloud meshed on ingest and a ScanNet scene's labels."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from services.core.domain.camera import look_at
from services.core.ingest.loading import load_space
from services.worker.blender.render import srgb_encode
from services.worker.blender.scene import srgb_to_linear
from services.worker.executor import render_view_cues
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import ViewGeometry
from tests.fixtures.cli import REPO
from tests.fixtures.raycast import object_view, raycast, smooth_mask
from tests.fixtures.scans import room_cloud, scannet_scene
from tests.worker.blender.test_render import sample_texture

pytestmark = pytest.mark.bpy  # every test renders


def test_glb_renders_its_base_colour_texture(tmp_path: Path, banana_path: Path) -> None:
    mesh = load_space(banana_path).mesh
    glb = tmp_path / "banana.glb"
    mesh.export(glb)
    loaded = load_space(glb)
    assert loaded.has_texture
    g = object_view(loaded.mesh, [0.2, -0.4, 1.0], 80, fill=1.0)
    files = render_view_cues(SpaceContext.from_loaded(loaded, key="glb"), g, ["rgb", "fragments"])
    rgb = np.array(Image.open(io.BytesIO(files["rgb"]))).astype(np.float64)
    cast = raycast(loaded.mesh, g)
    smooth = smooth_mask(cast)
    assert smooth.sum() > 300
    # glTF multiplies the texture by baseColorFactor (linear); trimesh's export turned the MTL's Kd into it.
    factor = np.asarray(loaded.mesh.visual.material.baseColorFactor)[:3] / 255.0
    assert np.all(factor < 0.9)
    tex = sample_texture(loaded.mesh, cast, smooth)
    expect = srgb_encode(srgb_to_linear(tex) * factor).astype(np.float64)
    err = np.abs(rgb[smooth] - expect)
    assert np.median(err) <= 2 and np.percentile(err, 90) <= 8
    frag = np.load(io.BytesIO(files["fragments"]))
    assert np.mean(frag[smooth].astype(np.int64) == cast.tri[smooth]) >= 0.99


def test_vertex_colours_are_interpolated_like_the_renderer_says(tmp_path: Path, bunny_path: Path) -> None:
    mesh = load_space(bunny_path).mesh.copy()
    # Smooth colours (a function of position), so barycentric interpolation is well defined per pixel.
    t = (mesh.vertices - mesh.bounds[0]) / mesh.extents
    colours = np.c_[(t * 255).round().astype(np.uint8), np.full(len(t), 255, np.uint8)]
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=colours)
    ply = tmp_path / "bunny_colours.ply"
    mesh.export(ply)
    loaded = load_space(ply)
    assert loaded.has_vertex_colors
    g = object_view(loaded.mesh, [0.6, -1.0, 0.5], 64)
    rgb = np.array(Image.open(io.BytesIO(render_view_cues(SpaceContext.from_loaded(loaded, key="vc"), g,
                                                          ["rgb"])["rgb"]))).astype(np.int64)
    cast = raycast(loaded.mesh, g)
    smooth = smooth_mask(cast)
    tri = cast.tri[smooth]
    bary = trimesh.triangles.points_to_barycentric(loaded.mesh.triangles[tri], cast.loc[smooth])
    vc = srgb_to_linear(np.asarray(loaded.mesh.visual.vertex_colors)[:, :3])
    expect = srgb_encode((vc[loaded.mesh.faces[tri]] * bary[..., None]).sum(axis=1)).astype(np.int64)
    assert np.mean(np.abs(rgb[smooth] - expect).max(axis=1) <= 2) >= 0.99


def _depth_m(png: bytes) -> np.ndarray:
    """depth_zbuffer PNG -> metres (NaN where no surface), DESIGN.md section 5."""
    raw = np.array(Image.open(io.BytesIO(png))).astype(np.float64)
    return np.where(raw == 65535, np.nan, raw / 512.0)


def test_point_cloud_renders_depth_of_the_true_room(tmp_path: Path) -> None:
    """A cloud sampled from a known room, meshed on ingest, renders depth within 5 cm of the room itself."""
    room, pts, _normals, colours = room_cloud(20_000, seed=2)
    src = tmp_path / "room.xyz"
    np.savetxt(src, np.column_stack([pts, colours]), fmt="%.5f")  # no normals: estimated on ingest
    loaded = load_space(src, cloud_cache_dir=tmp_path / "cache")
    assert loaded.reconstruction is not None and loaded.has_vertex_colors
    space = SpaceContext.from_loaded(loaded, key="cloud")
    true_room = room.copy().apply_transform(loaded.source_to_world)  # the same world frame
    for eye, target in (([1.0, 1.0, 1.5], [5.0, 3.0, 0.8]), ([5.0, 3.2, 1.2], [1.0, 0.5, 0.5])):
        g = ViewGeometry(
            look_at(loaded.source_to_world[:3, :3] @ eye, loaded.source_to_world[:3, :3] @ target),
            np.radians(70.0), 48,
        )
        depth = _depth_m(render_view_cues(space, g, ["depth_zbuffer"])["depth_zbuffer"])
        truth = raycast(true_room, g).z
        # both: sky above the walls
        agree = (np.abs(depth - truth) <= 0.05) | (np.isnan(depth) & np.isnan(truth))
        assert np.mean(agree) >= 0.8, float(np.mean(agree))
        assert np.mean(np.isfinite(truth)) > 0.5


def test_scannet_labels_render_as_semantic_and_instance(tmp_path: Path) -> None:
    ply, _ = scannet_scene(tmp_path / "scene")
    loaded = load_space(ply)
    g = ViewGeometry(look_at(np.array([0.0, 3.0, 2.5]), np.array([0.0, 0.0, 0.3])), np.radians(70.0), 48)
    files = render_view_cues(SpaceContext.from_loaded(loaded, key="scannet"), g,
                             ["segment_semantic", "segment_instance", "segment_panoptic"])
    cast = raycast(loaded.mesh, g)
    hit = cast.hit
    sem = np.array(Image.open(io.BytesIO(files["segment_semantic"])))
    inst = np.array(Image.open(io.BytesIO(files["segment_instance"])))
    assert hit.sum() > 1000
    # the same ids as the ray-cast triangles' labels (pixels on label borders may differ)
    assert np.mean(sem[hit] == loaded.face_class[cast.tri[hit]]) >= 0.95
    assert np.mean(inst[hit] == loaded.face_instance[cast.tri[hit]]) >= 0.95
    assert set(np.unique(sem[hit])) >= {1, 2, 3}  # chair, floor, table all seen


MESH_THEN_RENDER = r"""
import sys
import numpy as np
from services.core.domain.camera import look_at
from services.core.ingest.loading import load_space
from services.worker.inputs.space_cache import SpaceContext
from services.core.domain.jobspec import CueParams
from services.worker.passes import ViewGeometry
loaded = load_space(sys.argv[1], cloud_cache_dir=sys.argv[2])  # meshed here: the cache is empty
assert "bpy" not in sys.modules
space = SpaceContext.from_loaded(loaded, key="cloud", threads=1)
lo, hi = loaded.mesh.bounds
passes = space.render(ViewGeometry(look_at((lo + hi) / 2, hi), 1.0, 32), CueParams())
print("rendered", int(np.isfinite(passes.depth_z).sum()))
"""


def test_a_process_that_meshed_a_cloud_renders_it(tmp_path: Path) -> None:
    """A worker meshes a cloud it has not seen (pymeshlab), then imports Blender to render it, in that order,
    in a fresh interpreter as a worker process is: pymeshlab's older Embree, loaded first, made `import bpy`
    fail (undefined symbol rtcGetSceneTraversable)."""
    _room, pts, _normals, colours = room_cloud(8_000, seed=3)
    src = tmp_path / "room.xyz"
    np.savetxt(src, np.column_stack([pts, colours]), fmt="%.5f")
    run = subprocess.run([sys.executable, "-c", MESH_THEN_RENDER, str(src), str(tmp_path / "cache")],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert int(run.stdout.split()[-1]) > 0
