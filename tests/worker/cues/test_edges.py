"""Edge and keypoint cues (services/worker/cues/edges.py, keypoints.py) on a ray-cast cube."""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.executor import produce
from tests.fixtures.raycast import cube_scene, decode_png, raycast, raycast_passes

RES = 64


def test_edges_and_keypoints() -> None:
    mesh, g = cube_scene()
    cast = raycast(mesh, g)
    p = raycast_passes(mesh, g)
    # Texture: a bright square in the middle of the image.
    p.rgb[:] = 40
    p.rgb[48:80, 48:80] = 220
    ctx = ViewContext(g, passes=p)
    et = decode_png(produce("edge_texture", ctx)).astype(np.float64)
    assert et[64, 48] > 1000 and et[64, 64] == 0 and et[10, 10] == 0
    eo = decode_png(produce("edge_occlusion", ctx)).astype(np.float64)
    assert np.all(eo[~cast.hit] == 0)
    sil = cast.hit & ~np.pad(cast.hit, 1)[2:, 1:-1]  # bottom silhouette pixels
    assert eo[sil].mean() > 10 * max(eo[32:96, 32:96].mean(), 1.0)
    kp2 = decode_png(produce("keypoints2d", ctx)).astype(np.float64)
    # The square is a blob: the strongest 2D keypoint response lies inside it, around its centre.
    y, x = np.unravel_index(np.argmax(kp2), kp2.shape)
    assert 52 <= y <= 76 and 52 <= x <= 76
    kp3 = decode_png(produce("keypoints3d", ctx)).astype(np.float64)
    assert np.all(kp3[~cast.hit] == 0)
    # The cube's near corner (image centre) is a 3D keypoint; a face centre is not.
    corner = kp3[60:68, 60:68].mean()
    uv_face = np.array([[40, 64], [88, 64], [64, 96]])
    face = min(kp3[v - 3:v + 3, u - 3:u + 3].mean() for u, v in uv_face)
    assert corner > 3 * face and corner > 5000
