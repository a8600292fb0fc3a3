"""Issue 20's faster kernels give the same values as the code they replaced (reference versions kept here)."""

from __future__ import annotations

from unittest.mock import patch

import numpy as np
import pytest

from services.core.domain.cues import CURVATURE_FLAT, NORMAL_BACKGROUND
from services.core.domain.jobspec import CueParams
from services.worker.context import ViewContext
from services.worker.cues import ncuts
from services.worker.cues.basic import _curvature_pixels, _normal_pixels
from services.worker.cues.common import gaussian_blur, sobel_xy, valid
from services.worker.cues.feature_transform import nearest_site
from services.worker.cues.felzenszwalb import Felzenszwalb
from services.worker.cues.keypoints import _blur, _double, doh_response, narf_interest
from services.worker.cues.ncuts import _pairwise_sum, normalized_cuts, second_eigenvector
from services.worker.cues.registry import cue_value
from services.worker.cues.segmentation import (
    _gather,
    _relabel,
    _uniform_in_mask,
    features25d,
    region_graph,
    segment_unsup2d,
)
from tests.fixtures import reference_felzenszwalb, reference_narf, reference_ncuts, reference_segmentation
from tests.fixtures.raycast import cube_scene, make_room, raycast_passes, room_view
from tests.fixtures.reference_segmentation import reference_relabel


def reference_double(x: np.ndarray) -> np.ndarray:
    """keypoints' bilinear 2x upsampling before issue 20 (numpy take/stack)."""
    for axis in (0, 1):
        n = x.shape[axis]
        prev = np.take(x, np.r_[0, 0:n - 1], axis=axis)
        nxt = np.take(x, np.r_[1:n, n - 1], axis=axis)
        pair = np.stack([0.75 * x + 0.25 * prev, 0.75 * x + 0.25 * nxt], axis=axis + 1)
        x = pair.reshape(x.shape[:axis] + (2 * n,) + x.shape[axis + 1:])
    return x


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (31, 17), (128, 128)])
def test_double_is_bit_identical_to_the_numpy_version(shape) -> None:
    x = (np.random.default_rng(shape[0]).random(shape) * 3.7).astype(np.float32)
    new, old = _double(x), reference_double(x)
    assert new.dtype == old.dtype == np.float32
    assert np.array_equal(new, old)


def test_relabel_matches_the_unique_based_version() -> None:
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 40, (50, 60)) * 7  # sparse label values, some missing
    mask = rng.random((50, 60)) > 0.2
    assert np.array_equal(_relabel(labels, mask), reference_relabel(labels, mask))
    assert np.array_equal(_relabel(labels, np.zeros_like(mask)), np.zeros(labels.shape, np.uint16))


def test_normalized_cuts_splits_disconnected_parts_without_mixing_them() -> None:
    # Two 3-node cliques and a 4-node clique with no links between them: one segment each (no split of a
    # clique, whose cut would cost far above the threshold).
    W = np.zeros((10, 10))
    for part in (range(0, 3), range(3, 6), range(6, 10)):
        for i in part:
            for j in part:
                W[i, j] = 1.0
    W[0, 3] = W[3, 0] = 1e-30  # numerically absent link
    seg = normalized_cuts(W, thresh=0.005, num_cuts=10)
    assert len(set(seg[:3])) == len(set(seg[3:6])) == len(set(seg[6:])) == 1
    assert len({seg[0], seg[3], seg[6]}) == 3

    # A link below link_eps counts as absent: the graph splits there without an eigenproblem.
    W[0, 3] = W[3, 0] = 5e-4
    solve, sizes = ncuts.second_eigenvector, []

    def counted(A: np.ndarray, *args: str) -> np.ndarray:
        sizes.append(len(A))
        return solve(A, *args)

    with patch.object(ncuts, "second_eigenvector", counted):
        seg = normalized_cuts(W, thresh=0.005, num_cuts=10, link_eps=1e-3)
        assert len(set(seg[:3])) == len(set(seg[3:6])) == len(set(seg[6:])) == 1
        assert len({seg[0], seg[3], seg[6]}) == 3
        assert sorted(sizes) == [3, 3, 4]  # each clique's own check, nothing larger
        sizes.clear()
        normalized_cuts(W, thresh=0.005, num_cuts=10)  # the default keeps the weak link: the triples solved
        assert 6 in sizes


