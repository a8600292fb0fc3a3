"""Planning views of a posed capture on the real 7-Scenes capture: views at exactly the capture cameras, the
alignment score separating the raw depth-camera poses from the fitted colour camera (SOURCE.md) on every frame
and dropping 2-degree perturbations, views.min_alignment, fixated views from capture positions."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from services.core.domain.jobspec import JobSpec
from services.core.domain.plan import PlanError, plan_from_json, plan_to_json
from services.core.domain.plan_cues import point_info
from services.core.ingest.capture.model import CaptureFrame
from services.core.ingest.capture.photos import Photo, load_photo
from services.core.ingest.loading import load_space
from services.scheduler.planning import make_plan, space_rng
from services.scheduler.planning.alignment import alignment_score
from services.scheduler.planning.visibility import MeshQueries

KITCHEN = Path(__file__).resolve().parents[3] / "../shared/scenes/7scenes_redkitchen"
# SOURCE.md's fitted colour camera: K (integer pixel centres: +0.5 here) and the colour-from-depth translation
COLOUR_K = np.array([[526.0, 0.0, 324.5], [0.0, 526.0, 235.5], [0.0, 0.0, 1.0]])
COLOUR_FROM_DEPTH = np.array([-0.035, 0.010, 0.0])


@pytest.fixture(scope="module")
def kitchen():
    return load_space(KITCHEN)


def _plan(space, **spec):
    return make_plan(space, JobSpec.model_validate(spec), space_rng(0, "kitchen"), "kitchen")


@pytest.fixture(scope="module")
def capture_plan(kitchen):
    """Views at every capture camera, 32 px, unrefined (read only)."""
    return _plan(kitchen, cameras={"mode": "capture"}, views={"resolution": 32})


def colour_camera(frame: CaptureFrame) -> CaptureFrame:
    """The frame as SOURCE.md's fitted colour camera sees it (same photo)."""
    depth_from_colour = np.eye(4)
    depth_from_colour[:3, 3] = -COLOUR_FROM_DEPTH
    return CaptureFrame(frame.name, frame.image, frame.width, frame.height, COLOUR_K, "none", (),
                        frame.camera_to_world @ depth_from_colour)


def turned(frame: CaptureFrame, degrees: float, axis: int) -> CaptureFrame:
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    R = np.eye(3)
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    c2w = frame.camera_to_world.copy()
    c2w[:3, :3] = c2w[:3, :3] @ R
    return CaptureFrame(frame.name, frame.image, frame.width, frame.height, frame.K, "none", (), c2w)


def test_exact_views_at_every_capture_camera(kitchen):
    plan = _plan(kitchen, cameras={"mode": "capture"}, views={"resolution": 64})
    assert len(plan.views) == 100 and plan.capture["frames"] == 100
    for view in plan.views:
        frame = kitchen.capture.frames[view.camera_idx]
        np.testing.assert_allclose(view.world_to_camera, frame.world_to_camera, atol=1e-12)
        assert view.fov == pytest.approx(2 * np.arctan(239.5 / 585))  # the photo's inscribed square
        info = point_info(plan, view)
        assert info["alignment_score"] == view.alignment and info["photo_coverage"] == pytest.approx(1.0)
        # the point of interest is on the optical axis (image centre)
        point = plan.points[view.point_idx].position
        cam = view.world_to_camera[:3, :3] @ point + view.world_to_camera[:3, 3]
        assert abs(cam[0]) < 1e-6 * cam[2] and abs(cam[1]) < 1e-6 * cam[2]
    again = plan_from_json(plan_to_json(plan))
    assert [v.alignment for v in again.views] == [v.alignment for v in plan.views]
    hist = plan.capture["alignment"]["histogram"]
    assert sum(hist["counts"]) == 100


