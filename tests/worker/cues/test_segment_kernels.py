"""The segment cues' compiled steps (issue 20: the normalized-cut driver's per-split arithmetic, the 2.5d
feature image) give the labels of the numpy code they replaced bit for bit, on real views of both real rooms:
the ICL living room (untextured: its colour segmentation is one segment, so the colour cue is also run on the
rendered normal image) and the 7-Scenes kitchen (a textured TSDF scan), planner views rendered by Cycles.
Reference: tests/fixtures/reference_ncuts.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.core.domain.jobspec import JobSpec
from services.core.ingest.loading import load_space
from services.scheduler.planning import make_plan, space_rng
from services.worker.context import ViewContext
from services.worker.cues import segmentation
from services.worker.cues.common import valid
from services.worker.cues.edges import occlusion_response
from services.worker.cues.felzenszwalb import SORT_LEVELS
from services.worker.cues.ncuts import _best_split, normalized_cuts
from services.worker.cues.registry import cue_value
from services.worker.cues.segmentation import (
    _boundary,
    _gather,
    features25d,
    nearest_in_mask,
    region_graph,
    superpixels,
)
from services.worker.executor import make_context
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import ViewGeometry, ViewPasses
from tests.fixtures import reference_felzenszwalb, reference_ncuts, reference_segmentation
from tests.fixtures.segment_agreement import previous_definitions
from tests.worker.cues.test_equivalence import colour_from_normals

pytestmark = pytest.mark.bpy  # the views are Cycles renders

RESOLUTION = 256
N_VIEWS = 3
# name -> (space under scenes_dir, load_space frame); the kitchen's up is minus its gravity-direction.txt.
ROOMS = {
    "icl_livingroom": ("icl_livingroom", {}),
    "7scenes_redkitchen": (
        "7scenes_redkitchen/mesh_tsdf_2cm_from_1000frames.ply", {"up": (0.009, -0.904, -0.427)},
    ),
}


@pytest.fixture(scope="module", params=list(ROOMS))
def room_views(request: pytest.FixtureRequest, scenes_dir: Path) -> list[ViewPasses]:
    """Pass sets of N_VIEWS planner views of the room (spread over its points), rendered by Cycles."""
    path, frame = ROOMS[request.param]
    loaded = load_space(scenes_dir / path, **frame)
    plan = make_plan(loaded, JobSpec(), space_rng(0, request.param), request.param)  # type: ignore[arg-type]
    views = plan.views[:: len(plan.views) // N_VIEWS][:N_VIEWS]
    space = SpaceContext.from_loaded(loaded, key=f"{request.param}-segment-kernels")
    try:
        return [make_context(space, ViewGeometry(v.world_to_camera, v.fov, RESOLUTION), ["passes"]).passes
                for v in views]
    finally:
        space.close()


def test_segment_cues_are_the_numpy_versions_bit_for_bit(room_views) -> None:
    """With the definition the numpy versions have (float64 eigenvectors, no link threshold): the shipped one
    is held to the noise-floor bound instead (test_equivalence.py)."""
    counts = []
    for p in room_views + [colour_from_normals(p) for p in room_views]:
        for cue in ("segment_unsup2d", "segment_unsup25d"):
            with previous_definitions():
                new = cue_value(ViewContext(None, passes=p), cue)
            old = getattr(reference_ncuts, cue)(ViewContext(None, passes=p))
            assert new.dtype == old.dtype == np.uint16
            assert np.array_equal(new, old), cue
            counts.append(int(new.max()))
    assert sum(c > 10 for c in counts) >= len(room_views)  # real segmentations, not one-segment views only


class _ReferenceSuperpixels:
    """tests/fixtures/reference_felzenszwalb.py's kernel (pixel loops, two edge-end arrays) behind the
    interface segmentation.superpixels uses."""

    def __init__(self, features: np.ndarray, scale: float, sigma: float, *, connectivity: int, levels: int):
        assert (connectivity, levels) == (8, SORT_LEVELS)  # the only definition the reference has
        self._fz = reference_felzenszwalb.Felzenszwalb(features, scale, sigma)

    def count(self, min_size: int) -> int:
        return int(self._fz.labels(min_size).max()) + 1

    def labels(self, min_size: int) -> np.ndarray:
        return self._fz.labels(min_size)


def test_shipped_segment_cues_take_the_reference_superpixels_bit_for_bit(room_views, monkeypatch) -> None:
    """The shipped definition's labels on real views are those made with the reference Felzenszwalb kernel
    swapped in: the compiled kernel's row-wise distances and packed edges change no label."""
    counts = []
    for p in room_views + [colour_from_normals(p) for p in room_views]:
        for cue in ("segment_unsup2d", "segment_unsup25d"):
            new = cue_value(ViewContext(None, passes=p), cue)
            with monkeypatch.context() as m:
                m.setattr(segmentation, "Felzenszwalb", _ReferenceSuperpixels)
                old = cue_value(ViewContext(None, passes=p), cue)
            assert np.array_equal(new, old), cue
            counts.append(int(new.max()))
    assert sum(c > 10 for c in counts) >= len(room_views)  # real segmentations, not one-segment views only


