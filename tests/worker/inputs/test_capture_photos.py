"""Capture views end to end in the worker (real Cycles renders): the rgb cue of a view at a capture camera is
the photo undistorted and resampled (equal to the mesh-rendered rgb within JPEG noise), and every other cue is
rendered at exactly the capture camera (depth and normals equal an independent ray cast there)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from services.core.domain.jobspec import JobSpec
from services.scheduler.planning import make_plan, space_rng
from services.worker.executor import make_context, produce
from services.worker.inputs.photos import PhotoPainter
from services.worker.inputs.space_cache import SpaceContext
from services.worker.passes import ViewGeometry
from tests.fixtures.raycast import cast_normals_cam, raycast, smooth_mask

pytestmark = pytest.mark.bpy

CUES = ["passes", "rgb", "depth_zbuffer", "normal", "mask_valid", "mask_photo"]


def png(data: bytes) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(data)))


@pytest.fixture(scope="module")
def capture_renders(banana_capture_folder):
    _, space, frames = banana_capture_folder
    spec = JobSpec.model_validate({"cameras": {"mode": "capture"}, "views": {"resolution": 96}})
    plan = make_plan(space, spec, space_rng(0, "banana"), "banana")
    photo_space = SpaceContext(key="photos", mesh=space.mesh, photos=PhotoPainter(space.capture))
    mesh_space = SpaceContext(key="mesh", mesh=space.mesh)
    out = []
    for view in plan.views:
        with_photo = make_context(photo_space, view, CUES, plan=plan)
        with_mesh = make_context(mesh_space, view, ["passes", "rgb"], plan=plan)
        out.append((view, {c: produce(c, with_photo) for c in CUES}, png(produce("rgb", with_mesh))))
    return space, frames, plan, out


def test_views_are_exactly_the_capture_cameras(capture_renders):
    space, frames, plan, renders = capture_renders
    assert len(plan.views) == len(frames)
    for view in plan.views:
        frame = frames[view.camera_idx]
        np.testing.assert_allclose(view.world_to_camera, np.linalg.inv(frame.camera_to_world), atol=1e-9)
        assert plan.cameras[view.camera_idx].source == "capture"
        assert view.alignment is not None and view.photo_coverage == pytest.approx(1.0)


def test_rgb_from_photos_equals_mesh_rgb_within_jpeg_noise(capture_renders):
    space, _, _, renders = capture_renders
    for view, files, mesh_rgb in renders:
        g = ViewGeometry.of(view)
        smooth = smooth_mask(raycast(space.mesh, g))
        photo_rgb = png(files["rgb"]).astype(np.float64)
        covered = png(files["mask_photo"]) == 255
        assert covered.all()  # the inscribed field of view lies inside the undistorted photo
        err = np.abs(photo_rgb - mesh_rgb.astype(np.float64))[smooth]
        assert smooth.sum() > 300
        assert np.median(err) <= 3, np.median(err)
        assert np.percentile(err, 90) <= 12, np.percentile(err, 90)
        # and not by accident: the photo of another capture camera does not match
        other = png(renders[(renders.index((view, files, mesh_rgb)) + 1) % len(renders)][1]["rgb"]).astype(
            float
        )
        assert np.median(np.abs(other - mesh_rgb)[smooth]) > 2 * max(np.median(err), 1)


def test_depth_and_normals_are_the_raycast_at_the_capture_camera(capture_renders):
    space, frames, _, renders = capture_renders
    for view, files, _ in renders:
        g = ViewGeometry(np.linalg.inv(frames[view.camera_idx].camera_to_world), view.fov, view.resolution)
        cast = raycast(space.mesh, g)
        smooth = smooth_mask(cast)
        z = png(files["depth_zbuffer"]).astype(np.float64) / 512.0
        assert (
            np.mean(np.abs(z[smooth] - cast.z[smooth]) <= np.maximum(1 / 512, 0.005 * cast.z[smooth])) >= 0.99
        )
        px = png(files["normal"]).astype(np.float64) / 255.0
        n = np.stack([1 - 2 * px[..., 0], 2 * px[..., 1] - 1, 2 * px[..., 2] - 1], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        cos = np.einsum("hwc,hwc->hw", n, cast_normals_cam(space.mesh, cast, g))[smooth]
        assert np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))) < 2.0
        np.testing.assert_array_equal(png(files["mask_valid"]) == 255, z < 65535 / 512.0)


def test_photo_textured_novel_view(capture_renders, banana_path):
    """rgb_source photos for a camera at no capture centre: the photos projected onto the surface the view
    sees equal the mesh rgb where a photo saw it; the rest (seen by no photo) is masked."""
    from services.core.domain.camera import look_at
    from services.core.domain.plan import CameraPose, PlannedView, PointOfInterest, SpacePlan
    from services.worker.inputs.phototexture import PhotoTexturer

    space, frames, _, _ = capture_renders
    mesh = space.mesh
    centre = mesh.bounds.mean(axis=0)
    radius = float(np.linalg.norm(mesh.extents)) / 2
    between = (frames[0].camera_to_world[:3, 3] + frames[1].camera_to_world[:3, 3]) / 2
    side = (between - centre) * np.array([1.0, 1.0, 0.0])
    side = side / np.linalg.norm(side) + np.array([0.0, 0.0, -0.3])  # from below: the photos look down
    position = centre + 1.4 * radius * side / np.linalg.norm(side)
    W = look_at(position, centre)
    view = PlannedView(0, 0, 0, W, np.radians(50), 0.0, 96, 0.3, True)
    plan = SpacePlan("b", (CameraPose(0, position, "generated", "c"),),
                     (PointOfInterest(0, centre, np.array([0, 0, 1.0]), "p", (0,)),), (view,))
    painter = PhotoPainter(space.capture, texture=PhotoTexturer(mesh, space.capture, k=2))
    textured = make_context(SpaceContext(key="tex", mesh=mesh, photos=painter), view,
                            ["passes", "rgb", "mask_photo", "mask_valid"], plan=plan)
    mesh_rgb = png(
        produce("rgb", make_context(SpaceContext(key="m", mesh=mesh), view, ["passes", "rgb"], plan=plan))
    )
    rgb = png(produce("rgb", textured)).astype(np.float64)
    covered = png(produce("mask_photo", textured)) == 255
    valid = png(produce("mask_valid", textured)) == 255
    smooth = smooth_mask(raycast(mesh, ViewGeometry.of(view)))
    assert not (covered & ~valid).any()  # only surface a photo saw is coloured
    assert covered[valid].mean() > 0.3  # the photos see much of what this view sees
    assert covered[valid].mean() < 0.98  # ... but not the underside: masked, not invented
    assert (rgb[~covered] == 0).all()
    err = np.abs(rgb - mesh_rgb)[covered & smooth]
    assert np.median(err) <= 4 and np.percentile(err, 90) <= 20, (np.median(err), np.percentile(err, 90))