def frame_scores(q: MeshQueries, frame: CaptureFrame, photo: Photo) -> tuple:
    """(raw, colour, [perturbed x 4]) scores of one frame."""
    def score(f: CaptureFrame) -> float | None:
        return alignment_score(q, photo, f, f.world_to_camera, f.inscribed_fov())

    fitted = colour_camera(frame)
    return (
        score(frame), score(fitted), [score(turned(fitted, d, axis)) for axis in (0, 1) for d in (-2.0, 2.0)],
    )


@pytest.fixture(scope="module")
def scores_of(kitchen):
    """frame index -> frame_scores, each frame scored once for the module (the every-frame test reuses the
    every-tenth-frame test's scores)."""
    q = MeshQueries(kitchen.mesh)
    done: dict[int, tuple] = {}

    def scores(i: int) -> tuple:
        if i not in done:
            frame = kitchen.capture.frames[i]
            done[i] = frame_scores(q, frame, load_photo(str(kitchen.capture.image_path(frame)), frame))
        return done[i]

    return scores


def separation(kitchen, scores_of, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Scores of every stride-th frame: raw depth camera, fitted colour camera, and the colour camera turned
    by 2 degrees up, down, left and right (n, 4)."""
    picked = range(0, len(kitchen.capture.frames), stride)
    raw, colour, perturbed = zip(*(scores_of(i) for i in picked), strict=True)
    names = [kitchen.capture.frames[i].name for i in picked]
    return tuple(np.array(x, dtype=float) for x in (raw, colour, perturbed)) + (names,)  # type: ignore[return-value]


def check_separation(raw, colour, perturbed, names) -> None:
    assert np.isfinite(raw).all() and np.isfinite(colour).all() and np.isfinite(perturbed).all()
    # The fitted colour camera is one global fit; on frame 800 the raw depth camera lines up better (an
    # overlay of the cast edges on the photo shows it: Kinect colour and depth are not exposed at the same
    # instant, and the camera moves), so that frame is the one allowed exception.
    worse = [names[i] for i in np.flatnonzero(colour <= raw)]
    assert set(worse) <= {"frames/frame-000800"}, worse
    assert np.median(colour) > np.median(raw) + 0.2
    # turned 2 degrees, a view scores lower: on every frame against the mean of the four directions, and in at
    # least 90% of single turns (one direction can make up part of a frame's own residual misregistration)
    assert (colour > perturbed.mean(axis=1)).all(), np.flatnonzero(colour <= perturbed.mean(axis=1))
    assert (colour[:, None] > perturbed).mean() >= 0.9


def test_alignment_separates_raw_colour_and_perturbed_on_every_tenth_frame(kitchen, scores_of):
    check_separation(*separation(kitchen, scores_of, 10))


@pytest.mark.slow
def test_alignment_separates_raw_colour_and_perturbed_on_every_frame(kitchen, scores_of):
    check_separation(*separation(kitchen, scores_of, 1))


def test_min_alignment_drops_views_below_it(kitchen, capture_plan):
    base = capture_plan
    scores = np.array([v.alignment for v in base.views])
    cut = float(np.median(scores))
    plan = _plan(kitchen, cameras={"mode": "capture"}, views={"resolution": 32, "min_alignment": cut})
    assert len(plan.views) == int((scores >= cut).sum())
    assert all(v.alignment >= cut for v in plan.views)
    assert "alignment" in plan.shortfall and plan.capture["dropped"]["alignment"] == int((scores < cut).sum())


def test_fixated_views_from_capture_positions(kitchen):
    plan = _plan(kitchen, cameras={"mode": "capture", "capture_views": "fixated"}, points={"count": 10},
                 views={"resolution": 32, "min_photo_coverage": 0.6})
    centres = np.stack([f.center for f in kitchen.capture.frames])
    assert plan.views
    for view in plan.views:
        np.testing.assert_allclose(view.position, centres[view.camera_idx], atol=1e-9)
        assert view.photo_coverage >= 0.6
    loose = _plan(kitchen, cameras={"mode": "capture", "capture_views": "fixated"}, points={"count": 10},
                  views={"resolution": 32, "min_photo_coverage": 0.0})
    assert len(loose.views) > len(plan.views) and plan.capture["dropped"]["photo_coverage"] > 0


def test_capture_mode_without_a_capture_is_refused(scenes_dir):
    bunny = load_space(scenes_dir / "stanford_bunny" / "bun_zipper_res2.ply")
    with pytest.raises(
        PlanError, match="needs a posed capture.*at most 2 folders down beside a single mesh file"
    ):
        _plan(bunny, cameras={"mode": "capture"})


def test_refining_the_colour_camera_moves_towards_the_fitted_one(kitchen):
    """Maximising the alignment score from the raw depth camera finds a shorter focal length like SOURCE.md's
    fitted colour camera (526 / 585 = 0.90) and a better score; the record says what was refined."""
    from services.scheduler.planning.refine import refine_colour_camera

    correction, record = refine_colour_camera(
        MeshQueries(kitchen.mesh), kitchen.capture, frames=6, halvings=1
    )
    assert 0.85 <= correction.focal_scale <= 0.95, record
    assert record["score_after"] > record["score_before"] + 0.2
    assert "focal length" in record["refined"] and record["frames_scored"] == 6


@pytest.mark.slow
def test_capture_refine_plan_and_worker_agree(kitchen, capture_plan, monkeypatch):
    from services.core.ingest.capture.calibration import ColourCorrection
    from services.scheduler.planning import refine
    from services.worker.inputs.photos import painter_for

    # What the plan does with a refinement is the subject here, not the search (test_refining_... above): the
    # real search on 6 frames with 1 halving, as there, instead of 12 frames and 3 halvings (28 -> 5 CPU s).
    monkeypatch.setattr(refine, "refine_colour_camera",
                        functools.partial(refine.refine_colour_camera, frames=6, halvings=1))
    spec = JobSpec.model_validate(
        {"cameras": {"mode": "capture", "capture_refine": True}, "views": {"resolution": 32}}
    )
    plan = make_plan(kitchen, spec, space_rng(0, "kitchen"), "kitchen")
    refined = plan.capture["refined"]
    corrected = ColourCorrection.from_dict(refined["correction"]).capture(kitchen.capture)
    for view in plan.views:
        np.testing.assert_allclose(
            view.world_to_camera, corrected.frames[view.camera_idx].world_to_camera, atol=1e-12
        )
    painter = painter_for(kitchen, spec, refined)
    # the worker finds each refined camera
    assert all(len(painter.frames_at(v.position)) == 1 for v in plan.views)
    base = capture_plan
    assert np.median([v.alignment for v in plan.views]) > np.median([v.alignment for v in base.views]) + 0.2


def test_photo_textured_views_need_photo_coverage(kitchen):
    """views.rgb_source photos on generated cameras: views whose surface the photos saw too little of are
    dropped."""
    from services.scheduler.planning.capture_views import textured_coverage

    spec = {
        "cameras": {"mode": "generate", "max_count": 20, "min_spacing_m": 0.3},
        "points": {"count": 12, "min_views": 1}, "views": {"resolution": 32, "rgb_source": "photos"},
    }
    loose = _plan(kitchen, **{**spec, "views": {**spec["views"], "min_photo_coverage": 0.0}})
    strict = _plan(kitchen, **{**spec, "views": {**spec["views"], "min_photo_coverage": 0.6}})
    q = MeshQueries(kitchen.mesh)
    cov_loose = textured_coverage(q, kitchen.capture, np.stack([v.world_to_camera for v in loose.views]),
                                  np.array([v.fov for v in loose.views]))
    cov_strict = textured_coverage(q, kitchen.capture, np.stack([v.world_to_camera for v in strict.views]),
                                   np.array([v.fov for v in strict.views]))
    assert (cov_loose < 0.6).any() and len(strict.views) < len(loose.views)
    assert (cov_strict >= 0.6).all()
    assert "min_photo_coverage" in strict.shortfall
