"""The parameters of the 3D augmentation cues, drawn once per view and stored as that view's `augment_params`.

Every parameter is drawn from its JobSpec distribution (params.augment) by a generator seeded from the view's
identity in the plan: its point's uuid (which the planner derives from the job's seed and the space's name)
and its view index. So the same job gives the same draws on every worker and on a retry, every augmentation
cue of a view reads the same values, and a reader finds them in the JSON file beside the images. Draws happen
in a fixed order, one per parameter, whichever cues a job asks for.

Shared helpers of the family: sRGB <-> linear light (the corruptions are physical, so they act on light, not
on sRGB codes) and the view's focal length in pixels.
"""

from __future__ import annotations

import hashlib
import math
from typing import TypedDict

import numpy as np

from services.core.domain.plan import PlannedView
from services.worker.context import ViewContext
from services.worker.cues.common import depth_m, valid
from services.worker.cues.registry import register

VERSION = 1


def view_generator(ctx: ViewContext) -> tuple[np.random.Generator, str]:
    """The view's generator and what seeded it ('<point uuid>/<view>', or the pose when there is no plan)."""
    view = ctx.view
    plan = ctx.plan
    if plan is not None and isinstance(view, PlannedView):
        point = next(p for p in plan.points if p.idx == view.point_idx)
        key = f"{point.uuid}/{int(view.v)}"
    else:  # a bare view (tests, previews): its pose and fov identify it
        g = ctx.geometry
        key = "pose:" + hashlib.sha256(np.asarray(g.world_to_camera, dtype=np.float64).tobytes()
                                       + np.float64(g.fov).tobytes()).hexdigest()[:32]
    seed = int.from_bytes(hashlib.sha256(f"augment/v{VERSION}/{key}".encode()).digest()[:8], "big")
    return np.random.default_rng(seed), key


class Refocus(TypedDict):
    focus_quantile: float
    focus_distance_m: float
    f_number: float
    focal_length_mm: float
    sensor_width_mm: float
    max_coc_px: float


class Fog(TypedDict):
    beta_per_m: float
    airlight: float


class MotionBlur(TypedDict):
    translation_m: list[float]
    frame: str
    max_samples: int


class Flash(TypedDict):
    ambient: float
    power_m2: float


class AugmentParams(TypedDict):
    """The augment_params JSON of a view: what each augmentation cue drew, and what seeded the draw."""

    version: int
    seeded_by: str
    rgb_refocus: Refocus
    rgb_fog: Fog
    rgb_motion_blur: MotionBlur
    rgb_flash: Flash


def focal_px(ctx: ViewContext) -> float:
    """Focal length in pixels of the square view: (W / 2) / tan(fov / 2)."""
    return 0.5 * ctx.resolution / math.tan(0.5 * ctx.geometry.fov)


def draw(ctx: ViewContext) -> AugmentParams:
    """The view's augmentation parameters (JSON-ready), memoised per view."""

    def compute() -> AugmentParams:
        spec = ctx.params.augment
        rng, key = view_generator(ctx)
        quantile = spec.refocus_focus_quantile.sample(rng)
        f_number = spec.refocus_f_number.sample(rng)
        beta = spec.fog_beta_per_m.sample(rng)
        airlight = spec.fog_airlight.sample(rng)
        motion = [spec.motion_x_m.sample(rng), spec.motion_y_m.sample(rng), spec.motion_z_m.sample(rng)]
        ambient = spec.flash_ambient.sample(rng)
        power = spec.flash_power_m2.sample(rng)
        v = valid(ctx)
        z = depth_m(ctx)[v]
        focus = float(np.quantile(z, quantile)) if z.size else float(ctx.params.max_depth_m)
        focal_mm = 0.5 * spec.refocus_sensor_width_mm / math.tan(0.5 * ctx.geometry.fov)
        return {
            "version": VERSION,
            "seeded_by": key,
            "rgb_refocus": {
                "focus_quantile": quantile, "focus_distance_m": focus, "f_number": f_number,
                "focal_length_mm": focal_mm, "sensor_width_mm": spec.refocus_sensor_width_mm,
                "max_coc_px": spec.refocus_max_coc_px,
            },
            "rgb_fog": {"beta_per_m": beta, "airlight": airlight},
            "rgb_motion_blur": {
                "translation_m": motion, "frame": "camera, OpenCV axes (x right, y down, z forward)",
                "max_samples": spec.motion_max_samples,
            },
            "rgb_flash": {"ambient": ambient, "power_m2": power},
        }

    return ctx.memo("augment_params", compute)


@register("augment_params")
def augment_params(ctx: ViewContext) -> AugmentParams:
    """JSON: the parameters every augmentation cue of this view used, and what seeded their draw."""
    return draw(ctx)


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """float32 linear light in [0, 1] of uint8 sRGB codes (IEC 61966-2-1)."""
    c = np.asarray(srgb, dtype=np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """uint8 sRGB codes of linear light (clipped to [0, 1])."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.rint(255.0 * s).astype(np.uint8)
