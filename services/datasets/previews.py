"""Preview images people can read, one per cue file, made on demand and cached next to the job's outputs.

Display mapping only (the dataset files are untouched): depth with a colour map over its valid range (no
surface black), curvature as mean curvature on a diverging map (flat = grey), edges and keypoints on a
sequential map, labels with a palette, normals as their RGB encoding, fragments hashed to colours, positions
normalised per axis, JSON cues drawn (the fixated point, other visible points, vanishing directions).
Previews are 8-bit RGB PNGs stored under `_previews/v<N>/` of the job root, keyed like the outputs.
bpy-free: the API and the CLI use it.
"""

from __future__ import annotations

import io
import itertools
import json
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Literal, cast

import numpy as np
from PIL import Image, ImageDraw

from services.core.domain.cues import FRAGMENT_NONE, UINT16_NONE, get_cue
from services.core.domain.jobspec import CueParams
from services.core.domain.json_types import JSONObject, JSONValue
from services.core.domain.keys import file_name
from services.core.domain.plan_cues import Nonfixated, VanishingPoints
from services.core.storage import ObjectStore
from services.datasets.decode import (
    as_uint16,
    cue_params,
    curvature_per_m,
    read_raw,
)
from services.datasets.point_info import StoredPointInfo, camera_of
from services.datasets.source import ViewRecord, job_document

PREVIEW_VERSION = 1  # bump when the mapping changes: cached previews live under a versioned prefix
PREVIEW_PREFIX = f"_previews/v{PREVIEW_VERSION}"
MAX_PREVIEW_PX = 256  # previews are thumbnails: larger outputs are subsampled to at most this size
JSON_TILE_PX = 256
_AXIS_COLOURS: tuple[tuple[Literal["x", "y", "z"], tuple[int, int, int]], ...] = (
    ("x", (230, 60, 60)), ("y", (60, 200, 60)), ("z", (80, 120, 255)))
LABEL_CUES = {"segment_unsup2d", "segment_unsup25d", "segment_semantic", "segment_instance"}
MAGNITUDE_CUES = {"edge_texture", "edge_occlusion", "keypoints2d", "keypoints3d"}
# JSON cues holding pixel positions (need the resolution)
PIXEL_JSON_CUES = {"nonfixated", "vanishing_points"}

# Colour maps as anchor colours, linearly interpolated (0 -> first anchor, 1 -> last).
SEQUENTIAL = ((0, 0, 4), (80, 18, 123), (183, 55, 121), (252, 137, 97), (252, 253, 191))
DEPTH_NEAR_TO_FAR = (
    (180, 4, 38), (244, 109, 67), (254, 224, 139), (171, 221, 164), (50, 136, 189), (40, 30, 110),
)
DIVERGING = ((59, 76, 192), (221, 221, 221), (180, 4, 38))
NO_SURFACE = (0, 0, 0)


def colour_map(values: np.ndarray, anchors: Sequence[tuple[int, int, int]]) -> np.ndarray:
    """HxWx3 uint8 of values in [0, 1] (clipped; NaN -> black) through the anchor colours."""
    stops = np.linspace(0.0, 1.0, len(anchors))
    colours = np.asarray(anchors, dtype=np.float64)
    ramp = np.linspace(0.0, 1.0, 256)  # 256 entries: an 8-bit preview cannot show finer steps
    table = np.rint(np.stack([np.interp(ramp, stops, colours[:, c]) for c in range(3)], axis=-1)).astype(
        np.uint8
    )
    index = np.rint(np.clip(np.nan_to_num(values, nan=0.0), 0.0, 1.0) * 255).astype(np.intp)
    rgb = table[index]
    rgb[~np.isfinite(values)] = NO_SURFACE
    return rgb


