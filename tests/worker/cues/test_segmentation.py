"""Unsupervised segmentations (services/worker/cues/segmentation.py) on ray-cast pass sets."""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.executor import produce
from tests.fixtures.raycast import cube_scene, decode_png, raycast, raycast_passes

RES = 64


def test_segmentations_split_colours_and_faces() -> None:
    mesh, g = cube_scene()
    cast = raycast(mesh, g)
    p = raycast_passes(mesh, g)
    p.rgb[cast.hit] = [200, 40, 40]
    p.rgb[:, 64:][cast.hit[:, 64:]] = [40, 40, 200]
    ctx = ViewContext(g, passes=p)
    s2 = decode_png(produce("segment_unsup2d", ctx))
    assert s2.dtype == np.uint16 or s2.dtype == np.int32
    assert np.all(s2[~cast.hit] == 0)
    assert len(np.unique(s2[cast.hit])) == 2
    assert s2[64, 40] != s2[64, 90]
    s25 = decode_png(produce("segment_unsup25d", ctx))
    labels = np.unique(s25[cast.hit])
    assert 3 <= len(labels) <= 8 and 0 not in labels
    # Each of the three visible cube faces is dominated by one segment.
    for f in np.unique(mesh.face_normals[cast.tri[cast.hit]], axis=0):
        pix = cast.hit & np.all(np.isclose(mesh.face_normals[np.maximum(cast.tri, 0)], f), axis=-1)
        _, counts = np.unique(s25[pix], return_counts=True)
        assert counts.max() > 0.8 * pix.sum()


def test_superpixel_count_is_bounded() -> None:
    from services.worker.cues.segmentation import superpixels

    noise = np.random.default_rng(0).random((96, 96, 3)).astype(np.float32)
    labels = superpixels(noise, scale=1.0, sigma=0.0, min_size=1, max_count=40)
    assert labels.max() + 1 <= 40
