"""The compiled per-view passes of issue 20 (session 4) give the values of the code they replaced, bit for
bit.

Real views: the real planner's cameras in both real rooms (../shared/scenes: the ICL living room and the
7-Scenes kitchen), rendered by Cycles at 160 x 160, every changed cue compared byte for byte with the frozen
references (tests/fixtures/reference_view_cues.py, reference_narf.py: numpy and scipy). Synthetic inputs cover
what real views do not reach: back-facing normals, signed zeros, NaN and inf, odd shapes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.core.domain.jobspec import CueParams, JobSpec
from services.core.ingest.loading import load_space
from services.scheduler.planning import make_plan, space_rng
from services.worker.context import ViewContext
from services.worker.cues import basic, common, edges, keypoints
from services.worker.cues.registry import cue_value
from services.worker.executor import make_context
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import ViewGeometry, ViewPasses
from tests.fixtures import reference_narf
from tests.fixtures import reference_view_cues as ref
from tests.fixtures.raycast import make_room, raycast_passes, room_view

RESOLUTION = 160
VIEWS_PER_ROOM = 3
# name -> (space path under the scenes folder, load_space frame arguments), as bench/lib/rooms.py
ROOMS = {
    "icl_livingroom": ("icl_livingroom", {}),
    "7scenes_redkitchen": (
        "7scenes_redkitchen/mesh_tsdf_2cm_from_1000frames.ply", {"up": (0.009, -0.904, -0.427)},
    ),
}


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def changed_cues() -> dict:
    """name -> (current, reference) of every output the compiled passes produce."""
    return {
        "normal_cam": (common.normal_cam, ref.normal_cam),
        "normal": (
            lambda c: cue_value(c, "normal"),
            lambda c: basic._normal_pixels(ref.normal_cam(c), common.hit(c)),
        ),
        "reshading_intensity": (basic.reshading_intensity, ref.reshading_intensity),
        "reshading": (lambda c: cue_value(c, "reshading"), ref.reshading),
        "occlusion_response": (edges.occlusion_response, ref.occlusion_response),
        "edge_occlusion": (
            lambda c: cue_value(c, "edge_occlusion"),
            lambda c: ref.to_uint16_scaled(ref.occlusion_response(c), c.params.edge_scale),
        ),
        "edge_texture": (lambda c: cue_value(c, "edge_texture"), ref.edge_texture),
        "keypoints2d": (lambda c: cue_value(c, "keypoints2d"), ref.keypoints2d),
        "ray_dirs_cam64": (common.ray_dirs_cam64, lambda c: c.geometry.ray_directions_cam()),
        "ray_dirs_cam": (common.ray_dirs_cam, lambda c: c.geometry.ray_directions_cam().astype(np.float32)),
        "depth_zbuffer": (lambda c: cue_value(c, "depth_zbuffer"), ref.depth_zbuffer),
        "depth_euclidean": (lambda c: cue_value(c, "depth_euclidean"), ref.depth_euclidean),
        "mask_valid": (lambda c: cue_value(c, "mask_valid"), ref.mask_valid),
        "narf_interest": (keypoints.narf_interest, reference_narf.narf_interest),
        "keypoints3d": (
            lambda c: cue_value(c, "keypoints3d"),
            lambda c: ref.to_uint16_scaled(reference_narf.narf_interest(c), 65535.0),
        ),
    }


@pytest.fixture(scope="module")
def real_views(scenes_dir: Path) -> list[tuple[str, ViewPasses]]:
    """Pass sets of VIEWS_PER_ROOM planner views (spread over the points) of each real room, rendered by
    Cycles."""
    out = []
    for room, (path, frame) in ROOMS.items():
        loaded = load_space(scenes_dir / path, **frame)
        plan = make_plan(loaded, JobSpec(), space_rng(0, room), room)
        views = plan.views[:: max(1, len(plan.views) // VIEWS_PER_ROOM)][:VIEWS_PER_ROOM]
        space = SpaceContext.from_loaded(loaded, key=f"{room}-view-kernels")
        try:
            out += [
                (
                    room,
                    make_context(
                        space, ViewGeometry(v.world_to_camera, v.fov, RESOLUTION), ["passes"]
                    ).passes,
                )
                for v in views
            ]
        finally:
            space.close()
    return out


@pytest.mark.bpy
def test_every_changed_cue_is_the_previous_code_bit_for_bit_on_real_views_of_both_rooms(real_views) -> None:
    assert {room for room, _ in real_views} == set(ROOMS)
    for room, passes in real_views:
        for name, (new, old) in changed_cues().items():
            a, b = new(ViewContext(None, passes=passes)), old(ViewContext(None, passes=passes))
            assert same_bits(a, b), (room, name)
        interest = keypoints.narf_interest(ViewContext(None, passes=passes))
        assert interest.max() > 0.05, room  # real interest, not an empty comparison


def _raycast_contexts() -> list[ViewContext]:
    """A raycast room with a depth hole and its normals partly turned away from the camera (the facing flip),
    under default and shallow max depth."""
    room = make_room()[0]
    g = room_view(64)
    passes = raycast_passes(room, g)
    depth = passes.depth_z.copy()
    depth[20:26, 5:15] = np.inf
    passes.depth_z = depth
    normals = passes.normal_world.copy()
    normals[::3] *= -1.0  # back-facing rows: normal_cam turns them to the camera
    normals[1, 1] = 0.0
    passes.normal_world = normals
    return [ViewContext(g, passes=passes), ViewContext(g, CueParams(max_depth_m=2.5, reshading_albedo=1.0),
                                                       passes=passes)]


def test_every_changed_cue_is_the_previous_code_bit_for_bit_on_raycast_views() -> None:
    for ctx_args in _raycast_contexts():
        for name, (new, old) in changed_cues().items():
            a = new(ViewContext(ctx_args.view, ctx_args.params, passes=ctx_args.passes))
            b = old(ViewContext(ctx_args.view, ctx_args.params, passes=ctx_args.passes))
            assert same_bits(a, b), name


def test_normal_cam_is_the_fused_matmul_and_facing_flip_on_random_normals() -> None:
    rng = np.random.default_rng(3)
    g = room_view(48)
    for scale in (1.0, 1e-20, 1e20):
        n = (rng.normal(size=(48, 48, 3)) * scale).astype(np.float32)
        n[rng.random((48, 48)) < 0.1] = -0.0
        passes = raycast_passes(make_room()[0], g)
        passes.normal_world = n
        ctx = ViewContext(g, passes=passes)
        facing = np.einsum("hwc,hwc->hw", n @ g.rotation.astype(np.float32).T, common.ray_dirs_cam(ctx)) > 0
        assert 0.2 < facing.mean() < 0.8  # both branches of the flip
        for fn in (common.normal_cam, basic.reshading_intensity, basic.reshading):
            assert same_bits(
                fn(ViewContext(g, passes=passes)), getattr(ref, fn.__name__)(ViewContext(g, passes=passes))
            )


def _awkward(rng: np.random.Generator, shape: tuple[int, ...], scale: float) -> np.ndarray:
    """Float32 noise with signed zeros, and NaN / inf where there is room."""
    x = ((rng.random(shape) - 0.4) * scale).astype(np.float32)
    x[rng.random(shape) < 0.15] = 0.0
    x[rng.random(shape) < 0.15] = -0.0
    if x.size > 8:
        x.flat[1], x.flat[5], x.flat[7] = np.nan, np.inf, -np.inf
    return x


@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (5, 1), (2, 2), (3, 3), (37, 24)])
def test_sobel_magnitude_and_uint16_scaling_are_numpys_bit_for_bit(shape) -> None:
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    with np.errstate(all="ignore"):
        for scale in (1.0, 1e-3, 300.0, 1e30):
            img = _awkward(rng, shape, scale)
            mask = rng.random(shape) < 0.7
            assert same_bits(common.sobel_magnitude(img), ref.sobel_magnitude(img))
            assert same_bits(common.sobel_magnitude(img, mask=mask),
                             np.where(mask, ref.sobel_magnitude(img), 0.0).astype(np.float32))
            for s in (1.0, 1000.0, 65535.0):
                assert same_bits(common.to_uint16_scaled(img, s), ref.to_uint16_scaled(img, s))


@pytest.mark.parametrize("resolution", [1, 2, 7, 160, 333])
def test_ray_directions_are_the_geometrys_bit_for_bit(resolution) -> None:
    for fov in (0.2, 1.0, 1.35, 2.2):
        g = ViewGeometry(np.eye(4), fov, resolution)
        d = g.ray_directions_cam()
        assert same_bits(common.ray_dirs_cam64(ViewContext(g)), d)
        assert same_bits(common.ray_dirs_cam(ViewContext(g)), d.astype(np.float32))


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (37, 24)])
def test_depth_pngs_and_scale_split_are_the_numpy_steps_on_awkward_depths(shape) -> None:
    from services.worker.cues import narf_kernels

    rng = np.random.default_rng(shape[1])
    ctx = ViewContext(room_view(8))
    for scale in (1.0, 100.0, 1e30):
        metres = np.abs(_awkward(rng, shape, scale))
        edges = np.array([127.99805, 127.999, 0.5 / 512, 1e-30], np.float32)  # around 65535 and 0 units
        metres.flat[: min(4, metres.size)] = edges[: min(4, metres.size)]
        mask = rng.random(shape) < 0.7
        assert same_bits(common.to_uint16_depth(ctx, metres, mask), ref.depth_uint16(ctx, metres, mask))
        v = mask & ~np.isnan(metres)  # valid depth is never NaN; inf, 0 and tiny ones are here
        for fs in (0.5, 33.0, 1e6):
            kf = narf_kernels.support_px(v, metres, np.float32(fs))
            np.log2(kf, out=kf)
            k0, t, used = narf_kernels.scale_split(kf, v, 7)
            k0_ref, t_ref, used_ref = ref.support_scales(v, metres, fs, 7)
            assert same_bits(k0, k0_ref) and same_bits(t, t_ref) and np.array_equal(used, used_ref)


@pytest.mark.parametrize("mode", ["nearest", "reflect", "constant"])
def test_gaussian_blur_keeps_scipys_signed_zeros(mode) -> None:
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(7)
    for shape in ((1, 1), (3, 2), (5, 40), (9, 9), (40, 31)):
        for sigma, truncate in ((0.8, 4.0), (2.0, 4.0), (3.0, 4.0), (48**0.5, 3.0)):
            img = _awkward(rng, shape, 2.0)
            img[~np.isfinite(img)] = -0.0
            new, old = (
                common.gaussian_blur(img, sigma, truncate, mode),
                gaussian_filter(img, sigma, mode=mode, truncate=truncate),
            )
            assert same_bits(new, old), (shape, sigma)


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (31, 17), (128, 128)])
def test_max_doh_is_the_per_pixel_kernel_bit_for_bit(shape) -> None:
    rng = np.random.default_rng(shape[1])
    for scale in (1.0, 1e-20, 1e20):
        L = _awkward(rng, shape, scale)
        L[~np.isfinite(L)] = 0.5
        out = (rng.random(shape) * 0.01).astype(np.float32)
        out[rng.random(shape) < 0.3] = 0.0
        new, old = out.copy(), out.copy()
        keypoints._max_doh(L, np.float32(16.0), new)
        ref.max_doh(L, np.float32(16.0), old)
        assert same_bits(new, old)


@pytest.mark.parametrize("shape", [(4, 1, 1), (3, 5, 7), (4, 64, 48), (3, 2, 9), (4, 33, 20)])
def test_pyramid_steps_are_the_numpy_versions_bit_for_bit(shape) -> None:
    rng = np.random.default_rng(sum(shape))
    x = _awkward(rng, shape, 2.0)
    x[~np.isfinite(x)] = 0.25
    assert same_bits(keypoints._half(x), reference_narf._half(x))
    assert same_bits(keypoints._double(x[0]), reference_narf.double(x[0]))
    b = x.copy()
    b[0] = np.abs(b[0]) * (rng.random(shape[1:]) > 0.3)
    b[0][rng.random(shape[1:]) < 0.2] = np.float32(1e-6)
    tensor = np.abs(x[:3])
    tensor[2] = x[min(2, shape[0] - 1)]
    tensor[:, rng.random(shape[1:]) < 0.2] = 0.0
    with np.errstate(all="ignore"):
        if shape[0] == 4:
            assert same_bits(keypoints._surface_change(b), reference_narf._surface_change(b))
        assert same_bits(keypoints._isotropy(tensor), reference_narf._isotropy(tensor))


@pytest.mark.parametrize("size", [1, 3, 5, 9, 41])
def test_box_blur_along_rows_is_the_row_by_row_running_sum_bit_for_bit(size) -> None:
    rng = np.random.default_rng(size)
    for shape in ((64, 48), (7, 5), (3, 40), (1, 1), (13, 2), (6, 1), (5, 5)):
        x = _awkward(rng, shape, 3.0)
        x[~np.isfinite(x)] = -0.0
        assert same_bits(keypoints._box_cols(x, size), ref.box_cols(x, size)), shape
