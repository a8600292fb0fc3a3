"""Decode cue files (the encodings of the cue catalog) into arrays in physical units, channels first.

Bytes in, numpy out, no I/O: the dataset, the exporter and the previews share these. 16-bit PNGs are read
from Pillow's raw buffer and reinterpreted as unsigned, so no Pillow version can hand back int16 values
that wrap 65535 ("no depth") or keypoint responses above 32767 negative.

Units (what a training loop receives):
  rgb, rgb_*           float32 3xHxW in [0, 1] (rgb_refocus, rgb_fog, rgb_motion_blur, rgb_flash:
  augmentations) normal               float32 3xHxW unit vectors, camera frame x right, y up, z towards the
  viewer; NaN = none depth_*              float32 1xHxW metres; NaN = no surface
  mask_valid           bool 1xHxW
  mask_photo           bool 1xHxW (capture views: the rgb is a photo's here)
  reshading            float32 1xHxW in [0, 1]
  principal_curvature  float32 2xHxW k1, k2 in 1/m (clipped to +-1/curvature_clip_m); NaN = none
  edge_*               float32 1xHxW Sobel response (stored value / edge_scale)
  keypoints2d          float32 1xHxW determinant-of-Hessian response (stored value / keypoints2d_scale)
  keypoints3d          float32 1xHxW interest in [0, 1]
  segment_*            int64 1xHxW labels; segment_panoptic int64 2xHxW (class, instance)
  fragments            int64 1xHxW face index; -1 = none
  position             float32 3xHxW world XYZ metres; NaN = none
  JSON cues            the JSON text (str), which torch's default collate passes through as a list
"""

from __future__ import annotations

import io
import json

import numpy as np
from PIL import Image

from services.core.domain.cues import CURVATURE_FLAT, FRAGMENT_NONE, NORMAL_BACKGROUND, UINT16_NONE, get_cue
from services.core.domain.exr import decode_exr_rgb
from services.core.domain.job_document import JobDocument
from services.core.domain.jobspec import CueParams
from services.core.domain.json_types import JSONObject

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_bit_depth(data: bytes) -> int:
    """Bits per sample from the PNG header (IHDR is always the first chunk)."""
    if data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise ValueError("not a PNG file")
    return data[24]


def as_uint16(values: np.ndarray) -> np.ndarray:
    """16-bit samples as uint16 whatever signed type a decoder used (int16 wrap undone: -1 -> 65535)."""
    if values.dtype == np.uint16:
        return values
    return (values.astype(np.int64) & 0xFFFF).astype(np.uint16)


def read_png(data: bytes) -> np.ndarray:
    """HxW or HxWxC array of a PNG: uint8 for 8-bit files, uint16 (exact) for 16-bit ones."""
    bits = png_bit_depth(data)
    with Image.open(io.BytesIO(data)) as img:
        if bits != 16:
            if img.mode not in ("L", "RGB", "RGBA"):
                img = img.convert("RGBA" if "A" in img.mode else "RGB")
            return np.asarray(img)
        w, h = img.size
        if img.mode.startswith("I;16"):  # raw 16-bit samples in the mode's byte order
            order = ">" if img.mode.endswith("B") else "<"
            return np.frombuffer(img.tobytes(), dtype=f"{order}u2").reshape(h, w).astype(np.uint16)
        if img.mode in ("I", "I;32"):  # 16-bit grey widened to int32 by some Pillow versions
            return as_uint16(np.asarray(img))
        # 16-bit RGB(A): Pillow keeps only the high byte; ask it for the full samples via numpy
        arr = np.asarray(img)
        return as_uint16(arr) if arr.dtype.kind in "iu" and arr.itemsize >= 2 else arr


def read_npy(data: bytes) -> np.ndarray:
    """The array of a .npy file (no pickles)."""
    return np.load(io.BytesIO(data), allow_pickle=False)


def read_raw(cue: str, data: bytes) -> np.ndarray | JSONObject:
    """A cue file as stored: HxW(xC) array in the file's dtype, or the parsed JSON."""
    ext = get_cue(cue).ext
    if ext == "json":
        parsed: JSONObject = json.loads(data)
        return parsed
    if ext == "npy":
        return read_npy(data)
    if ext == "exr":
        return decode_exr_rgb(data)
    if data[:8] == PNG_SIGNATURE:
        return read_png(data)
    with Image.open(io.BytesIO(data)) as img:  # starter datasets hold a few JPEGs
        return np.asarray(img.convert("RGB"))


