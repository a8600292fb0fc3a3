"""The faster cue implementations of issue 10 give the same outputs as the ones they replaced, on real room
views.

Views: the real planner's cameras inside ../shared/scenes/icl_livingroom (a furnished room, every pixel a
surface) rendered by Cycles at 192 x 192. The room is untextured (its colour image is one grey), so the colour
segmentation is compared on the rendered normal image used as the colour input, and on the textured banana.
References: the implementations before issue 10, kept in tests/fixtures/reference_segmentation.py,
reference_keypoints2d.py and reference_keypoints3d.py.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest
from skimage.segmentation import felzenszwalb

from services.core.domain.cues import default_cues
from services.core.domain.exr import decode_exr_rgb
from services.core.domain.jobspec import CueParams, JobSpec
from services.core.ingest.loading import load_space
from services.datasets.decode import read_png
from services.scheduler.planning import make_plan, space_rng
from services.worker.context import ViewContext
from services.worker.cues.common import grey, to_uint16_scaled, valid
from services.worker.cues.encoding import encode_png, zlib_deflater
from services.worker.cues.felzenszwalb import Felzenszwalb
from services.worker.cues.keypoints import keypoints2d, narf_interest
from services.worker.cues.registry import cue_value
from services.worker.cues.segmentation import segment_unsup2d, segment_unsup25d
from services.worker.executor import make_context, produce
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import ViewGeometry, ViewPasses
from tests.fixtures import reference_keypoints2d, reference_keypoints3d, reference_segmentation
from tests.fixtures.exr import openexr_file_bytes
from tests.fixtures.raycast import decode_png, object_view
from tests.fixtures.segment_agreement import (
    adjusted_rand_index,
    equivalence_failures,
    imperceptibly_perturbed,
    noise_floor_failures,
    previous_definitions,
)

pytestmark = pytest.mark.bpy  # the views are Cycles renders

RESOLUTION = 192
N_VIEWS = 4


def test_adjusted_rand_index_is_one_for_relabelings_and_low_for_unrelated_partitions():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 5, (40, 40))
    assert adjusted_rand_index(a, (a + 3) * 7) == pytest.approx(1.0)
    assert abs(adjusted_rand_index(a, rng.integers(0, 5, (40, 40)))) < 0.05


@pytest.fixture(scope="module")
def room_passes(scenes_dir: Path) -> list[ViewPasses]:
    """Pass sets of N_VIEWS planner views of the real room (spread over its points), rendered by Cycles."""
    loaded = load_space(scenes_dir / "icl_livingroom")
    plan = make_plan(loaded, JobSpec(), space_rng(0, "icl_livingroom"), "icl_livingroom")
    views = plan.views[:: len(plan.views) // N_VIEWS][:N_VIEWS]
    space = SpaceContext.from_loaded(loaded, key="icl_livingroom-equivalence")
    try:
        return [make_context(space, ViewGeometry(v.world_to_camera, v.fov, RESOLUTION), ["passes"]).passes
                for v in views]
    finally:
        space.close()


@pytest.fixture(scope="module")
def banana_passes(banana_path: Path) -> list[ViewPasses]:
    loaded = load_space(banana_path)
    space = SpaceContext.from_loaded(loaded, key="banana-equivalence")
    try:
        return [make_context(space, object_view(loaded.mesh, d, RESOLUTION, fill=1.6), ["passes"]).passes
                for d in ([1.0, 0.3, 0.8], [-0.5, 1.0, 0.6])]
    finally:
        space.close()


def colour_from_normals(p: ViewPasses) -> ViewPasses:
    """The view with its rendered normal image as the colour image (the room scan itself is one grey)."""
    normal_png = produce("normal", ViewContext(None, passes=p))
    return ViewPasses(geometry=p.geometry, depth_z=p.depth_z, normal_world=p.normal_world,
                      rgb=decode_png(normal_png), face_index=p.face_index)


def assert_same_segmentation(old: np.ndarray, new: np.ndarray) -> None:
    assert not equivalence_failures(old, new), equivalence_failures(old, new)


def test_segment_unsup25d_matches_the_previous_implementation_on_room_views(room_passes):
    counts = []
    for p in room_passes:
        old = reference_segmentation.segment_unsup25d(ViewContext(None, passes=p))
        new = segment_unsup25d(ViewContext(None, passes=p))
        assert_same_segmentation(old, new)
        counts.append(int(old.max()))
    assert sum(counts) >= 10 * len(counts)  # real views with many segments, not a trivial comparison


def test_segment_unsup2d_matches_the_previous_implementation_on_colour_views(room_passes, banana_passes):
    counts = []
    for p in [colour_from_normals(p) for p in room_passes] + banana_passes:
        old = reference_segmentation.segment_unsup2d(ViewContext(None, passes=p))
        new = segment_unsup2d(ViewContext(None, passes=p))
        assert_same_segmentation(old, new)
        counts.append(int(old.max()))
    assert sum(counts) >= 5 * len(counts)


@pytest.mark.parametrize("cue", ["segment_unsup2d", "segment_unsup25d"])
def test_the_segment_definitions_move_labels_less_than_imperceptible_noise(cue, room_passes, banana_passes):
    """The acceptance rule of a cheaper segment definition (docs/conventions.md): over the same views, the
    shipped labels agree with the previous definition's (median and 10th percentile of the ARI) at least as
    well as the previous definition agrees with itself when its inputs move by one level of their stored
    encoding on 1% of the pixels. Views: the room's and the textured banana's; the colour cue runs on the
    room's normal image (the scan is one grey)."""
    views = room_passes if cue == "segment_unsup25d" else [colour_from_normals(p) for p in room_passes]
    views = views + banana_passes
    make = {"segment_unsup2d": segment_unsup2d, "segment_unsup25d": segment_unsup25d}[cue]
    with previous_definitions():
        previous = [make(ViewContext(None, passes=p)) for p in views]
        noisy = [make(ViewContext(None, passes=imperceptibly_perturbed(p, i))) for i, p in enumerate(views)]
    shipped = [make(ViewContext(None, passes=p)) for p in views]
    assert sum(int(a.max()) > 5 for a in previous) >= len(views) // 2  # real segmentations
    assert any(not np.array_equal(a, b) for a, b in zip(previous, noisy, strict=True))  # the noise moves them
    noise = [adjusted_rand_index(a, b) for a, b in zip(previous, noisy, strict=True)]
    agreement = [adjusted_rand_index(a, b) for a, b in zip(previous, shipped, strict=True)]
    failures = noise_floor_failures(agreement, noise)
    assert not failures, (failures, agreement, noise)
    for a, b in zip(previous, shipped, strict=True):
        assert np.array_equal(a == 0, b == 0)  # the same "no surface" pixels


