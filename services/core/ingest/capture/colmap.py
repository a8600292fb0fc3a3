"""COLMAP sparse models, text (`cameras.txt`, `images.txt`, `points3D.txt`) and binary (`.bin`), as COLMAP
writes them (`sparse/0/` beside `images/`, or the files in one folder).

images hold world-to-camera poses (quaternion qw qx qy qz, translation) in OpenCV axes; COLMAP's pixel
convention is ours (centre of the top-left pixel at (0.5, 0.5)). Camera models read: SIMPLE_PINHOLE, PINHOLE,
SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE; a camera of another model is reported and its images skipped.
Images are looked up under `images/` next to the model's folder (or its parents up to the root), else beside
it.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

from services.core.domain.camera import quaternion_wxyz_to_rotation
from services.core.ingest.capture.checks import MAX_FRAMES, FrameCollector, inside, read_text
from services.core.ingest.capture.model import Capture

# model id -> (name, number of params)
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
          4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
          8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}
MODEL_IDS = {name: (i, n) for i, (name, n) in MODELS.items()}
MAX_BIN_BYTES = 4 << 30

Camera = tuple[str, int, int, list[float]]  # model, width, height, params


def model_folders(files: list[Path]) -> list[Path]:
    """Folders holding a COLMAP model (cameras + images, text or binary)."""
    names: dict[Path, set[str]] = {}
    for p in files:
        names.setdefault(p.parent, set()).add(p.name)
    return sorted(d for d, n in names.items()
                  if {"cameras.txt", "images.txt"} <= n or {"cameras.bin", "images.bin"} <= n)


def intrinsics(model: str, params: list[float]) -> tuple[np.ndarray, str, tuple[float, ...]] | None:
    """(K, distortion model, distortion params) of a COLMAP camera, None for an unsupported model."""
    p = params
    one_focal = model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
    distortion = {"SIMPLE_PINHOLE": "none", "PINHOLE": "none", "SIMPLE_RADIAL": "radial", "RADIAL": "radial",
                  "OPENCV": "opencv", "OPENCV_FISHEYE": "fisheye"}.get(model)
    if distortion is None:
        return None
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if one_focal else (p[0], p[1], p[2], p[3])
    dist_params: tuple[float, ...] = tuple(p[3:]) if one_focal else tuple(p[4:])
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), distortion, dist_params


def _read_cameras_txt(text: str, problems: list[str]) -> dict[int, Camera]:
    cams: dict[int, Camera] = {}
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            cams[int(parts[0])] = (parts[1], int(parts[2]), int(parts[3]), [float(x) for x in parts[4:]])
        except (IndexError, ValueError):
            problems.append(f"cameras.txt: unreadable line {line[:80]!r}")
    return cams


def _read_images_txt(text: str, problems: list[str]) -> list[tuple[str, np.ndarray, int]]:
    """(name, world_to_camera 4x4, camera id) per image; every other line lists its 2D points (ignored)."""
    out = []
    lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]
    for i in range(0, len(lines), 2):
        parts = lines[i].split()
        if not parts:
            continue
        try:
            q = np.array([float(x) for x in parts[1:5]])
            t = np.array([float(x) for x in parts[5:8]])
            cam, name = int(parts[8]), " ".join(parts[9:])
        except (IndexError, ValueError):
            problems.append(f"images.txt: unreadable line {lines[i][:80]!r}")
            continue
        out.append((name, _w2c(q, t), cam))
        if len(out) > MAX_FRAMES:
            break
    return out


def _w2c(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    W = np.full((4, 4), np.nan)
    W[3] = [0.0, 0.0, 0.0, 1.0]
    if np.isfinite(q).all() and np.linalg.norm(q) > 0.5:
        W[:3, :3] = quaternion_wxyz_to_rotation(q) if abs(np.linalg.norm(q) - 1) < 1e-3 else np.nan
    W[:3, 3] = t
    return W


def _unpack(f: BinaryIO, fmt: str) -> tuple:
    size = struct.calcsize(fmt)
    data = f.read(size)
    if len(data) != size:
        raise EOFError("file ends early")
    return struct.unpack(fmt, data)


def _read_cameras_bin(f: BinaryIO, problems: list[str]) -> dict[int, Camera]:
    cams: dict[int, Camera] = {}
    (n,) = _unpack(f, "<Q")
    for _ in range(min(n, MAX_FRAMES)):
        cam_id, model_id, width, height = _unpack(f, "<iiQQ")
        name, count = MODELS.get(model_id, (f"model id {model_id}", -1))
        if count < 0:
            problems.append(
                f"cameras.bin: camera {cam_id} has unknown model id {model_id}; the file cannot be read on"
            )
            break
        cams[cam_id] = (name, int(width), int(height), list(_unpack(f, f"<{count}d")))
    return cams


def _read_images_bin(f: BinaryIO) -> list[tuple[str, np.ndarray, int]]:
    out = []
    (n,) = _unpack(f, "<Q")
    for _ in range(min(n, MAX_FRAMES)):
        values = _unpack(f, "<i7di")
        name = bytearray()
        while (c := f.read(1)) not in (b"\x00", b""):
            name += c
            if len(name) > 4096:
                raise ValueError("an image name longer than 4096 bytes")
        (n2d,) = _unpack(f, "<Q")
        f.seek(24 * n2d, 1)  # x, y (double), point3D id (int64) per 2D point
        out.append(
            (name.decode("utf-8", "replace"), _w2c(np.array(values[1:5]), np.array(values[5:8])), values[8])
        )
    return out


def _images_folder(root: Path, model_dir: Path) -> Path:
    here = model_dir
    while True:
        if (here / "images").is_dir():
            return here / "images"
        if here == root or root not in here.parents:
            return model_dir
        here = here.parent


def read_model(
    root: Path, model_dir: Path
) -> tuple[dict[int, Camera], list[tuple[str, np.ndarray, int]], list[str]]:
    """(cameras, images, problems) of one model folder, text preferred over binary."""
    problems: list[str] = []
    if (model_dir / "cameras.txt").is_file() and (model_dir / "images.txt").is_file():
        cams = _read_cameras_txt(read_text(model_dir / "cameras.txt", root), problems)
        images = _read_images_txt(read_text(model_dir / "images.txt", root), problems)
        return cams, images, problems
    for name in ("cameras.bin", "images.bin"):
        path = model_dir / name
        if inside(root, path.relative_to(root).as_posix()) is None or path.stat().st_size > MAX_BIN_BYTES:
            raise ValueError(f"{name} lies outside the capture or is too large")
    try:
        with open(model_dir / "cameras.bin", "rb") as f:
            cams = _read_cameras_bin(f, problems)
        with open(model_dir / "images.bin", "rb") as f:
            images = _read_images_bin(f)
    except (EOFError, struct.error, ValueError) as e:
        raise ValueError(f"COLMAP binary model in {model_dir.name}: truncated or corrupt ({e})") from None
    return cams, images, problems


def point_count_note(root: Path, model_dir: Path) -> list[str]:
    """How many sparse points the model's points3D holds (a note; the points themselves are not needed)."""
    try:
        if (model_dir / "points3D.txt").is_file():
            text = read_text(model_dir / "points3D.txt", root)
            n = sum(1 for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#"))
        elif (model_dir / "points3D.bin").is_file() and inside(
            root, (model_dir / "points3D.bin").relative_to(root).as_posix()
        ):
            with open(model_dir / "points3D.bin", "rb") as f:
                (n,) = _unpack(f, "<Q")
        else:
            return []
    except (OSError, ValueError, EOFError, struct.error):
        return ["points3D unreadable"]
    return [f"points3D: {n} sparse points"]


def read_colmap(root: Path, model_dir: Path) -> Capture:
    """The registered images of the COLMAP model in `model_dir` (see the module docstring)."""
    col = FrameCollector(root)
    try:
        cams, images, problems = read_model(root, model_dir)
    except (OSError, ValueError) as e:
        return Capture("colmap", root, (), (f"COLMAP model: {e}",))
    col.problems.extend(problems)
    images_dir = _images_folder(root, model_dir)
    prefix = images_dir.relative_to(root).as_posix() if images_dir != root else ""
    reported: set[int] = set()
    for name, w2c, cam_id in sorted(images, key=lambda x: x[0]):
        cam = cams.get(cam_id)
        if cam is None:
            col.problem(f"frame {name}: camera {cam_id} is not in the cameras file; skipped")
            continue
        found = intrinsics(cam[0], cam[3]) if len(cam[3]) == MODEL_IDS.get(cam[0], (0, -1))[1] else None
        if found is None:
            if cam_id not in reported:
                col.problem(
                    f"camera {cam_id}: model {cam[0]} with {len(cam[3])} parameters is not supported (use "
                    "PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE); its images are skipped"
                )
                reported.add(cam_id)
            continue
        K, dist, dp = found
        c2w = np.linalg.inv(w2c) if np.isfinite(w2c).all() else w2c
        col.add(
            name, f"{prefix}/{name}" if prefix else name, c2w, K=K, size=(cam[1], cam[2]), distortion=dist,
            params=dp,
        )
    notes = (f"COLMAP model in {model_dir.relative_to(root).as_posix() or '.'}, images in {prefix or '.'}",
             *point_count_note(root, model_dir))
    return Capture("colmap", root, tuple(col.frames), tuple(col.problems), notes=notes)
