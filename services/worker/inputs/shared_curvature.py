"""Per-vertex curvature computed once per machine, not once per worker process.

Every worker process of a run needs the same space's curvature (1.5-2 CPU-s a room), and they all meet it at
their first render. The first to get here computes it under an exclusive file lock and writes it to the local
cache folder; the others wait on the lock and read the array back. The file's name is a digest of everything
the estimator reads (vertices, faces, vertex normals, the radius) and of the estimator's own source, so a
changed mesh, frame or estimator never meets an old file; what is read back is the computed array itself, so
the result is bit-identical to computing it. The file is the array in .npy form after a sha256 of those bytes
(services.core.user_cache.write_checked, as a parsed space's entry): a damaged file of the right shape is
refused, removed and computed again, never used. Any trouble with the folder falls back to computing.

`omnidata generate` shares the user's folder ($OMNIDATA_DATA_DIR/curvature, services.core.user_cache), so a
later run on the same scan reads the file too.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import logging
from pathlib import Path

import numpy as np
import trimesh

from services.core.user_cache import CURVATURE, TEMP_PREFIX, read_checked, touch, write_checked
from services.worker.inputs import curvature as estimator

log = logging.getLogger(__name__)

_ESTIMATOR_DIGEST = hashlib.sha256(Path(estimator.__file__).read_bytes()).hexdigest()
FORMAT = 2  # in every file's name: bump when the layout changes, so a file of another layout is never read
_MAGIC = f"omnidata-curvature {FORMAT}\n".encode()
# An entry keeps the .npy suffix (though a header comes first) so that files of every layout are pruned alike.


def curvature_digest(mesh: trimesh.Trimesh, radius: float) -> str:
    """sha256 of the estimator's inputs: vertices, faces, vertex normals, radius, and of the estimator's
    source and the file's layout."""
    h = hashlib.sha256(f"{FORMAT}:{_ESTIMATOR_DIGEST}".encode())
    for arr in (mesh.vertices, mesh.faces, mesh.vertex_normals):
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(np.float64(radius).tobytes())
    return h.hexdigest()


def shared_curvature(mesh: trimesh.Trimesh, radius: float, folder: Path | None) -> np.ndarray:
    """`principal_curvatures(mesh, radius)`, read from `folder` when another process computed it there."""
    if folder is None:
        return estimator.principal_curvatures(mesh, radius)
    digest = curvature_digest(mesh, radius)
    path = folder / f"{digest}.npy"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        lock = open(folder / f"{digest}.lock", "a+b")  # noqa: SIM115 (held across the compute below)
    except OSError as e:
        log.warning("curvature cache %s unusable (%s); computing", folder, e)
        return estimator.principal_curvatures(mesh, radius)
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one process computes, the others wait for its file
        found = _read(path, len(mesh.vertices))
        if found is not None:
            touch(path)  # used: kept longest when the folder is pruned
            return found
        out = estimator.principal_curvatures(mesh, radius)
        _write(path, out)
        return out


def _read(path: Path, vertices: int) -> np.ndarray | None:
    """The array at `path` when it is whole (its sha256 fits) and a float32 V x 2 array of this mesh, else
    None; a file that is not is removed (the caller holds its lock and writes it again)."""
    body = read_checked(path, _MAGIC)
    arr = None
    if body is not None:
        try:
            arr = np.load(io.BytesIO(body), allow_pickle=False)
        except ValueError:
            log.warning("curvature cache %s is damaged; computing it again", path)
    if arr is not None and arr.dtype == np.float32 and arr.shape == (vertices, 2):
        return arr
    try:
        path.unlink(missing_ok=True)
    except OSError:  # a read-only folder: the write after the compute fails too, and only logs
        pass
    return None


def _write(path: Path, arr: np.ndarray) -> None:
    """Keep `arr` at `path` (user_cache.write_checked); failures are only logged."""
    body = io.BytesIO()
    np.save(body, arr, allow_pickle=False)
    try:
        write_checked(path, _MAGIC, body.getbuffer(), TEMP_PREFIX[CURVATURE])
    except OSError as e:
        log.warning("could not keep the curvature at %s: %s", path, e)
