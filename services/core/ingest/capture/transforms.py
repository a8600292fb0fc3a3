"""nerfstudio / instant-ngp `transforms.json`: camera-to-world `transform_matrix` per frame in OpenGL camera
axes (x right, y up, z backwards), intrinsics shared at the top level or per frame (`fl_x`, `fl_y`, `cx`,
`cy`, `w`, `h`, or instant-ngp's `camera_angle_x`/`camera_angle_y`), distortion `k1..k4`, `p1`, `p2` with
`camera_model` OPENCV (default) or OPENCV_FISHEYE. `file_path` is relative to the JSON's folder (instant-ngp's
synthetic scenes leave out the extension: .png, then .jpg is tried). Poses are kept as written (an
`applied_transform` is noted).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from services.core.domain.camera import CV_TO_BLENDER
from services.core.ingest.capture.checks import FrameCollector, inside, read_capture_json
from services.core.ingest.capture.model import Capture

GL_TO_CV = CV_TO_BLENDER  # diag(1, -1, -1, 1) maps either way


def _num(d: Mapping[str, object], key: str) -> float | None:
    v = d.get(key)
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def _camera(shared: Mapping[str, object], frame: Mapping[str, object]) -> dict[str, object]:
    keys = (
        "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "k1", "k2", "k3", "k4",
        "p1", "p2", "camera_model",
    )
    return {k: frame[k] if k in frame else shared.get(k) for k in keys}


def _intrinsics(
    cam: Mapping[str, object], size: tuple[int, int] | None
) -> tuple[np.ndarray, tuple[int, int] | None] | str:
    w, h = _num(cam, "w"), _num(cam, "h")
    given = (int(w), int(h)) if w and h else None
    width, height = given or size or (None, None)
    if width is None or height is None:
        return "no image size (w, h) and no readable image"
    fx, fy = _num(cam, "fl_x"), _num(cam, "fl_y")
    ax, ay = _num(cam, "camera_angle_x"), _num(cam, "camera_angle_y")
    if fx is None and ax is not None:
        fx = 0.5 * width / math.tan(0.5 * ax)
    if fy is None and ay is not None:
        fy = 0.5 * height / math.tan(0.5 * ay)
    fy = fy if fy is not None else fx
    fx = fx if fx is not None else fy
    if fx is None or fy is None:
        return "no focal length (fl_x/fl_y or camera_angle_x)"
    cx, cy = _num(cam, "cx"), _num(cam, "cy")
    K = np.array([[fx, 0.0, width / 2.0 if cx is None else cx], [0.0, fy, height / 2.0 if cy is None else cy],
                  [0.0, 0.0, 1.0]])
    return K, given


def _distortion(cam: Mapping[str, object]) -> tuple[str, tuple[float, ...]] | str:
    model = str(cam.get("camera_model") or "OPENCV").upper()
    k = [_num(cam, n) or 0.0 for n in ("k1", "k2", "k3", "k4", "p1", "p2")]
    if model == "OPENCV_FISHEYE":
        return "fisheye", tuple(k[:4])
    if model in ("OPENCV", "PINHOLE", "PERSPECTIVE"):
        if not any(k):
            return "none", ()
        if k[3]:
            return "k4 is not part of the OPENCV model"
        return "opencv", (k[0], k[1], k[4], k[5], k[2])
    return f"camera_model {model} is not supported (OPENCV or OPENCV_FISHEYE)"


def _image(root: Path, base: str, file_path: str) -> str:
    rel = f"{base}/{file_path}" if base else file_path
    rel = rel.replace("\\", "/").removeprefix("./").replace("/./", "/")
    if Path(rel).suffix == "":
        for ext in (".png", ".jpg"):
            cand = inside(root, rel + ext)
            if cand is not None and cand.is_file():
                return rel + ext
    return rel


def read_transforms(root: Path, path: Path) -> Capture:
    """The frames of one transforms.json (see the module docstring)."""
    col = FrameCollector(root)
    doc, unreadable = read_capture_json(root, path, "transforms")
    if unreadable is not None:
        return unreadable
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(doc, dict) or not isinstance(frames, list):
        return Capture("transforms", root, (), (f"{path.name}: no 'frames' list",))
    base = path.parent.relative_to(root).as_posix()
    base = "" if base == "." else base
    notes = [f"{path.relative_to(root).as_posix()}: OpenGL camera axes turned to OpenCV"]
    if "applied_transform" in doc:
        notes.append("applied_transform present: poses kept as written (nerfstudio's frame)")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            col.problem(f"frame {i}: no file_path; skipped")
            continue
        name = frame["file_path"]
        cam = _camera(doc, frame)
        rel = _image(root, base, name)
        full = inside(root, rel)
        size = None
        if full is not None and full.is_file():
            from services.core.ingest.capture.checks import image_size

            size = image_size(full)
        found = _intrinsics(cam, size)
        dist = _distortion(cam)
        if isinstance(found, str) or isinstance(dist, str):
            col.problem(f"frame {name}: {found if isinstance(found, str) else dist}; skipped")
            continue
        try:
            gl = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
            pose = np.vstack([gl, [0, 0, 0, 1]]) @ GL_TO_CV if gl.shape == (3, 4) else gl @ GL_TO_CV
        except (TypeError, ValueError):
            pose = None
        col.add(name, rel, pose, K=found[0], size=found[1], distortion=dist[0], params=dist[1])
    return Capture("transforms", root, tuple(col.frames), tuple(col.problems), notes=tuple(notes))