def stretch(
    a: np.ndarray, valid: np.ndarray | None = None, lo_pct: float = 1, hi_pct: float = 99
) -> np.ndarray:
    """Values scaled to [0, 1] between two percentiles of the valid finite ones (NaN outside `valid`)."""
    a = a.astype(np.float64)
    mask = np.isfinite(a) if valid is None else (valid & np.isfinite(a))
    vals = a[mask]
    out = np.full(a.shape, np.nan)
    if vals.size == 0:
        return out
    if (lo_pct, hi_pct) == (0, 100):
        lo, hi = vals.min(), vals.max()
    else:  # a subsample is enough for display percentiles (a full sort of 512x512 costs ~20 ms)
        lo, hi = np.percentile(vals[:: max(1, vals.size // 65536)], [lo_pct, hi_pct])
    if hi - lo < 1e-12:  # constant: show the middle of the map rather than an edge
        lo, hi = lo - 1.0, lo + 1.0
    out[mask] = np.clip((a[mask] - lo) / (hi - lo), 0.0, 1.0)
    return out


def hashed_colours(ids: np.ndarray, none: int | None = None) -> np.ndarray:
    """HxWx3 uint8: a stable pseudo-random colour per integer id (Knuth's multiplicative hash); `none` is
    black.

    Colours stay above a floor of 48 per channel, so no id (label 0 included) looks like "none".
    """
    h = ((ids.astype(np.uint64) + np.uint64(1)) * np.uint64(2654435761)) & np.uint64(0xFFFFFF)
    channels = [(h >> np.uint64(s)) & np.uint64(255) for s in (16, 8, 0)]
    rgb = np.stack([48 + c.astype(np.uint16) * 207 // 255 for c in channels], axis=-1).astype(np.uint8)
    if none is not None:
        rgb[ids == none] = NO_SURFACE
    return rgb


def _grey_to_rgb(a: np.ndarray) -> np.ndarray:
    return np.stack([a] * 3, axis=-1) if a.ndim == 2 else a[..., :3]


def _image_preview(cue: str, raw: np.ndarray, params: CueParams) -> np.ndarray:
    """HxWx3 uint8 of an image cue's stored array."""
    # rgb_*: augmentations
    if cue in ("rgb", "normal", "reshading", "mask_valid", "mask_photo") or cue.startswith("rgb_"):
        return _grey_to_rgb(raw).astype(np.uint8)
    if cue.startswith("depth_"):
        d = as_uint16(raw)
        valid = d != UINT16_NONE
        return colour_map(stretch(d, valid), DEPTH_NEAR_TO_FAR)
    if cue == "principal_curvature":
        mean = curvature_per_m(raw, params).mean(axis=-1) * params.curvature_clip_m  # -1..1
        return colour_map(0.5 + 0.5 * mean, DIVERGING)
    if cue in MAGNITUDE_CUES:
        m = as_uint16(raw).astype(np.float64)
        positive = m > 0
        hi = np.percentile(m[positive], 99) if positive.any() else 1.0
        return colour_map(m / max(hi, 1.0), SEQUENTIAL)
    if cue in LABEL_CUES:
        return hashed_colours((as_uint16(raw) if raw.dtype.itemsize >= 2 else raw).astype(np.int64))
    if cue == "segment_panoptic":
        rgb = raw.astype(np.int64)
        return hashed_colours(rgb[..., 0] * 65536 + rgb[..., 1] * 256 + rgb[..., 2])
    if cue == "fragments":
        return hashed_colours(raw, none=FRAGMENT_NONE)
    if cue == "position":
        valid = np.isfinite(raw).all(axis=-1)
        out = np.stack([stretch(raw[..., i], valid, 0, 100) for i in range(3)], axis=-1)
        return np.where(valid[..., None], np.rint(np.nan_to_num(out) * 255), 0).astype(np.uint8)
    raise ValueError(f"cue {cue!r}: no preview mapping")


# ---------------------------------------------------------------------------------------------- JSON cues


def _tile(size: int) -> tuple[Image.Image, ImageDraw.ImageDraw]:
    img = Image.new("RGB", (size, size), (24, 24, 32))
    draw = ImageDraw.Draw(img)
    draw.line([(size / 2, 0), (size / 2, size)], fill=(60, 60, 72))
    draw.line([(0, size / 2), (size, size / 2)], fill=(60, 60, 72))
    return img, draw


def _dot(draw: ImageDraw.ImageDraw, xy: tuple[float, float], r: float, colour: tuple[int, int, int]) -> None:
    draw.ellipse([xy[0] - r, xy[1] - r, xy[0] + r, xy[1] + r], outline=colour, width=2)


def _draw_point_info(doc: StoredPointInfo, size: int) -> Image.Image:
    """The fixated point where the view sees it, and the camera's field of view and distance."""
    from services.core.domain.camera import project

    img, draw = _tile(size)
    K, w2c = camera_of(doc)
    scale = size / float(doc.get("resolution", size))
    uv, z = project(np.asarray([doc["point_location"]]), K.astype(np.float64), w2c.astype(np.float64))
    if z[0] > 0:
        _dot(draw, (uv[0, 0] * scale, uv[0, 1] * scale), max(3, size / 24), (255, 200, 60))
    fov = math.degrees(float(doc.get("field_of_view_rads", 0.0)))
    draw.text((4, 4), f"fov {fov:.1f} deg", fill=(230, 230, 230))
    if "camera_distance" in doc:
        draw.text((4, size - 14), f"distance {float(doc['camera_distance']):.2f} m", fill=(230, 230, 230))
    return img


def _draw_nonfixated(doc: Nonfixated, size: int, view: int, resolution: int) -> Image.Image:
    """Other points visible in this view, at their pixels (nearer points drawn larger)."""
    img, draw = _tile(size)
    scale = size / resolution
    entry = next((v for v in doc.get("views", []) if int(v.get("view_id", -1)) == view), None)
    points = entry.get("points", []) if entry is not None else []
    for p in points:
        u, v = p["pixel"]
        r = max(2.0, size / 16 / max(float(p.get("depth_zbuffer_m", 1.0)), 0.25))
        colour = tuple(int(c) for c in hashed_colours(np.array([int(p.get("point_idx", 0))]))[0])
        _dot(draw, (u * scale, v * scale), min(r, size / 8), colour)  # type: ignore[arg-type]
    draw.text((4, 4), f"{len(points)} other point(s)", fill=(230, 230, 230))
    return img


def _draw_vanishing_points(doc: VanishingPoints, size: int, resolution: int) -> Image.Image:
    """Rays from the image centre towards the vanishing point of each world axis (x red, y green, z blue)."""
    img, draw = _tile(size)
    scale = size / resolution
    centre = np.array([size / 2, size / 2])
    for axis, colour in _AXIS_COLOURS:
        vp = doc.get(axis)
        d = np.asarray(vp.get("direction", [0, 0, 1]) if vp else [0, 0, 1], dtype=np.float64)
        image = vp.get("image") if vp else None
        if image is not None:
            target = np.asarray(image, dtype=np.float64) * scale
            ray = target - centre
        else:  # parallel to the image: its direction in the image plane
            ray = d[:2]
        n = float(np.linalg.norm(ray))
        if n < 1e-9:
            _dot(draw, (centre[0], centre[1]), 4, colour)
            continue
        end = centre + ray / n * (size * 0.45)
        draw.line([tuple(centre), tuple(end)], fill=colour, width=3)
        draw.text((end[0] - 4, end[1] - 6), axis, fill=colour)
    return img


def _draw_augment_params(doc: Mapping[str, Mapping[str, JSONValue]], size: int) -> Image.Image:
    """The drawn augmentation parameters of the view, one line per cue."""
    img, draw = _tile(size)
    refocus, fog = doc.get("rgb_refocus", {}), doc.get("rgb_fog", {})
    motion, flash = doc.get("rgb_motion_blur", {}), doc.get("rgb_flash", {})
    lines = [
        f"focus {refocus.get('focus_distance_m', 0):.2f} m f/{refocus.get('f_number', 0):.1f}",
        f"fog beta {fog.get('beta_per_m', 0):.3f}/m A {fog.get('airlight', 0):.2f}",
        "move "
        + " ".join(
            f"{1000 * float(cast(float, x)):.0f}"
            for x in cast(list[JSONValue], motion.get("translation_m", []))
        )
        + " mm",
        f"flash {flash.get('power_m2', 0):.2f} amb {flash.get('ambient', 0):.2f}",
    ]
    for i, line in enumerate(lines):
        draw.text((4, 4 + i * 14), line, fill=(230, 230, 230))
    return img


def json_preview(cue: str, doc: JSONObject, *, view: int = 0, resolution: int | None = None) -> np.ndarray:
    """HxWx3 uint8 drawing of a JSON cue (pixel positions scaled from `resolution` to the tile)."""
    declared = doc.get("resolution")
    res = int(resolution or (declared if isinstance(declared, int | float) else 0) or JSON_TILE_PX)
    size = min(res, JSON_TILE_PX) if res >= 64 else 128
    if cue == "point_info":
        img = _draw_point_info(cast("StoredPointInfo", doc), size)
    elif cue == "nonfixated":
        img = _draw_nonfixated(cast(Nonfixated, doc), size, view, res)
    elif cue == "vanishing_points":
        img = _draw_vanishing_points(cast(VanishingPoints, doc), size, res)
    elif cue == "augment_params":
        img = _draw_augment_params(cast(Mapping[str, Mapping[str, JSONValue]], doc), max(size, 160))
    else:
        raise ValueError(f"cue {cue!r}: no preview drawing")
    return np.asarray(img)


# ---------------------------------------------------------------------------------------------- entry points


def preview_array(
    cue: str, data: bytes, params: CueParams | None = None, *, view: int = 0, resolution: int | None = None
) -> np.ndarray:
    """HxWx3 uint8 preview of one cue file's bytes (`view` and `resolution` place per-point JSON drawings)."""
    params = params or CueParams()
    raw = read_raw(cue, data)
    if isinstance(raw, dict):
        return json_preview(cue, raw, view=view, resolution=resolution)
    # thumbnails: subsample before mapping (cheaper, exact labels)
    step = -(-max(raw.shape[:2]) // MAX_PREVIEW_PX)
    return _image_preview(cue, raw[::step, ::step], params)


def png_bytes(img: np.ndarray) -> bytes:
    """An 8-bit RGB PNG of an HxWx3 uint8 array."""
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=3)
    return buf.getvalue()


def preview_key(output_key: str, cue: str, point: int, view: int) -> str:
    """Where the preview of an output (relative to the job root) is cached:
    `_previews/v<N>/<cue>/.../<file>.png`.

    Per-point files get one preview per view (the drawing depends on the view), so the name always has the
    view.
    """
    folder = output_key.rsplit("/", 1)[0]
    get_cue(cue)
    return f"{PREVIEW_PREFIX}/{folder}/point_{point}_view_{view}_domain_{cue}.png"


_PREVIEW_NAME = re.compile(r"^point_(?P<point>\d+)_view_(?P<view>\d+)_domain_(?P<cue>\w+)\.png$")


def parse_preview_key(key: str) -> tuple[str, str, str, int, int]:
    """(job root, output key relative to it, cue, point, view) of a preview key; ValueError if it names
    none."""
    marker = PREVIEW_PREFIX + "/"
    root, sep, rest = (
        key.rpartition("/" + marker) if not key.startswith(marker) else ("", marker, key[len(marker) :])
    )
    parts = rest.split("/")
    m = _PREVIEW_NAME.match(parts[-1]) if sep and len(parts) == 4 else None
    if m is None or m["cue"] != parts[0]:
        raise ValueError(f"{key!r} is not a preview key")
    cue, point, view = m["cue"], int(m["point"]), int(m["view"])
    if get_cue(cue).internal:
        raise ValueError(f"{key!r} names an internal cue")
    return root, f"{'/'.join(parts[:3])}/{file_name(cue, point, view)}", cue, point, view


def cached_preview(
    store: ObjectStore,
    output_key: str,
    cue: str,
    *,
    point: int,
    view: int,
    params: CueParams | None = None,
    resolution: int | None = None,
) -> tuple[str, bytes]:
    """(key, PNG bytes) of an output's preview: read from the cache, or made from the output and stored."""
    key = preview_key(output_key, cue, point, view)
    if store.exists(key):
        return key, store.get_bytes(key)
    data = png_bytes(
        preview_array(cue, store.get_bytes(output_key), params, view=view, resolution=resolution)
    )
    store.put_bytes(key, data, content_type="image/png")
    return key, data


class Previewer:
    """Cached previews of a dataset root's outputs, with each view's resolution for the drawn JSON cues."""

    def __init__(self, store: ObjectStore):
        self.store = store
        self.params = cue_params(job_document(store))

    def resolution(self, record: ViewRecord) -> int | None:
        if "point_info" not in record.files:
            return None
        res = json.loads(self.store.get_bytes(record.files["point_info"].key)).get("resolution")
        return None if res is None else int(res)

    def previews(self, record: ViewRecord, cues: Iterable[str]) -> dict[str, bytes]:
        """PNG bytes of the view's preview per cue (made and stored when not cached yet)."""
        cues = list(cues)
        res = self.resolution(record) if PIXEL_JSON_CUES.intersection(cues) else None
        return {
            cue: cached_preview(self.store, record.files[cue].key, cue, point=record.point, view=record.view,
                                params=self.params, resolution=res)[1]
            for cue in cues if cue in record.files
        }


# ---------------------------------------------------------------------------------------------- video


def write_video(frames: Iterable[np.ndarray], path: Path, *, fps: float = 10.0) -> int:
    """Write HxWx3 uint8 frames (all the same size) to an H.264 MP4; returns the number of frames written."""
    import imageio_ffmpeg

    it = iter(frames)
    first = next(it, None)
    if first is None:
        raise ValueError("a video needs at least one frame")
    h, w = first.shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    # yuv420p (what players expect) needs even sizes: pad by one pixel when odd
    pad_h, pad_w = h % 2, w % 2
    writer = imageio_ffmpeg.write_frames(
        str(path), (w + pad_w, h + pad_h), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
        macro_block_size=1, ffmpeg_log_level="error", output_params=["-crf", "18"],
    )
    writer.send(None)
    n = 0
    try:
        for frame in itertools.chain([first], it):
            if frame.shape[:2] != (h, w):
                raise ValueError(f"frame {n} is {frame.shape[:2]}, the first was {(h, w)}")
            padded = np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
            writer.send(np.ascontiguousarray(padded, dtype=np.uint8).tobytes())
            n += 1
    finally:
        writer.close()
    return n

