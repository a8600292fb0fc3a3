"""Cues read (almost) directly from the pass set: rgb, normal, depths, mask, reshading, curvature, position,
fragments, and the internal `passes` cue (encodings from the cue catalog; units in metres)."""

from __future__ import annotations

import numpy as np
from numba import njit

from services.core.domain.cues import CURVATURE_FLAT, NORMAL_BACKGROUND
from services.worker.context import ViewContext
from services.worker.cues.common import (
    euclidean_m,
    hit,
    normal_cam,
    position_world,
    ray_dirs_cam,
    to_uint16_depth,
    valid,
)
from services.worker.cues.registry import register
from services.worker.passes import NO_FACE, RENDER_PASSES

CURVATURE_BACKGROUND = 0  # R = G = B = 0 where nothing is seen (use mask_valid); B is always 0


@register("passes", passes=RENDER_PASSES)
def passes(ctx: ViewContext) -> bytes:
    """The whole pass set as .npz bytes (the worker-side cache every render cue can be made from)."""
    return ctx.passes.to_bytes()


@register("rgb")
def rgb(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3 unlit sRGB colour (texture / vertex colour / grey); black where nothing is seen."""
    return np.ascontiguousarray(ctx.passes.rgb, dtype=np.uint8)


@register("normal", passes={"normal"})
def normal(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3: 255*(0.5-0.5x, 0.5+0.5y, 0.5+0.5z) of the camera-space normal; 128 where nothing is
    seen."""
    return _normal_pixels(normal_cam(ctx), hit(ctx))


@njit(cache=True, nogil=True, error_model="numpy")
def _normal_pixels(n: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """rint(255 (0.5 + 0.5 n (-1, 1, 1))) clipped to 0..255 where seen, NORMAL_BACKGROUND elsewhere: the
    float32 operations of the numpy expression it replaced, in its order, in one pass."""
    h, w, _ = n.shape
    half, full = np.float32(0.5), np.float32(255.0)
    out = np.empty((h, w, 3), np.uint8)
    for y in range(h):
        for x in range(w):
            for c in range(3):
                if not seen[y, x]:
                    out[y, x, c] = NORMAL_BACKGROUND
                    continue
                v = half * n[y, x, c]
                if c == 0:
                    v = -v
                px = np.rint(full * (half + v))
                out[y, x, c] = np.uint8(min(max(px, np.float32(0.0)), np.float32(255.0)))
    return out


@register("depth_zbuffer")
def depth_zbuffer(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W optical-axis depth in 1/512 m (depth_units_per_m); 65535 = none or deeper than
    max_depth_m."""
    return to_uint16_depth(ctx, ctx.passes.depth_z, valid(ctx))


@register("depth_euclidean")
def depth_euclidean(ctx: ViewContext) -> np.ndarray:
    """uint16 H x W distance to the camera centre, same units; 65535 where depth_zbuffer is none (or
    overflow)."""
    return to_uint16_depth(ctx, euclidean_m(ctx), valid(ctx))


@register("mask_valid")
def mask_valid(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W: 255 where depth_zbuffer is valid, else 0."""
    return valid(ctx).view(np.uint8) * np.uint8(255)  # numpy's bools are the bytes 0 and 1


def reshading_intensity(ctx: ViewContext) -> np.ndarray:
    """float32 H x W: albedo * max(0, n.l), l = unit vector from the surface to the camera (no falloff)."""
    return _reshading_intensity(normal_cam(ctx), ray_dirs_cam(ctx), np.float32(ctx.params.reshading_albedo))


@njit(cache=True, nogil=True, error_model="numpy")
def _reshading_intensity(n: np.ndarray, d: np.ndarray, albedo: np.float32) -> np.ndarray:
    """albedo * maximum(-einsum(n (1, -1, -1), d), 0) per pixel: the float32 operations of the numpy
    expression it replaced, in its order (einsum adds left to right from 0, then the output's 0; numpy's
    maximum gives its second operand on ties, so -0 becomes +0, and keeps NaN), in one pass."""
    h, w, _ = n.shape
    out = np.empty((h, w), np.float32)
    zero, one, minus = np.float32(0.0), np.float32(1.0), np.float32(-1.0)
    for y in range(h):
        for x in range(w):
            dot = ((zero + (n[y, x, 0] * one) * d[y, x, 0]) + (n[y, x, 1] * minus) * d[y, x, 1]) \
                + (n[y, x, 2] * minus) * d[y, x, 2]
            cos = -(dot + zero)
            out[y, x] = albedo * (cos if cos > zero or np.isnan(cos) else zero)
    return out


@register("reshading", passes={"normal"})
def reshading(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W grey albedo lit by a point light at the camera, no indirect light, no distance falloff.

    Analytic from the rendered normal and the view ray: I = albedo * max(0, n.l) with l the unit vector from
    the surface point to the camera centre; px = round(255 * I); 0 where nothing is seen. The light's
    intensity does not fall off with distance (a 1/d^2 falloff would make the image depend on the scene's
    scale and need an exposure knob; shading is what this cue is about).
    """
    return _reshading_pixels(reshading_intensity(ctx), hit(ctx))


@njit(cache=True, nogil=True, error_model="numpy")
def _reshading_pixels(i: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """rint(255 i) as uint8 where seen, 0 elsewhere (i in [0, 1]: albedo <= 1; NaN, which numpy's cast makes
    0, too): the numpy expression it replaced, in one pass."""
    h, w = i.shape
    out = np.zeros((h, w), np.uint8)
    full = np.float32(255.0)
    for y in range(h):
        for x in range(w):
            v = np.rint(full * i[y, x])
            if seen[y, x] and not np.isnan(v):
                out[y, x] = np.uint8(v)
    return out


@register("principal_curvature", passes={"curvature"})
def principal_curvature(ctx: ViewContext) -> np.ndarray:
    """uint8 H x W x 3: R, G = k1, k2 clipped to +-1/curvature_clip_m mapped linearly to 0..254 (127 = flat),
    B = 0.

    Curvature is per vertex (services.worker.inputs.curvature, 1/m, positive = convex, k1 >= k2), interpolated
    over the seen triangle by the renderer. Where nothing is seen all three channels are 0 (background, see
    mask_valid).
    """
    k = ctx.passes.curvature
    if k is None:
        raise RuntimeError(
            "principal_curvature needs a pass set rendered with curvature (render pass 'curvature')"
        )
    return _curvature_pixels(k, hit(ctx), np.float32(1.0 / ctx.params.curvature_clip_m))


@njit(cache=True, nogil=True, error_model="numpy")
def _curvature_pixels(k: np.ndarray, seen: np.ndarray, kmax: np.float32) -> np.ndarray:
    """rint((clip(nan_to_num(k), -kmax, kmax) / kmax + 1) * CURVATURE_FLAT) in R, G where seen, 0 elsewhere
    and in B: the float32 operations of the numpy expression it replaced, in its order, in one pass."""
    h, w, _ = k.shape
    out = np.zeros((h, w, 3), np.uint8)
    big = np.float32(np.finfo(np.float32).max)
    for y in range(h):
        for x in range(w):
            if not seen[y, x]:
                out[y, x, 0] = out[y, x, 1] = CURVATURE_BACKGROUND
                continue
            for c in range(2):
                v = k[y, x, c]
                v = np.float32(0.0) if np.isnan(v) else min(max(v, -big), big)  # nan_to_num
                v = min(max(v, -kmax), kmax)
                out[y, x, c] = np.uint8(np.rint((v / kmax + np.float32(1.0)) * np.float32(CURVATURE_FLAT)))
    return out


@register("position")
def position(ctx: ViewContext) -> np.ndarray:
    """float32 H x W x 3 world XYZ (metres) of the seen surface, NaN where nothing is seen; from depth and
    pose."""
    return position_world(ctx)


@register("fragments", passes={"faces"})
def fragments(ctx: ViewContext) -> np.ndarray:
    """uint32 H x W index of the seen triangle in the space's mesh faces, 4294967295 = none."""
    f = np.asarray(ctx.passes.require("face_index"), dtype=np.uint32)
    return np.where(hit(ctx), f, NO_FACE).astype(np.uint32, copy=False)  # uint32 already: no second copy
