"""Capture photos decoded within a pixel budget, and no larger than the views that sample them need.

A 0.6 MB PNG can declare 10000 x 10000 pixels: decoded whole and filtered in float it held 3.4 GB of a worker
for two 128 px views. So a photo's size is read from its header first (Pillow's `open` parses only the header)
and a photo over MAX_PHOTO_PIXELS (the texture limit) is refused, naming the file and the limit, at ingest
(the frame is skipped) and again by the loader that really decodes it. A photo within the budget is decoded
reduced by the largest integer factor that keeps it at least as dense as the view sampling it (a view of focal
length f pixels needs about f pixels per radian): a JPEG through its decoder's 1/2..1/8 scaling (only the
reduced image is ever held), then any image box-reduced. The reduced photo's pixel centre i + 0.5 is the full
photo's coordinate (i + 0.5) / scale, so cameras (K, width, height) keep describing the full photo.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from services.core.ingest.capture.model import CaptureError, CaptureFrame
from services.core.ingest.guard.texture_limits import MAX_TEXTURE_PIXELS, MAX_TEXTURE_SIDE

MAX_PHOTO_PIXELS = MAX_TEXTURE_PIXELS  # 67 Mpx: a 48 Mpx phone photo fits, 10000 x 10000 does not
_REDUCIBLE = {"L", "LA", "RGB", "RGBA", "RGBX", "I", "F"}  # modes Pillow's reduce takes as they are


class PhotoRefused(CaptureError):
    """A photo that is not decoded: over the pixel budget, unreadable, or not the size its camera says."""


@dataclass(frozen=True, eq=False)
class Photo:
    """A decoded capture photo: uint8 h x w x 3 `pixels` holding the photo reduced by `scale` (decoded pixels
    per photo pixel, 1 when full size). The photo's continuous coordinate x (pixel u's centre at u + 0.5) is
    at x * scale in `pixels`."""

    pixels: np.ndarray
    scale: float = 1.0


def limit_text() -> str:
    """The budget as messages state it."""
    return f"{MAX_PHOTO_PIXELS:,} pixels ({MAX_TEXTURE_SIDE} x {MAX_TEXTURE_SIDE})"


def photo_header(path: str | Path) -> tuple[int, int] | None:
    """(width, height) a photo's header declares, None when it is no readable image; PhotoRefused when it
    declares more than the budget (Pillow's own bomb limit included), without decoding a pixel."""
    name = Path(path).name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # ours is lower: judged below
        try:
            with Image.open(path) as im:
                size = int(im.width), int(im.height)
        except Image.DecompressionBombError:
            bomb = 2 * (Image.MAX_IMAGE_PIXELS or 0)  # where Pillow refuses to open an image
            raise PhotoRefused(f"photo {name} declares more than {bomb:,} pixels, more than the limit of "
                               f"{limit_text()} for a photo; downscale it") from None
        except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
            return None
    if size[0] * size[1] > MAX_PHOTO_PIXELS:
        raise PhotoRefused(f"photo {name} declares {size[0]:,} x {size[1]:,} pixels, more than the limit of "
                           f"{limit_text()} for a photo; downscale it")
    return size


def reduction(frame: CaptureFrame, focal_px: float | None) -> int:
    """The integer factor a frame's photo can be reduced by and still be as dense as a view of focal length
    `focal_px` (pixels; None: the full photo is needed)."""
    if focal_px is None or frame.K is None or focal_px <= 0:
        return 1
    photo_focal = math.sqrt(float(frame.K[0, 0]) * float(frame.K[1, 1]))
    return max(1, int(photo_focal / focal_px))


def load_photo(path: str | Path, frame: CaptureFrame, focal_px: float | None = None) -> Photo:
    """The frame's photo decoded for views of focal length up to `focal_px` pixels (see the module docstring);
    PhotoRefused naming the file when it is over the budget, unreadable or not the size its camera says."""
    name = Path(path).name
    size = photo_header(path)
    if size is None:
        raise PhotoRefused(f"photo {name} is not a readable image")
    if frame.width is not None and size != (frame.width, frame.height):
        raise PhotoRefused(
            f"photo {name} is {size[0]}x{size[1]}, its camera says {frame.width}x{frame.height}")
    factor = reduction(frame, focal_px)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                drafted = 1
                if factor > 1 and im.format == "JPEG":
                    drafted_to = im.draft("RGB", (-(-size[0] // factor), -(-size[1] // factor)))
                    if drafted_to is not None:  # (mode, (0, 0, width / scale, height / scale))
                        drafted = round(size[0] / drafted_to[1][2])
                rest = max(1, factor // drafted)
                if im.mode not in _REDUCIBLE:
                    im = im.convert("RGB")  # palette, 16-bit: reduce needs a plain mode
                if rest > 1:
                    im = im.reduce(rest)
                pixels = np.asarray(im.convert("RGB"))
    except MemoryError:
        raise PhotoRefused(f"photo {name} ({size[0]:,} x {size[1]:,} pixels) does not fit in this process's "
                           "memory budget: downscale the capture's photos") from None
    except (OSError, ValueError, SyntaxError) as e:
        raise PhotoRefused(f"photo {name} cannot be decoded ({e})") from None
    return Photo(pixels, 1.0 / (drafted * rest))