def test_position_cue_is_the_pass_sets_position_bit_for_bit() -> None:
    mesh, g = cube_scene()
    passes = raycast_passes(mesh, g)
    ctx = ViewContext(g, passes=passes)
    cue_value(ctx, "normal")  # the memoised rays shared with other cues
    new, old = cue_value(ctx, "position"), passes.position_world()
    assert np.isnan(new).any() and np.isfinite(new).any()
    assert np.array_equal(new.view(np.uint32), old.view(np.uint32))


@pytest.mark.parametrize("with_boundary", [False, True])
def test_region_graph_is_bit_identical_to_the_numpy_version(with_boundary) -> None:
    rng = np.random.default_rng(7)
    # Blocky labels (regions of 6 x 6 pixels, ids shuffled) so regions have several neighbours and long
    # borders.
    blocks = rng.permutation(100).reshape(10, 10)
    labels = np.kron(blocks, np.ones((6, 6), dtype=np.int64))
    features = rng.random((60, 60, 4)).astype(np.float32) * 255.0
    boundary = rng.random((60, 60)).astype(np.float32) if with_boundary else None
    new = region_graph(labels, features, 255.0, boundary)
    old = reference_segmentation.region_graph(labels, features, 255.0, boundary)
    assert np.count_nonzero(new - np.diag(np.diag(new))) > 200  # real links, not an empty comparison
    assert np.array_equal(new, old)


def reference_doh_response(g: np.ndarray, sigmas: tuple[float, ...]) -> np.ndarray:
    """keypoints2d's response before issue 20 (padded copy and in-place numpy arithmetic per scale)."""
    from scipy.ndimage import gaussian_filter

    out = np.zeros(g.shape, dtype=np.float32)
    L, prev = g.astype(np.float32), 0.0
    P = np.empty((g.shape[0] + 2, g.shape[1] + 2), dtype=np.float32)
    for s in sorted(sigmas):
        inc = float(np.sqrt(max(s * s - prev * prev, 0.0)))
        if inc > 0:
            L = gaussian_filter(L, inc, mode="nearest", truncate=3.0)
        prev = s
        P[1:-1, 1:-1] = L
        P[0, 1:-1], P[-1, 1:-1] = L[0], L[-1]
        P[:, 0], P[:, -1] = P[:, 1], P[:, -2]
        lxx = P[1:-1, 2:] + P[1:-1, :-2]
        lxx -= 2 * L
        lyy = P[2:, 1:-1] + P[:-2, 1:-1]
        lyy -= 2 * L
        lxy = P[2:, 2:] - P[2:, :-2]
        lxy -= P[:-2, 2:]
        lxy += P[:-2, :-2]
        lxx *= lyy
        lxy *= lxy
        lxx -= lxy * 0.0625
        lxx *= s**4
        np.maximum(out, lxx, out=out)
    return out


def test_doh_response_is_bit_identical_to_the_numpy_version() -> None:
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:96, 0:80]
    g = (0.5 + 0.4 * np.sin(x / 5.0) * np.cos(y / 7.0) + 0.05 * rng.random((96, 80))).astype(np.float32)
    sigmas = (1.0, 2.0, 4.0, 8.0)
    new, old = doh_response(g, sigmas), reference_doh_response(g, sigmas)
    assert new.max() > 0.01  # blobs found, not an empty comparison
    assert np.array_equal(new, old)