def test_features25d_is_the_numpy_version_bit_for_bit(room_views) -> None:
    for p in room_views:
        new = features25d(ViewContext(None, passes=p))
        old = reference_ncuts.features25d(ViewContext(None, passes=p))
        assert new.dtype == old.dtype == np.float32
        assert np.array_equal(new.view(np.uint32), old.view(np.uint32))


def test_every_split_of_a_view_is_the_numpy_versions_bit_for_bit(room_views) -> None:
    """Each candidate split (the node mask or None) of the room views' region graphs, recursion and all."""
    splits = 0
    for p in room_views:
        ctx = ViewContext(None, passes=p)
        params = ctx.params
        mask = valid(ctx)
        iy, ix = nearest_in_mask(ctx, mask)
        features = _gather(features25d(ctx), mask, iy, ix)
        ids = superpixels(features, params.segment2d_scale, 0.0, params.segment2d_min_size,
                          params.segment_max_superpixels)
        W = region_graph(ids, features * 255.0, params.segment_ncut_sigma)
        assert np.array_equal(
            normalized_cuts(W, params.segment_ncut_thresh, params.segment_num_cuts),
            reference_ncuts.normalized_cuts(W, params.segment_ncut_thresh, params.segment_num_cuts),
        )
        # The root split at several thresholds and cut counts (more kinds of ties and of outcomes).
        for thresh in (0.005, 0.05, 1.0):
            for num_cuts in (1, 10, 37):
                new = _best_split(W, thresh, num_cuts)
                old = reference_ncuts.best_split(W, thresh, num_cuts)
                assert (new is None) == (old is None)
                if new is not None:
                    assert np.array_equal(new, old)
                    splits += 1
    assert splits >= len(room_views)


def test_boundary_and_region_graph_are_the_numpy_versions_bit_for_bit(room_views) -> None:
    for p in room_views:
        ctx = ViewContext(None, passes=p)
        occ = occlusion_response(ctx)
        for we in (1.0, 0.37, 0.0):
            top = max(float(occ.max()), 1e-6)
            new = _boundary(occ, np.float32(we), np.float32(top))
            old = np.clip(we * occ / top, 0.0, None)
            assert new.dtype == old.dtype == np.float32
            assert np.array_equal(new.view(np.uint32), old.view(np.uint32))
        features = features25d(ctx)
        ids = superpixels(features, ctx.params.segment2d_scale, 0.0, 50, 512)
        for b in (None, new, _boundary(occ, np.float32(1.0), np.float32(max(float(occ.max()), 1e-6)))):
            W = region_graph(ids, features * 255.0, ctx.params.segment_ncut_sigma, b)
            assert np.array_equal(W, reference_segmentation.region_graph(ids, features * 255.0,
                                                                           ctx.params.segment_ncut_sigma, b))
