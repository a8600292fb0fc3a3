"""A loaded space handed from `omnidata generate` to its local workers, so they do not parse the scan again.

The parent process has parsed and checked every space before the job exists (validate_sources); a worker's
first render used to fetch the source and run `load_space` once more (0.3-0.5 CPU-s a room, plus the fetch's
copy). `keep_loaded` writes what a worker's SpaceContext is built from (the world-frame vertices and faces,
the colour source: UVs and the texture's pixels, or vertex/face colours, and the per-face labels) as an
uncompressed .npz in the run's own cache folder (--out/.omnidata/cache/loaded), named by the stored source's
checksum and a digest of the exact source_to_world; `read_loaded` gives it back as a mesh equal to
`load_space(source, source_to_world=...)`'s, or None whenever anything does not fit (no file, another frame, a
damaged or foreign file, an unknown layout), and the worker then loads the scan as before.

Equal means: the same vertex and face arrays, the same visual, and no cached normals (a mesh fresh from
`trimesh.load` + `apply_transform` holds none either; both compute them on first use from the same arrays).
Only layouts known to round-trip are written: meshes read by trimesh (not point-cloud reconstructions), with
no visual, vertex or face colours, or a SimpleMaterial texture whose image is plain RGB/RGBA (what the Blender
scene reads of it: the pixels, main_color). The file is written and read without pickle; its arrays carry a
sha256 of their content, so a truncated or altered file is refused, never half used.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh

from services.core.user_cache import LOADED, TEMP_PREFIX, remove_stale_temps

if TYPE_CHECKING:
    from services.core.ingest.loading import LoadedSpace

log = logging.getLogger(__name__)

FORMAT = 1  # bump when the layout or what it must equal changes: older files are then ignored
FOLDER = LOADED
_PNG_IMAGE_INFO = {"icc_profile", "transparency", "default_image"}  # what PIL writes into the PNG the Blender
# scene makes of the texture, besides the pixels: an image holding one is not kept (its pixels alone are)


@dataclass
class CachedSpace:
    """What SpaceContext.from_loaded reads of a LoadedSpace: the world-frame mesh and its per-face labels."""

    mesh: trimesh.Trimesh
    face_class: np.ndarray | None
    face_instance: np.ndarray | None
    checksum: str


def frame_digest(source_to_world: Any) -> str:
    """sha256 of a 4x4 source_to_world as float64 (the exact matrix the mesh was transformed with)."""
    m = np.ascontiguousarray(np.asarray(source_to_world, dtype=np.float64))
    return hashlib.sha256(f"{m.shape}".encode() + m.tobytes()).hexdigest()


def loaded_path(cache_dir: Path, checksum: str, source_to_world: Any) -> Path:
    """Where the loaded space of a source (`checksum`) in a frame is kept under the run's cache folder."""
    return Path(cache_dir) / FOLDER / f"{checksum}-{frame_digest(source_to_world)[:32]}.npz"