@pytest.mark.parametrize("mode", ["nearest", "reflect", "constant"])
@pytest.mark.parametrize("sigma,truncate", [(0.8, 4.0), (1.0, 4.0), (2.0, 4.0), (1.0, 3.0), (12**0.5, 3.0),
                                            (48**0.5, 3.0)])
def test_gaussian_blur_is_scipys_gaussian_filter_bit_for_bit(mode, sigma, truncate) -> None:
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(int(sigma * 10))
    for shape, scale in (((64, 48), 1.0), ((5, 7), 300.0), ((1, 30), 1e-3), ((37, 33), 1.0)):
        img = (rng.random(shape) * scale).astype(np.float32)
        new = gaussian_blur(img, sigma, truncate, mode)
        old = gaussian_filter(img, sigma, mode=mode, truncate=truncate)
        assert new.dtype == np.float32 and np.array_equal(new, old), shape


@pytest.mark.parametrize("radius", [1, 2, 4, 9])
def test_box_blur_is_scipys_uniform_filter_bit_for_bit(radius) -> None:
    from scipy.ndimage import uniform_filter

    rng = np.random.default_rng(radius)
    for shape in ((4, 64, 48), (3, 7, 5), (1, 3, 40), (30, 20)):
        x = rng.random(shape).astype(np.float32)
        x[..., :2, :] = 0.0  # zero rows: the running sums pass through exact zeros
        old = x
        size = radius | 1
        for _ in range(3):
            old = uniform_filter(old, (1,) * (x.ndim - 2) + (size, size), mode="constant")
        new = _blur(x, radius)
        assert new.dtype == np.float32 and new.shape == x.shape and np.array_equal(new, old), shape


def test_normal_pixels_are_the_numpy_expressions_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    n = rng.uniform(-1, 1, (64, 64, 3)).astype(np.float32)
    n[0] = ((np.arange(64, dtype=np.float32)[:, None] + 0.5) / 255 * 2 - 1)  # at the rounding boundaries
    n[1, :3] = [[1, 1, 1], [-1, -1, -1], [0, 0, 0]]
    seen = rng.random((64, 64)) > 0.1
    px = np.rint(255.0 * (0.5 + 0.5 * n * np.array([-1.0, 1.0, 1.0], dtype=np.float32)))
    old = np.where(seen[..., None], np.clip(px, 0, 255), NORMAL_BACKGROUND).astype(np.uint8)
    assert np.array_equal(_normal_pixels(n, seen), old)


def test_curvature_pixels_are_the_numpy_expressions_bit_for_bit() -> None:
    rng = np.random.default_rng(1)
    k = rng.normal(0, 40, (50, 50, 2)).astype(np.float32)
    k[0, 0], k[0, 1, 0], k[0, 2, 1] = np.nan, np.inf, -np.inf
    k[1, :, 0] = np.linspace(-40, 40, 50)  # across the clip limits and the rounding steps
    seen = rng.random((50, 50)) > 0.1
    kmax = 1.0 / 0.03
    px = np.rint((np.clip(np.nan_to_num(k), -kmax, kmax) / kmax + 1.0) * CURVATURE_FLAT)
    old = np.zeros((50, 50, 3), dtype=np.uint8)
    old[..., :2] = np.where(seen[..., None], px, 0)
    assert np.array_equal(_curvature_pixels(k, seen, np.float32(kmax)), old)


def test_one_colour_surface_takes_the_shortcut_to_the_labels_felzenszwalb_gives() -> None:
    mesh, g = cube_scene()
    passes = raycast_passes(mesh, g, grey=128)  # one colour on every face
    ctx = ViewContext(g, passes=passes)
    assert _uniform_in_mask(passes.rgb.astype(np.float32), passes.hit)
    new = segment_unsup2d(ctx)
    old = reference_segmentation.segment_unsup2d(ViewContext(g, passes=passes))  # skimage + dense cuts
    assert np.array_equal(new, old) and np.array_equal(new, passes.hit.astype(np.uint16))
    rgb = passes.rgb.copy()
    rgb[passes.hit.nonzero()[0][-1], passes.hit.nonzero()[1][-1]] = 7  # one pixel differs: no shortcut
    assert not _uniform_in_mask(rgb.astype(np.float32), passes.hit)
    assert _uniform_in_mask(rgb.astype(np.float32), np.zeros_like(passes.hit))


