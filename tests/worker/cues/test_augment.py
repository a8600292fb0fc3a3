"""The 3D augmentation cues against their physics, each checked by an independent computation: the thin-lens
blur spot of a point source (image distances from the lens equation), fog transmittance exp(-beta d) on
ray-cast distances, the smear of a moving camera (f t / Z), the inverse-square flash; per-view draws seeded by
the plan and recorded in augment_params; the JobSpec's distributions and their refusals."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pydantic import ValidationError

from services.core.domain.augment_spec import AugmentParams, Dist
from services.core.domain.jobspec import CueParams, JobSpec
from services.datasets.decode import decode_cue
from services.worker.context import ViewContext
from services.worker.cues.augment_params import draw, linear_to_srgb, srgb_to_linear
from services.worker.cues.flash import flash
from services.worker.cues.fog import fog
from services.worker.cues.motion_blur import motion_blur
from services.worker.cues.refocus import coc_radius_px, refocus
from services.worker.executor import produce
from tests.fixtures.raycast import plane_scene, raycast, raycast_passes

FOCAL_MM, SENSOR_MM, WIDTH = 50.0, 36.0, 256


def blur_spot_radius_px(depth_m: float, focus_m: float, f_number: float) -> float:
    """Radius on the sensor of a point's blur disc, from first principles: the lens equation 1/f = 1/d + 1/v
    gives where the point images (v) and where the sensor sits (v_s, focused at S); the cone of light through
    the aperture (diameter f/N) cut by the sensor is a disc of diameter A |v - v_s| / v."""
    f = FOCAL_MM / 1000
    v, v_s = 1 / (1 / f - 1 / depth_m), 1 / (1 / f - 1 / focus_m)
    diameter = (f / f_number) * abs(v - v_s) / v
    return 0.5 * diameter / (SENSOR_MM / 1000) * WIDTH


def spot(depth_m: float, focus_m: float, f_number: float) -> np.ndarray:
    image = np.zeros((WIDTH, WIDTH, 3))
    image[WIDTH // 2, WIDTH // 2] = 1.0  # a point source
    depth = np.full((WIDTH, WIDTH), depth_m)
    radius = coc_radius_px(depth, focus_m=focus_m, f_number=f_number, focal_mm=FOCAL_MM, sensor_mm=SENSOR_MM,
                           width_px=WIDTH)
    return refocus(image, radius)[..., 0]


@pytest.mark.parametrize("depth_m", [0.6, 3.0, 8.0])
def test_refocus_spreads_a_point_over_its_circle_of_confusion(depth_m: float) -> None:
    out = spot(depth_m, focus_m=1.0, f_number=1.4)
    expected = blur_spot_radius_px(depth_m, 1.0, 1.4)
    # a uniform disc: light / plateau = its area, pi r^2
    measured = math.sqrt(out.sum() / out.max() / math.pi)
    # radii are quantised (0.5 px)
    assert expected > 2 and abs(measured - expected) < 0.55, (measured, expected)
    assert out.sum() == pytest.approx(1.0, abs=1e-9)  # the light is spread, not lost


def test_refocus_leaves_the_focus_plane_sharp_and_blurs_elsewhere() -> None:
    rng = np.random.default_rng(0)
    texture = rng.random((WIDTH, WIDTH, 3))
    depth = np.full((WIDTH, WIDTH), 1.0)
    depth[:, WIDTH // 2:] = 6.0  # the right half is far behind the focus plane
    radius = coc_radius_px(
        depth, focus_m=1.0, f_number=1.4, focal_mm=FOCAL_MM, sensor_mm=SENSOR_MM, width_px=WIDTH
    )
    out = refocus(texture, radius)
    # in focus: exactly the scan's colour
    assert np.array_equal(out[:, : WIDTH // 2], texture[:, : WIDTH // 2])
    assert radius[0, -1] == pytest.approx(blur_spot_radius_px(6.0, 1.0, 1.4)) and radius[0, -1] > 4
    right = out[:, WIDTH // 2 + 16:]
    # blurred: the texture's contrast averages out
    assert right.std() < 0.5 * texture[:, WIDTH // 2 + 16:].std()
    assert abs(right.mean() - texture[:, WIDTH // 2 + 16:].mean()) < 0.02


def test_fog_transmittance_follows_exp_minus_beta_d_on_ray_cast_distances() -> None:
    plane, view = plane_scene(tilt_deg=60.0, dist=4.0, resolution=48)
    cast = raycast(plane, view)
    beta, airlight = 0.3, 0.8
    colour = np.full((48, 48, 3), 0.1)
    out = fog(colour, np.where(cast.hit, cast.t, np.inf), beta_per_m=beta, airlight=airlight)
    t = (airlight - out[..., 0]) / (airlight - 0.1)
    np.testing.assert_allclose(t[cast.hit], np.exp(-beta * cast.t[cast.hit]), rtol=1e-9)
    assert np.allclose(out[~cast.hit], airlight)  # nothing seen: the fog itself


def _vertical_line(depth: float, translation: tuple[float, float, float], focal: float) -> np.ndarray:
    image = np.zeros((64, 64, 1))
    image[:, 32] = 1.0
    out, _ = motion_blur(image, np.full((64, 64), depth), np.asarray(translation), focal, 128)
    return out[32, :, 0]


def test_sideways_motion_smears_by_f_t_over_z() -> None:
    focal, tx = 60.0, 0.1
    for depth in (1.0, 2.0):
        row = _vertical_line(depth, (tx, 0.0, 0.0), focal)
        length = focal * tx / depth  # pixels the image moves during the exposure
        lit = np.flatnonzero(row > 1e-9)
        assert abs((lit.max() - lit.min()) - length) <= 1.5, (depth, lit, length)
        assert row.sum() == pytest.approx(1.0, abs=1e-6)
        assert abs(np.average(np.arange(64), weights=row) - 32) < 0.5  # centred: the exposure is symmetric


def test_forward_motion_smears_radially_and_keeps_the_centre() -> None:
    image = np.zeros((65, 65, 1))
    image[32, 32] = 1.0  # on the optical axis (pixel centre 32.5 = W / 2)
    image[32, 52] = 1.0  # to the right of it
    out, samples = motion_blur(image, np.full((65, 65), 2.0), np.array([0.0, 0.0, 0.3]), 60.0, 128)
    assert samples > 2
    assert out[32, 32, 0] > 0.9  # the centre does not move
    right = out[:, 40:, 0]
    rows, cols = np.nonzero(right > 1e-6)
    assert set(rows.tolist()) <= {31, 32, 33} and cols.max() - cols.min() >= 2  # along the radius only


def test_flash_falls_off_with_the_square_of_the_distance() -> None:
    plane, view = plane_scene(tilt_deg=0.0, dist=2.0, resolution=32)
    cast = raycast(plane, view)
    cosine = np.einsum("hwc,c->hw", -cast.dirs, np.array([0.0, 0.0, 1.0]))  # the plane's normal is +z
    colour = np.full((32, 32, 3), 0.2)
    out = flash(colour, cosine, np.where(cast.hit, cast.t, np.inf), ambient=0.3, power_m2=1.5)
    gain = out[..., 0] / 0.2
    np.testing.assert_allclose(gain, 0.3 + 1.5 * cosine / cast.t**2, rtol=1e-9)


def _context(params: CueParams) -> ViewContext:
    plane, view = plane_scene(tilt_deg=40.0, dist=3.0, resolution=32)
    return ViewContext(view, params, passes=raycast_passes(plane, view, grey=150))


def test_cues_through_the_registry_match_their_recorded_draws() -> None:
    spec = JobSpec.model_validate({"params": {"augment": {
        "fog_beta_per_m": 0.25, "fog_airlight": {"dist": "uniform", "low": 0.5, "high": 0.9},
        "refocus_focus_quantile": 0.5}}})
    ctx = _context(spec.params)
    doc = json.loads(produce("augment_params", ctx))
    assert doc["rgb_fog"]["beta_per_m"] == 0.25 and 0.5 <= doc["rgb_fog"]["airlight"] <= 0.9
    assert doc["rgb_refocus"]["focus_distance_m"] == pytest.approx(
        float(np.median(ctx.passes.depth_z)), rel=1e-6
    )
    fogged = decode_cue("rgb_fog", produce("rgb_fog", ctx))  # decoded like rgb: 3 x H x W in [0, 1]
    assert fogged.shape == (3, 32, 32) and fogged.dtype == np.float32
    cast = raycast(*plane_scene(tilt_deg=40.0, dist=3.0, resolution=32))
    t = np.exp(-0.25 * cast.t)
    expected = linear_to_srgb(srgb_to_linear(np.full((32, 32, 3), 150)) * t[..., None]
                              + doc["rgb_fog"]["airlight"] * (1 - t[..., None]))
    assert np.abs(np.rint(fogged.transpose(1, 2, 0) * 255) - expected).max() <= 1
    for cue in ("rgb_refocus", "rgb_motion_blur", "rgb_flash"):
        assert decode_cue(cue, produce(cue, ctx)).shape == (3, 32, 32)
    # the same view draws the same values every time; another pose draws others
    assert draw(_context(spec.params)) == doc
    other = ViewContext(plane_scene(dist=3.5)[1], spec.params, passes=ctx.passes)
    assert draw(other)["rgb_fog"]["airlight"] != doc["rgb_fog"]["airlight"]


def test_distributions_sample_within_bounds_and_bad_ones_are_refused() -> None:
    rng = np.random.default_rng(1)
    log = Dist(dist="log_uniform", low=0.01, high=1.0)
    values = [log.sample(rng) for _ in range(2000)]
    assert min(values) >= 0.01 and max(values) <= 1.0 and np.median(values) == pytest.approx(0.1, rel=0.15)
    assert Dist.model_validate(0.3).sample(rng) == 0.3
    for bad, message in [({"fog_airlight": {"dist": "uniform", "low": 0.9, "high": 0.2}}, "at most high"),
                         ({"fog_beta_per_m": {"dist": "log_uniform", "low": 0.0, "high": 1.0}}, "low > 0"),
                         ({"motion_z_m": 3.0}, "motion_z_m must lie in"),
                         ({"refocus_max_coc_px": 500}, "less than or equal to 64")]:
        with pytest.raises(ValidationError, match=message):
            AugmentParams.model_validate(bad)


def test_previews_of_the_augmentations() -> None:
    from services.datasets.previews import preview_array

    ctx = _context(CueParams())
    for cue in ("rgb_refocus", "rgb_fog", "rgb_motion_blur", "rgb_flash", "augment_params"):
        img = preview_array(cue, produce(cue, ctx))
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3, cue
        assert cue != "augment_params" or img.std() > 0  # its values drawn as text