def _content_digest(arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256(str(FORMAT).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _visual_arrays(mesh: trimesh.Trimesh) -> dict[str, np.ndarray] | None:
    """The mesh's visual as plain arrays, or None when its kind is not one known to round-trip."""
    visual: Any = mesh.visual
    kind = getattr(visual, "kind", None)
    if isinstance(visual, trimesh.visual.ColorVisuals):
        if kind is None:
            return {"visual": np.array("none")}
        if kind == "vertex":
            return {"visual": np.array("vertex"), "vertex_colors": np.asarray(visual.vertex_colors)}
        if kind == "face":
            return {"visual": np.array("face"), "face_colors": np.asarray(visual.face_colors)}
        return None
    if not isinstance(visual, trimesh.visual.TextureVisuals):
        return None
    mat = visual.material
    if type(mat) is not trimesh.visual.material.SimpleMaterial:
        return None
    out = {"visual": np.array("texture"), "main_color": np.asarray(mat.main_color)}
    if visual.uv is not None:
        out["uv"] = np.asarray(visual.uv)
    img = mat.image
    if img is not None:
        if img.mode not in ("RGB", "RGBA") or _PNG_IMAGE_INFO & set(img.info):
            return None
        out["image"] = np.asarray(img)
    return out


def keep_loaded(cache_dir: Path, checksum: str, loaded: LoadedSpace) -> Path | None:
    """Write `loaded` (the space whose stored source has sha256 `checksum`) for the workers of this run,
    atomically; None when its layout is not kept or on failure."""
    if loaded.reconstruction is not None:
        return None
    mesh = loaded.mesh
    visual = _visual_arrays(mesh)
    if visual is None:
        return None
    arrays: dict[str, np.ndarray] = {
        "vertices": np.asarray(mesh.vertices), "faces": np.asarray(mesh.faces),
        "source_to_world": np.asarray(loaded.source_to_world, dtype=np.float64),
        "checksum": np.array(checksum), **visual,
    }
    if loaded.face_class is not None:
        arrays["face_class"] = np.asarray(loaded.face_class)
    if loaded.face_instance is not None:
        arrays["face_instance"] = np.asarray(loaded.face_instance)
    arrays["digest"] = np.array(_content_digest(arrays))
    path = loaded_path(cache_dir, checksum, loaded.source_to_world)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path.parent)  # what writers killed in earlier runs into this --out left
        fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX[LOADED], suffix=".npz", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    except OSError as e:
        log.warning("could not keep the loaded space at %s: %s", path, e)
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        return None
    return path


def read_loaded(cache_dir: Path, checksum: str, frame: Mapping[str, Any]) -> CachedSpace | None:
    """The space `keep_loaded` wrote for this source and frame (`{"source_to_world": 4x4}` only), else
    None."""
    if set(frame) != {"source_to_world"}:
        return None
    try:
        want = np.asarray(frame["source_to_world"], dtype=np.float64)
        path = loaded_path(cache_dir, checksum, want)
        if not path.is_file():
            return None
        with np.load(path, allow_pickle=False) as z:
            arrays = {name: z[name] for name in z.files}
        return _rebuild(arrays, checksum, want)
    except Exception as e:  # a damaged or foreign file of any kind: load the scan instead
        log.warning("loaded space cache of %s unusable (%s: %s); loading the scan", checksum[:12],
                    type(e).__name__, e)
        return None


def _rebuild(arrays: dict[str, np.ndarray], checksum: str, want: np.ndarray) -> CachedSpace | None:
    digest = str(arrays.pop("digest"))
    if digest != _content_digest(arrays):
        raise ValueError("content digest mismatch")
    if str(arrays["checksum"]) != checksum or not np.array_equal(arrays["source_to_world"], want):
        raise ValueError("another source or frame")
    v, f = arrays["vertices"], arrays["faces"]
    if (
        v.dtype != np.float64
        or v.ndim != 2
        or v.shape[1] != 3
        or f.ndim != 2
        or f.shape[1] != 3
        or f.dtype.kind != "i"
    ):
        raise ValueError("bad vertex or face arrays")
    if len(f) == 0 or f.min() < 0 or f.max() >= len(v):
        raise ValueError("faces refer to vertices that do not exist")
    labels = {}
    for name in ("face_class", "face_instance"):
        a = arrays.get(name)
        if a is not None and (a.size != len(f) or a.dtype.kind not in "iu"):  # kept as loaded: F or F x 1
            raise ValueError(f"{name} has the wrong length")
        labels[name] = a
    kind = str(arrays["visual"])
    if kind == "none":
        mesh = trimesh.Trimesh(vertices=v, faces=f, process=False, validate=False)
    elif kind == "vertex":
        vc = arrays["vertex_colors"]
        if vc.shape != (len(v), 4) or vc.dtype != np.uint8:
            raise ValueError("bad vertex colours")
        mesh = trimesh.Trimesh(vertices=v, faces=f, vertex_colors=vc, process=False, validate=False)
    elif kind == "face":
        fc = arrays["face_colors"]
        if fc.shape != (len(f), 4) or fc.dtype != np.uint8:
            raise ValueError("bad face colours")
        mesh = trimesh.Trimesh(vertices=v, faces=f, face_colors=fc, process=False, validate=False)
    elif kind == "texture":
        from PIL import Image

        img = arrays.get("image")
        image = None
        if img is not None:
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4):
                raise ValueError("bad texture image")
            image = Image.fromarray(img)  # RGB or RGBA by the last axis
        mat = trimesh.visual.material.SimpleMaterial(image=image, diffuse=arrays["main_color"])
        visual = trimesh.visual.TextureVisuals(uv=arrays.get("uv"), material=mat)
        mesh = trimesh.Trimesh(vertices=v, faces=f, visual=visual, process=False, validate=False)
    else:
        raise ValueError(f"unknown visual {kind!r}")
    return CachedSpace(mesh, labels["face_class"], labels["face_instance"], checksum)