def test_sobel_is_scipys_bit_for_bit() -> None:
    from scipy.ndimage import sobel

    rng = np.random.default_rng(9)
    for shape, scale in (((64, 48), 1.0), ((1, 1), 1.0), ((1, 7), 300.0), ((6, 1), 1e-3), ((33, 20), 5.0)):
        img = ((rng.random(shape) - 0.5) * scale).astype(np.float32)
        img.flat[0] = 0.0
        gx, gy = sobel_xy(img)
        for new, axis in ((gx, 1), (gy, 0)):
            old = sobel(img, axis=axis, mode="nearest")
            assert new.dtype == np.float32 and np.array_equal(new.view(np.uint32), old.view(np.uint32)), (
                shape, axis,
            )


def _test_image(rng: np.random.Generator, h: int, w: int, c: int) -> np.ndarray:
    """Blocks of flat colour (exact ties: zero-weight edges), a ramp and quantised noise (many equal
    weights)."""
    blocks = rng.random((max(1, h // 8) + 1, max(1, w // 8) + 1, c))
    img = np.kron(blocks, np.ones((8, 8, 1)))[:h, :w]
    img = img + np.linspace(0, 0.3, w)[None, :, None] * (rng.random(c) > 0.5)
    noisy = rng.random((h, w)) > 0.7
    img[noisy] += np.round(rng.normal(0, 0.05, (int(noisy.sum()), c)), 2)
    return img.astype(np.float32)


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (7, 1), (37, 53), (96, 80)])
@pytest.mark.parametrize("channels,sigma", [(3, 0.8), (4, 0.0), (1, 0.0)])
def test_felzenszwalb_is_the_previous_kernel_bit_for_bit(shape, channels, sigma) -> None:
    img = _test_image(np.random.default_rng(shape[0] * 31 + channels), *shape, channels)
    new, old = Felzenszwalb(img, 200.0, sigma), reference_felzenszwalb.Felzenszwalb(img, 200.0, sigma)
    for min_size in (1, 5, 50, 400):
        a, b = new.labels(min_size), old.labels(min_size)
        assert a.dtype == b.dtype and np.array_equal(a, b), min_size
        assert new.count(min_size) == int(a.max()) + 1
    if shape[0] * shape[1] > 1000:
        assert 1 < new.labels(5).max() < new.labels(1).max()  # real merges at both passes, not a trivial case


def test_felzenszwalb_connectivity_4_leaves_out_the_diagonal_edges() -> None:
    """A checkerboard: its like colours touch only diagonally, so the 8-connected grid joins each colour into
    one region at zero cost and the 4-connected grid joins nothing (every edge it has crosses the full colour
    step, above a tiny scale's threshold). bench/cues/segment_stability.py measures the 4-connected grid on
    real rooms."""
    board = (np.indices((6, 8)).sum(axis=0) % 2).astype(np.float32)[..., None]
    eight = Felzenszwalb(board, 1e-3, 0.0).labels(1)
    four = Felzenszwalb(board, 1e-3, 0.0, connectivity=4).labels(1)
    assert np.array_equal(eight, (board[..., 0] != board[0, 0, 0]).astype(np.int64))
    assert np.array_equal(four, np.arange(48).reshape(6, 8))
    img = _test_image(np.random.default_rng(3), 37, 53, 3)
    assert np.array_equal(Felzenszwalb(img, 200.0, 0.8, connectivity=8, levels=1 << 16).labels(50),
                          reference_felzenszwalb.Felzenszwalb(img, 200.0, 0.8).labels(50))  # the defaults
    assert not np.array_equal(Felzenszwalb(img, 200.0, 0.8, levels=16).labels(1),
                              # a coarser sort orders the edges otherwise
                              Felzenszwalb(img, 200.0, 0.8).labels(1))
    with pytest.raises(ValueError, match="connectivity"):
        Felzenszwalb(board, 1.0, 0.0, connectivity=6)


def _narf_views() -> list[ViewContext]:
    """A raycast room (boxes, a sphere: folds, corners, occlusion borders) with depth holes and a far cut, and
    a cube on an empty background."""
    room = make_room()[0]
    g = room_view(96)
    passes = raycast_passes(room, g)
    depth = passes.depth_z.copy()
    depth[40:52, 10:30] = np.inf  # a hole in the surface: borders all around it
    passes.depth_z = depth
    mesh, cube = cube_scene()
    return [ViewContext(g, passes=passes), ViewContext(g, CueParams(max_depth_m=2.5), passes=passes),
            ViewContext(cube, passes=raycast_passes(mesh, cube))]


def test_narf_interest_is_the_numpy_version_bit_for_bit() -> None:
    for ctx in _narf_views():
        new, old = narf_interest(ctx), reference_narf.narf_interest(ctx)
        assert new.dtype == old.dtype == np.float32
        assert np.array_equal(new.view(np.uint32), old.view(np.uint32))
        assert new.max() > 0.05 and (new == 0).mean() < 0.99  # real interest, not an empty comparison


@pytest.mark.parametrize("n", [3, 4, 17, 64, 230])
def test_second_eigenvector_is_scipys_eigh_bit_for_bit(n) -> None:
    from scipy.linalg import eigh

    rng = np.random.default_rng(n)
    w = rng.random((n, n)) * (rng.random((n, n)) < 0.2)
    w = w + w.T + np.eye(n)
    d = w.sum(axis=1)
    dis = 1.0 / np.sqrt(d)
    A = (np.diag(d) - w) * dis[:, None] * dis[None, :]  # as a normalized cut builds it
    old = eigh(A, subset_by_index=[0, 1], driver="evr")[1][:, 1]
    old32 = eigh(A.astype(np.float32), subset_by_index=[0, 1], driver="evr")[1][:, 1]
    assert old32.dtype == np.float32
    for _ in range(2):  # the second call takes the cached workspace sizes
        new = second_eigenvector(A)
        assert np.array_equal(new, old)
        new32 = second_eigenvector(A, "float32")
        assert new32.dtype == np.float64 and np.array_equal(new32, old32.astype(np.float64))


def _site_masks() -> list[np.ndarray]:
    rng = np.random.default_rng(11)
    masks = [
        rng.random(shape) < p
        for shape, p in (
            ((1, 1), 1.0), ((1, 9), 0.3), ((9, 1), 0.3), ((37, 53), 0.01), ((64, 64), 0.5), ((50, 70), 0.003),
            ((96, 80), 0.9),
        )
    ]
    hole = np.ones((60, 80), bool)
    hole[10:50, 20:70] = False  # a big hole: long runs with ties between its borders
    one = np.zeros((31, 31), bool)
    one[15, 15] = True  # every pixel's nearest is the one site; rows and columns without any
    grid = np.zeros((40, 40), bool)
    grid[::6, ::6] = True  # equidistant sites: ties everywhere
    return masks + [hole, one, grid, np.ones((5, 6), bool)]


def test_nearest_site_is_scipys_feature_transform_index_for_index() -> None:
    from scipy.ndimage import distance_transform_edt

    for mask in _site_masks():
        if not mask.any():
            mask.flat[0] = True
        old = distance_transform_edt(~mask, return_distances=False, return_indices=True)
        iy, ix = nearest_site(mask)
        assert iy.dtype == ix.dtype == np.int32
        assert np.array_equal(iy, old[0]) and np.array_equal(ix, old[1]), mask.shape
    assert (nearest_site(np.zeros((3, 4), bool))[0] == -1).all()


def test_background_fill_is_numpys_gather_at_the_nearest_sites() -> None:
    """The segment cues' fill (each pixel takes its nearest mask pixel's features) copies the mask pixels and
    gathers only the others: the same floats as features[iy, ix] for every pixel."""
    rng = np.random.default_rng(5)
    for mask in _site_masks():
        if not mask.any():
            continue
        features = rng.random((*mask.shape, 4)).astype(np.float32)
        iy, ix = nearest_site(mask)
        assert np.array_equal(_gather(features, mask, iy, ix), features[iy, ix]), mask.shape


@pytest.mark.parametrize(
    "n", [0, 1, 7, 8, 9, 127, 128, 129, 255, 256, 257, 1000, 4096, 8191, 8192, 8193, 20000]
)
def test_pairwise_sum_is_numpys_sum_bit_for_bit(n) -> None:
    rng = np.random.default_rng(n)
    for _ in range(5):
        a = rng.random((2, n)) * 10.0 ** rng.uniform(-6, 6, (2, n)) * rng.choice([-1.0, 1.0], (2, n))
        rows = a.sum(axis=1)  # a contiguous axis of a matrix (degrees) and a vector (their total)
        assert _pairwise_sum(a[0]) == rows[0] and _pairwise_sum(a[1]) == rows[1]
        assert _pairwise_sum(a[1]) == a[1].sum()
    assert _pairwise_sum(np.array([-0.0])) == 0.0 and not np.signbit(_pairwise_sum(np.array([-0.0])))


@pytest.mark.parametrize("seed", range(6))
def test_normalized_cuts_are_the_numpy_versions_bit_for_bit(seed) -> None:
    """Region graphs of blocky random label images (dense, sparse, with a disconnected part and a constant
    block, so splits, ties, refusals and component peeling all occur)."""
    rng = np.random.default_rng(seed)
    side = int(rng.integers(6, 22))
    blocks = rng.permutation(side * side).reshape(side, side)
    labels = np.kron(blocks, np.ones((4, 4), dtype=np.int64))
    features = (rng.random((side * 4, side * 4, 3)) * 40.0 + (rng.random((1, side * 4, 3)) * 200.0)).astype(
        np.float32
    )
    W = region_graph(labels, features, 255.0 * (1 + seed))
    if seed % 2:  # cut one node off numerically
        W[0, 1:] = W[1:, 0] = 1e-30
    for thresh, num_cuts in ((0.005, 10), (0.2, 10), (1.0, 3), (0.05, 1)):
        new = normalized_cuts(W, thresh, num_cuts)
        old = reference_ncuts.normalized_cuts(W, thresh, num_cuts)
        assert np.array_equal(new, old)
    assert len(np.unique(normalized_cuts(W, 0.2, 10))) > 1


def test_features25d_is_the_numpy_version_on_a_room_with_holes() -> None:
    ctxs = _narf_views()[:2]  # the room with a hole, then also cut at 2.5 m: pixels off valid depth
    for weights in ((1.0, 1.0, 1.0), (0.3, 2.5, 0.0), (0.0, 1.0, 1.0)):
        for ctx in ctxs:
            params = ctx.params.model_copy(update={"segment25d_weights": weights})
            new = features25d(ViewContext(ctx.view, params, passes=ctx.passes))
            old = reference_ncuts.features25d(ViewContext(ctx.view, params, passes=ctx.passes))
            assert new.dtype == old.dtype == np.float32
            assert np.array_equal(new.view(np.uint32), old.view(np.uint32))
    assert 0.05 < 1 - valid(ctxs[1]).mean() < 0.95  # the off-surface branch is compared too
