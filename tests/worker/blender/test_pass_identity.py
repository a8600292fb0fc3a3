"""The pass render is bit-identical to the render before issue 20 part 3, on real views of a real room, but
for the normals, which are now derived from the face index and checked against Cycles' Normal pass.

Before: six AOVs (face index + 1 in two 16-bit halves, class, instance, k1, k2), the Normal pass and a numpy
decode. Now: face index + 1 in one AOV (meshes below 2^24 faces), class and instance looked up from the face
index, the normals derived from the face index (no Normal pass), single-pass decode kernels and a table sRGB
encoding. The reference here renders the same views in a second Blender scene with the old AOVs and the Normal
pass, and decodes them with the old numpy expressions (copied below); every other array of the pass set must
have the same bytes. The room (../shared/scenes/icl_livingroom) gets made-up labels (negative ids too).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.core.domain.jobspec import CueParams, JobSpec
from services.core.ingest.loading import load_space
from services.scheduler.planning import make_plan, space_rng
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import NO_FACE, NO_LABEL, RENDER_PASSES, ViewGeometry, ViewPasses

pytestmark = pytest.mark.bpy

RESOLUTION = 256
N_VIEWS = 4


def old_decode(channels: dict[str, np.ndarray], layer: str) -> dict[str, np.ndarray]:
    """The decode of the six-AOV EXR before issue 20 part 3 (render.render_passes, every pass)."""
    from services.worker.blender.render import srgb_encode

    def unit_normals(x: np.ndarray, y: np.ndarray, z: np.ndarray, hit: np.ndarray) -> np.ndarray:
        n = np.stack([x, y, z], axis=-1)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        return np.where(hit[..., None] & (norm > 0), n / np.maximum(norm, 1e-12), 0.0).astype(np.float32)

    def aov(name: str) -> np.ndarray:
        key = f"{layer}.{name}"
        return channels[key] if key in channels else channels[f"{key}.X"]

    depth = channels.get(f"{layer}.Depth.Z", channels.get(f"{layer}.Depth"))
    hit = depth < 1e9
    face1 = aov("omni_face_hi").astype(np.int64) * 65536 + aov("omni_face_lo").astype(np.int64)
    hit &= face1 > 0
    k = np.stack([aov("omni_k1"), aov("omni_k2")], axis=-1)
    return {
        "face_index": np.where(hit, face1 - 1, int(NO_FACE)).astype(np.uint32),
        "depth_z": np.where(hit, depth, np.inf).astype(np.float32),
        "normal_world": unit_normals(*(channels[f"{layer}.Normal.{c}"] for c in "XYZ"), hit),
        "rgb": np.where(hit[..., None], srgb_encode(channels[f"{layer}.Combined"][..., :3]), 0).astype(
            np.uint8
        ),
        "face_class": np.where(hit, np.rint(aov("omni_class")), NO_LABEL).astype(np.int32),
        "face_instance": np.where(hit, np.rint(aov("omni_instance")), NO_LABEL).astype(np.int32),
        "curvature": np.where(hit[..., None], k, np.nan).astype(np.float32),
    }


@pytest.fixture(scope="module")
def renders(scenes_dir: Path) -> list[tuple[ViewPasses, dict[str, np.ndarray], ViewPasses]]:
    """Per view: (the pass render now, the old render decoded the old way, the old render decoded now)."""
    import bpy
    import OpenEXR

    from services.worker.blender import render as r

    loaded = load_space(scenes_dir / "icl_livingroom")
    plan = make_plan(loaded, JobSpec(), space_rng(0, "icl_livingroom"), "icl_livingroom")
    views = [
        ViewGeometry(v.world_to_camera, v.fov, RESOLUTION) for v in plan.views[:: len(plan.views) // N_VIEWS]
    ]
    rng = np.random.default_rng(3)
    nf = len(loaded.mesh.faces)
    space = SpaceContext(key="icl-pass-identity", mesh=loaded.mesh, face_class=rng.integers(-3, 40, nf),
                         face_instance=rng.integers(-1, 5000, nf))
    try:
        now = [space.render(g, CueParams(), passes=RENDER_PASSES) for g in views[:N_VIEWS]]
        bs = space.scene()
        old = bpy.data.scenes.new("old")
        old.collection.objects.link(bs.object)
        old.collection.objects.link(bs.camera)
        old.camera = bs.camera
        old_aovs = (r.AOV_FACE_HI, r.AOV_FACE_LO, r.AOV_CLASS, r.AOV_INSTANCE, r.AOV_K1, r.AOV_K2)
        r.configure_scene(old, bs.options, bs.scene.render.filepath + ".old.exr", old_aovs)
        old.view_layers[0].use_pass_normal = True
        out = []
        for p, g in zip(now, views, strict=False):
            again = r.render_passes(old, bs.camera, g, face_normals=bs.face_normals)  # today's decode
            channels = {n: c.pixels for n, c in OpenEXR.File(old.render.filepath).parts[0].channels.items()}
            out.append((p, old_decode(channels, old.view_layers[0].name), again))
        return out
    finally:
        space.close()


def test_the_pass_render_has_fewer_aovs_than_before_and_no_normal_pass():
    from services.worker.blender.render import AOV_FACE, AOV_FACE_HI, AOV_K1, AOV_K2, pass_aovs

    assert pass_aovs(2**24 - 1) == (AOV_FACE, AOV_K1, AOV_K2)
    assert pass_aovs(2**24)[0] == AOV_FACE_HI  # face index + 1 = 2^24 + 1 is not a float32: two halves


def test_the_pass_scene_renders_no_normal_pass_and_the_floor_scene_does(scenes_dir: Path):
    loaded = load_space(scenes_dir / "icl_livingroom")
    space = SpaceContext.from_loaded(loaded, key="icl-normal-pass")
    try:
        bs = space.scene()
        bs.render_floor(ViewGeometry(np.eye(4), 1.0, 8))
        assert not bs.scene.view_layers[0].use_pass_normal and bs._floor.view_layers[0].use_pass_normal
    finally:
        space.close()


@pytest.mark.parametrize("name", ["face_index", "depth_z", "rgb", "face_class", "face_instance", "curvature"])
def test_every_pass_is_bit_identical_to_the_old_render(renders, name: str) -> None:
    seen = 0
    for now, old, again in renders:
        want = old[name]
        for got in (getattr(now, name), getattr(again, name)):
            assert got is not None and got.dtype == want.dtype and got.shape == want.shape
            assert got.tobytes() == want.tobytes(), name
        seen += int(now.hit.sum())
    assert seen > N_VIEWS * RESOLUTION**2 // 2  # the room's views mostly see surfaces
    if name in ("face_class", "face_instance"):
        assert len(np.unique(renders[0][0].require(name))) > 3  # many labels, negative ones too
        assert (renders[0][0].require(name) < -1).any() or name == "face_instance"


def test_normals_from_the_face_index_are_cycles_normal_pass_to_float32_rounding(renders) -> None:
    """Cycles computes the triangle's normal in float32, the decode in float64 from the same float32 vertices:
    the unit vectors agree to a few 1e-7, the side (turned against the ray) everywhere, and the normal cue's
    8-bit pixels on all but a handful (a value within 1e-7 of a rounding boundary), by one level."""
    from services.worker.cues.basic import _normal_pixels

    differ = total = 0
    for now, old, again in renders:
        want, got = old["normal_world"], now.require("normal_world")
        assert got.dtype == np.float32 and got.shape == want.shape
        assert np.array_equal(again.require("normal_world"), got)  # the same derivation from either render
        hit = now.hit
        assert np.abs(got - want).max() < 2e-6
        assert ((got[hit] * want[hit]).sum(-1) > 0.999999).all() and (got[~hit] == 0).all()
        R = now.geometry.rotation.astype(np.float32)
        a, b = (_normal_pixels(np.ascontiguousarray(n @ R.T), hit) for n in (got, want))
        assert np.abs(a.astype(int) - b).max() <= 1
        differ += int((a != b).any(-1).sum())
        total += int(hit.sum())
    assert differ <= total * 1e-4
