"""Other source formats through the real loader: a .glb (PBR base colour texture) and a vertex-coloured .ply."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from services.core.spaces import load_space
from services.worker.blender import srgb_encode, srgb_to_linear
from services.worker.executor import render_view_cues
from services.worker.space_cache import SpaceContext
from tests.worker.conftest import object_view, raycast, smooth_mask
from tests.worker.test_render import sample_texture


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
