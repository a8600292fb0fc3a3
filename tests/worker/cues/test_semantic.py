"""Semantic cues (services/worker/cues/semantic.py): labels from the pass set, refused without labels."""

from __future__ import annotations

import numpy as np
import pytest

from services.worker.context import SemanticsUnavailableError, ViewContext
from services.worker.executor import produce
from tests.fixtures.raycast import cube_scene, decode_png, raycast, raycast_passes

RES = 64


def test_semantic_cues_need_labels() -> None:
    mesh, g = cube_scene()
    ctx = ViewContext(g, passes=raycast_passes(mesh, g))
    for cue in ("segment_semantic", "segment_instance", "segment_panoptic"):
        with pytest.raises(SemanticsUnavailableError, match="unlabelled"):
            produce(cue, ctx)
    cls = np.arange(len(mesh.faces), dtype=np.int32) // 2 + 1
    inst = np.arange(len(mesh.faces), dtype=np.int32) + 300
    cast = raycast(mesh, g)
    ctx = ViewContext(g, passes=raycast_passes(mesh, g, face_class=cls, face_instance=inst))
    sem = decode_png(produce("segment_semantic", ctx))
    ins = decode_png(produce("segment_instance", ctx)).astype(np.int64)
    np.testing.assert_array_equal(sem[cast.hit], cls[cast.tri[cast.hit]])
    np.testing.assert_array_equal(ins[cast.hit], inst[cast.tri[cast.hit]])
    assert np.all(sem[~cast.hit] == 0) and np.all(ins[~cast.hit] == 0)
    pan = decode_png(produce("segment_panoptic", ctx)).astype(np.int64)
    np.testing.assert_array_equal(pan[..., 0], sem)
    np.testing.assert_array_equal(pan[..., 1] * 256 + pan[..., 2], ins)
    # Negative ids ("unlabelled" in some scans) become 0; ids the encoding cannot hold are refused by name.
    neg = ViewContext(g, passes=raycast_passes(mesh, g, face_class=cls * 0 - 1, face_instance=inst))
    assert np.all(decode_png(produce("segment_semantic", neg)) == 0)
    big = ViewContext(g, passes=raycast_passes(mesh, g, face_class=cls + 300, face_instance=inst))
    with pytest.raises(ValueError, match="class id 30[0-9] in view exceeds 255"):
        produce("segment_semantic", big)