def _chw(a: np.ndarray) -> np.ndarray:
    return a[None] if a.ndim == 2 else np.moveaxis(a, -1, 0)


def _grey(a: np.ndarray) -> np.ndarray:
    return a if a.ndim == 2 else a[..., 0]


def depth_metres(raw: np.ndarray, params: CueParams) -> np.ndarray:
    """float32 metres of a 16-bit depth image; NaN where it says no surface (65535)."""
    d = as_uint16(_grey(raw))
    return np.where(d == UINT16_NONE, np.nan, d.astype(np.float64) / params.depth_units_per_m).astype(
        np.float32
    )


def normal_vectors(raw: np.ndarray) -> np.ndarray:
    """HxWx3 float32 unit camera-frame normals of an 8-bit normal image; NaN on the grey background
    (NORMAL_BACKGROUND)."""
    n = raw[..., :3].astype(np.float32) * np.float32(2.0 / 255.0) - np.float32(1.0)
    n[..., 0] *= -1.0  # px_x = 255 * (0.5 - 0.5 x)
    length = np.sqrt(np.einsum("hwc,hwc->hw", n, n))
    grey = NORMAL_BACKGROUND
    background = (raw[..., 0] == grey) & (raw[..., 1] == grey) & (raw[..., 2] == grey) | (length < 0.5)
    with np.errstate(divide="ignore"):
        n *= np.where(background, np.float32(np.nan), 1.0 / length)[..., None]
    return n


def curvature_per_m(raw: np.ndarray, params: CueParams) -> np.ndarray:
    """HxWx2 float32 principal curvatures k1, k2 in 1/m; NaN where nothing is seen (stored as R = G = B =
    0)."""
    kmax = 1.0 / params.curvature_clip_m
    k = (raw[..., :2].astype(np.float64) / CURVATURE_FLAT - 1.0) * kmax
    k[(raw[..., :3] == 0).all(axis=-1)] = np.nan
    return k.astype(np.float32)


def decode_cue(cue: str, data: bytes, params: CueParams | None = None) -> np.ndarray | str:
    """The cue file `data` as a channels-first array in the units of the module docstring (JSON: its text)."""
    spec = get_cue(cue)
    if spec.ext == "json":
        return data.decode("utf-8")
    params = params or CueParams()
    raw = read_raw(cue, data)
    assert isinstance(raw, np.ndarray)
    if cue == "rgb" or cue.startswith("rgb_"):  # rgb_*: the 3D augmentations, sRGB like rgb
        return _chw((raw[..., :3] if raw.ndim == 3 else np.stack([raw] * 3, -1)).astype(np.float32) / 255.0)
    if cue == "normal":
        return _chw(normal_vectors(raw))
    if cue.startswith("depth_"):
        return _chw(depth_metres(raw, params))
    if cue in ("mask_valid", "mask_photo"):
        return _chw(_grey(raw) > 0)
    if cue == "reshading":
        return _chw(_grey(raw).astype(np.float32) / 255.0)
    if cue == "principal_curvature":
        return _chw(curvature_per_m(raw, params))
    if cue.startswith("edge_"):
        return _chw((as_uint16(_grey(raw)).astype(np.float64) / params.edge_scale).astype(np.float32))
    if cue == "keypoints2d":
        return _chw((as_uint16(_grey(raw)).astype(np.float64) / params.keypoints2d_scale).astype(np.float32))
    if cue == "keypoints3d":
        return _chw((as_uint16(_grey(raw)).astype(np.float64) / UINT16_NONE).astype(np.float32))
    if cue == "segment_panoptic":
        rgb = raw.astype(np.int64)
        return np.stack([rgb[..., 0], rgb[..., 1] * 256 + rgb[..., 2]])
    if cue.startswith("segment_"):
        g = _grey(raw)
        return _chw((as_uint16(g) if g.dtype.itemsize >= 2 else g).astype(np.int64))
    if cue == "fragments":
        f = _grey(raw).astype(np.int64)
        return _chw(np.where(f == FRAGMENT_NONE, -1, f))
    if cue == "position":
        return _chw(raw.astype(np.float32))
    raise ValueError(f"cue {cue!r}: no decoder")  # a new catalog entry needs one here


def cue_params(job_document: JobDocument | None) -> CueParams:
    """The job's cue parameters from its job.json (defaults for datasets without one)."""
    spec = job_document.get("spec") if job_document is not None else None
    params = spec.get("params") if spec else None
    return CueParams.model_validate(params) if params else CueParams()
