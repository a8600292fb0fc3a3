"""RGB from a capture's photographs instead of the mesh texture: the worker side of posed captures.

`PhotoPainter.paint(view, passes)` replaces a freshly rendered pass set's `rgb` with the photo data for the
view and adds `photo_coverage` (where that rgb came from a photo). A view whose centre is a capture camera's
centre (exact capture views, fixated views from capture positions) takes that frame's photo through the
rotation homography (services.core.ingest.capture.resample): exact, no parallax. Any other view is
photo-textured (services.worker.inputs.phototexture) when that is enabled. Frames: world metres, OpenCV camera
axes.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np

from services.core.ingest.capture.model import Capture
from services.core.ingest.capture.photos import Photo, load_photo, reduction
from services.core.ingest.capture.resample import photo_for_view
from services.worker.passes import ViewGeometry, ViewPasses

if TYPE_CHECKING:  # imported where used: the worker loads them only for jobs with photos
    from services.core.domain.capture_records import RefinedCamera
    from services.core.domain.jobspec import JobSpec
    from services.core.ingest.loading import LoadedSpace
    from services.worker.inputs.phototexture import PhotoTexturer

SAME_CENTRE_M = 1e-5  # a view this close to a capture centre sees through it (parallax below a pixel)
PHOTO_CACHE = 8  # decoded photos kept per worker process (each no larger than the views asking for it need)


class PhotoPainter:
    """Paints views from one capture's photos (world frame); keeps a few decoded photos."""

    def __init__(self, capture: Capture, *, texture: PhotoTexturer | None = None):
        if not capture.has_photos:
            raise ValueError(f"the {capture.format} capture has no photos with intrinsics to take rgb from")
        self.capture = capture
        self.centres = np.stack([f.center for f in capture.frames])
        self.texture = texture  # a PhotoTexturer for views away from every capture centre, or None
        self._photos: OrderedDict[int, Photo] = OrderedDict()

    def photo(self, i: int, focal_px: float) -> Photo:
        """The photo of frame i decoded for a view of focal length `focal_px` pixels (a kept one when it is
        dense enough for that view)."""
        frame = self.capture.frames[i]
        kept = self._photos.get(i)
        if kept is not None and round(1.0 / kept.scale) <= reduction(frame, focal_px):
            self._photos.move_to_end(i)
            return kept
        img = load_photo(str(self.capture.image_path(frame)), frame, focal_px)
        self._photos[i] = img
        self._photos.move_to_end(i)
        while len(self._photos) > PHOTO_CACHE:
            self._photos.popitem(last=False)
        return img

    def frames_at(self, centre: np.ndarray) -> np.ndarray:
        """Indices of the frames whose camera centre is the given point."""
        return np.flatnonzero(np.linalg.norm(self.centres - centre, axis=1) <= SAME_CENTRE_M)

    def paint(self, view: ViewGeometry, passes: ViewPasses) -> ViewPasses:
        """The pass set with rgb from the photos and photo_coverage set (see the module docstring)."""
        n = view.resolution
        focal = float(view.K[0, 0])
        same = self.frames_at(view.center)
        if len(same):
            best: tuple[np.ndarray, np.ndarray] | None = None
            for i in same:  # several frames from one centre (a panorama): the one covering most of the view
                rgb, covered = photo_for_view(self.photo(int(i), focal), self.capture.frames[int(i)], view.K,
                                              view.world_to_camera, n, n)
                if best is None or covered.sum() > best[1].sum():
                    best = (rgb, covered)
            assert best is not None
            passes.rgb, passes.photo_coverage = best
        elif self.texture is not None:
            # a photo seen from another point: its density on the surface there is taken as the view's own
            passes.rgb, passes.photo_coverage = self.texture.paint(view, passes,
                                                                   lambda j: self.photo(j, focal))
        else:
            raise ValueError("this view's centre is no capture camera's centre, and photo texturing is off")
        return passes


def painter_for(
    loaded: LoadedSpace, spec: JobSpec, refined: RefinedCamera | None = None
) -> PhotoPainter | None:
    """The painter a job needs for a loaded space (None when its rgb comes from the mesh); `refined`: the
    plan's record of a refined colour camera (cameras.capture_refine), applied to the capture as the planner
    did."""
    if not spec.uses_photos():
        return None
    capture = getattr(loaded, "capture", None)
    if capture is None:
        raise ValueError("the job takes rgb from photos, but no capture was found with the scan")
    if refined is not None:
        from services.core.ingest.capture.calibration import ColourCorrection

        capture = ColourCorrection.from_dict(refined["correction"]).capture(capture)
    texture = None
    if spec.cameras.mode != "capture":
        from services.worker.inputs.phototexture import PhotoTexturer

        texture = PhotoTexturer(loaded.mesh, capture, k=spec.views.photo_count)
    return PhotoPainter(capture, texture=texture)
