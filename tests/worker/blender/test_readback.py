"""Passes read from the render result in memory (services.worker.blender.readback): no EXR is written, and
every array of the pass set is bit for bit the one the EXR readback gives for the same render."""

from __future__ import annotations

import os

import numpy as np
import pytest

from services.core.domain.camera import look_at
from services.core.domain.jobspec import CueParams
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import OPTIONAL_ARRAYS, RENDER_PASSES, ViewGeometry
from services.worker.process.kernel_warm_up import synthetic_room

pytestmark = pytest.mark.bpy

VIEWS = [
    ViewGeometry(look_at(np.array([3.6, 2.6, 1.6]), np.array([1.0, 0.8, 0.5])), np.radians(90.0), 96),
    ViewGeometry(look_at(np.array([0.5, 0.4, 2.2]), np.array([3.0, 2.0, 0.3])), np.radians(70.0), 80),
]


@pytest.fixture(scope="module")
def space():
    mesh = synthetic_room(np.random.default_rng(1))
    rng = np.random.default_rng(2)
    nf = len(mesh.faces)
    s = SpaceContext(key="readback", mesh=mesh, face_class=rng.integers(-3, 40, nf),
                     face_instance=rng.integers(-1, 5000, nf))
    yield s
    s.close()


def test_the_worker_scene_reads_passes_from_memory_bit_identical_to_the_exr(space: SpaceContext) -> None:
    import bpy

    from services.worker.blender import render as r

    memory = [space.render(g, CueParams(), passes=RENDER_PASSES) for g in VIEWS]
    bs = space.scene()
    assert os.listdir(bs._tmp) == []  # nothing written
    exr = bpy.data.scenes.new("exr")
    exr.collection.objects.link(bs.object)
    exr.collection.objects.link(bs.camera)
    exr.camera = bs.camera
    path = os.path.join(bs._tmp, "exr.exr")
    r.configure_scene(exr, bs.options, path, r.pass_aovs(len(space.mesh.faces)))
    exr.view_layers[0].use_pass_normal = False
    assert any((~p.hit).any() for p in memory)  # the window's empty pixels in a view
    for g, got in zip(VIEWS, memory, strict=True):
        want = r.render_passes(exr, bs.camera, g, RENDER_PASSES, bs.labels, bs.face_normals)
        assert os.path.exists(path)
        for name in ("depth_z", "rgb", *OPTIONAL_ARRAYS[:-1]):
            a, b = getattr(got, name), getattr(want, name)
            assert a is not None and a.dtype == b.dtype and a.shape == b.shape, name
            assert a.tobytes() == b.tobytes(), name
        assert got.hit.mean() > 0.5
        assert np.isfinite(got.curvature[got.hit]).all() and np.abs(got.curvature[got.hit]).max() > 0.1


def test_renders_outside_a_capture_copy_nothing_and_the_engine_is_wrapped_once(space: SpaceContext) -> None:
    import cycles

    from services.worker.blender import readback

    bs = space.scene()
    wrapped = cycles.CyclesRender.render
    assert readback.install() and cycles.CyclesRender.render is wrapped
    with readback.capture() as channels:
        pass
    bs.render_floor(VIEWS[0])
    assert channels == {}
    with readback.capture() as channels:
        bs.render_floor(VIEWS[1])  # the floor's result: Combined, Depth and Normal, rows top-down
    assert channels["ViewLayer.Normal.X"].shape == (80, 80) and "ViewLayer.Combined.A" in channels
    depth = channels["ViewLayer.Depth"]
    assert depth.dtype == np.float32 and (depth < 1e9).mean() > 0.9
