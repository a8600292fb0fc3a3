"""The pass set (services/worker/passes.py): its bytes round trip gives identical cues."""

from __future__ import annotations

import numpy as np

from services.worker.context import ViewContext
from services.worker.executor import produce
from services.worker.passes import ViewPasses
from tests.fixtures.raycast import cube_scene, raycast_passes

RES = 64


def test_passes_round_trip_gives_identical_cues() -> None:
    mesh, g = cube_scene()
    cls = np.arange(len(mesh.faces), dtype=np.int32)
    p = raycast_passes(mesh, g, face_class=cls, face_instance=cls)
    p.curvature = np.full((128, 128, 2), 3.0, dtype=np.float32)
    a = ViewContext(g, passes=p)
    data = produce("passes", a)
    b = ViewContext(None, passes=ViewPasses.from_bytes(data))
    for cue in ("rgb", "normal", "depth_euclidean", "principal_curvature", "segment_panoptic", "fragments",
                "keypoints3d", "position"):
        assert produce(cue, a) == produce(cue, b), cue