def test_felzenszwalb_kernel_matches_skimage_superpixels(room_passes):
    params = CueParams()
    for p in room_passes:
        img = decode_png(produce("normal", ViewContext(None, passes=p))).astype(np.float32) / 255.0
        old = felzenszwalb(img, scale=params.segment2d_scale, sigma=params.segment2d_sigma,
                           min_size=params.segment2d_min_size, channel_axis=-1)
        new = Felzenszwalb(img, params.segment2d_scale, params.segment2d_sigma).labels(
            params.segment2d_min_size
        )
        assert new.shape == old.shape and new.min() == 0
        assert adjusted_rand_index(old, new) >= 0.9
        assert abs(int(new.max()) - int(old.max())) <= 0.2 * int(old.max())


def assert_same_response(old: np.ndarray, new: np.ndarray, min_corr: float, max_rel_err: float) -> None:
    """Two interest images agree: correlated, close in L2, and the strongest responses of the old stay
    strong."""
    assert np.corrcoef(old.ravel(), new.ravel())[0, 1] >= min_corr
    assert np.linalg.norm(new - old) <= max_rel_err * np.linalg.norm(old)
    top_old = old >= np.quantile(old, 0.99)
    assert np.mean(new[top_old] >= np.quantile(new, 0.95)) >= 0.9


def test_keypoints3d_matches_the_previous_implementation_on_room_views(room_passes):
    for p in room_passes:
        ctx = ViewContext(None, passes=p)
        new = narf_interest(ctx)
        assert np.all(new[~valid(ctx)] == 0)
        assert_same_response(reference_keypoints3d.narf_interest(ctx), new, 0.98, 0.2)


def test_keypoints2d_matches_the_previous_implementation_on_colour_views(room_passes, banana_passes):
    params = CueParams()
    for p in [colour_from_normals(p) for p in room_passes] + banana_passes:
        ctx = ViewContext(None, params, passes=p)
        old = reference_keypoints2d.doh_response(grey(ctx), params.keypoints2d_sigmas)
        new = keypoints2d(ctx).astype(np.float64)
        assert new.max() > 1000  # a view with blobs, not an empty comparison
        assert_same_response(
            to_uint16_scaled(old, params.keypoints2d_scale).astype(np.float64), new, 0.995, 0.05
        )


def test_every_png_cue_of_a_room_view_decodes_to_its_array(room_passes):
    """The PNG deflater trades size for speed only: ISA-L's files decode to the exact arrays, as the files of
    zlib level 1 + Z_RLE (the encoder before) do, 16-bit ones read explicitly as uint16."""
    before = zlib_deflater(1, zlib.Z_RLE)
    pngs = [c for c in default_cues(False) if c not in ("fragments", "position", "point_info", "nonfixated",
                                                        "vanishing_points")]
    for p in room_passes:
        ctx = ViewContext(None, CueParams(), passes=p)
        for cue in pngs:
            value, data = cue_value(ctx, cue), produce(cue, ctx)
            assert np.array_equal(read_png(data), value), cue
            assert np.array_equal(decode_png(data), decode_png(encode_png(value, before))), cue


def test_position_exr_of_a_room_view_decodes_to_its_array_bit_for_bit(room_passes):
    """The position (compiled loop) is the pass set's numpy arithmetic bit for bit, and its file the bytes
    OpenEXR's writer makes of it (written here without OpenEXR's temp file)."""
    for p in room_passes:
        ctx = ViewContext(None, CueParams(), passes=p)
        position = cue_value(ctx, "position")
        assert np.array_equal(position.view(np.uint32), p.position_world().view(np.uint32))
        data = produce("position", ctx)
        assert data == openexr_file_bytes(position)
        back = decode_exr_rgb(data)
        assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), position.view(np.uint32))


@pytest.mark.parametrize("resolution,fov", [(1, 1.0), (7, 0.3), (64, 2.1), (192, 1.35)])
def test_ray_directions_match_the_meshgrid_construction_exactly(resolution, fov):
    g = ViewGeometry(np.eye(4), fov, resolution)
    K = g.K
    u, v = np.meshgrid(np.arange(resolution) + 0.5, np.arange(resolution) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    assert np.array_equal(g.ray_directions_cam(), d / np.linalg.norm(d, axis=-1, keepdims=True))
