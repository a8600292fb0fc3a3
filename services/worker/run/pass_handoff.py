"""A view's pass set handed from the process that rendered it to the ones that derive it.

In the store's usual form (ViewPasses.to_bytes: an .npz, written flushed, with its sha256, like any object) a
hand-off costs ~15 ms of CPU a view at 512 px with a worker's heap (the zip's CRC over 8 MB, copies, the hash,
then reading it back), ~30 ms without, besides the wait for the disk's flush. `generate`'s renderers write it
raw instead (RawPassSets): a short header and each array's bytes, straight from the arrays to the file
(LocalStore.put_unflushed), not flushed and with no checksum (a cache read back within seconds; a file a
machine crash tore is rendered again): ~3.4 ms a view to write and ~1.2 ms to read back. A raw set carries
its run's stamp and is read only by that run: unflushed, a set that a crash left may hold zeros where its
data was, so a later run (a resumed job) renders its view again instead of trusting it.
read_pass_set reads either form.
"""

from __future__ import annotations

import json
import logging
import struct
import zipfile
from typing import Any, Protocol

import numpy as np

from services.core.storage import LocalStore, ObjectInfo, ObjectStore
from services.worker.passes import OPTIONAL_ARRAYS, ViewGeometry, ViewPasses

log = logging.getLogger(__name__)

MAGIC = b"ODPASS1\n"  # an .npz starts with "PK": the two forms never meet
_LENGTH = struct.Struct("<Q")


class PassSets(Protocol):
    """Where a renderer puts the pass sets it hands off."""

    def put(self, key: str, passes: ViewPasses) -> ObjectInfo: ...

    def read(self, data: bytes) -> ViewPasses | None: ...


class StoredPassSets:
    """Pass sets as .npz objects of the store (the service: a deriver may be another machine)."""

    def __init__(self, store: ObjectStore) -> None:
        self.store = store

    def put(self, key: str, passes: ViewPasses) -> ObjectInfo:
        return self.store.put_bytes(key, passes.to_bytes())

    def read(self, data: bytes) -> ViewPasses | None:
        return read_pass_set(data)


class RawPassSets:
    """Pass sets as raw files of a local folder, unflushed (module docstring)."""

    def __init__(self, store: LocalStore, run: str) -> None:
        self.store = store
        self.run = run  # the stamp of this `generate` run (every one of its processes shares it)

    def read(self, data: bytes) -> ViewPasses | None:
        return read_pass_set(data, self.run)

    def put(self, key: str, passes: ViewPasses) -> ObjectInfo:
        arrays = _arrays(passes)
        header = json.dumps({
            "run": self.run, "fov": passes.geometry.fov, "resolution": passes.geometry.resolution,
            "arrays": [[name, a.dtype.str, list(a.shape)] for name, a in arrays.items()],
        }).encode()
        chunks: list[bytes | memoryview] = [MAGIC + _LENGTH.pack(len(header)) + header]
        chunks += [np.ascontiguousarray(a).data for a in arrays.values()]
        return self.store.put_unflushed(key, chunks)


def _arrays(passes: ViewPasses) -> dict[str, np.ndarray]:
    arrays = {"world_to_camera": np.asarray(passes.geometry.world_to_camera, dtype=np.float64),
              "depth_z": passes.depth_z, "rgb": passes.rgb}
    for name in OPTIONAL_ARRAYS:
        value = getattr(passes, name)
        if value is not None:
            arrays[name] = np.asarray(value)
    return arrays


def read_pass_set(data: bytes, run: str | None = None) -> ViewPasses | None:
    """A stored pass set of either form, or None when torn, unreadable or raw from a run other than `run`
    (its view is rendered again)."""
    try:
        return _read_raw(data, run) if data.startswith(MAGIC) else ViewPasses.from_bytes(data)
    except (ValueError, EOFError, KeyError, TypeError, struct.error, zipfile.BadZipFile) as exc:
        log.warning("a stored pass set is unreadable (%s): its view is rendered again", exc)
        return None


def _read_raw(data: bytes, run: str | None) -> ViewPasses:
    at = len(MAGIC)
    (length,) = _LENGTH.unpack_from(data, at)
    at += _LENGTH.size
    header = json.loads(data[at:at + length])
    if run is None or header.get("run") != run:
        raise ValueError("a raw pass set of another run")
    at += length
    arrays: dict[str, np.ndarray] = {}
    for name, dtype, shape in header["arrays"]:
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        if at + n > len(data):
            raise ValueError(f"raw pass set cut short in {name!r}")
        # a copy: the cues may write into their inputs, and the bytes object is read-only
        count = int(np.prod(shape))
        arrays[name] = np.frombuffer(data, dtype=dtype, count=count, offset=at).reshape(shape).copy()
        at += n
    geometry = ViewGeometry(world_to_camera=arrays.pop("world_to_camera"), fov=float(header["fov"]),
                            resolution=int(header["resolution"]))
    depth_z, rgb = arrays.pop("depth_z"), arrays.pop("rgb")
    optional: dict[str, Any] = {"normal_world": None, "face_index": None, **arrays}
    return ViewPasses(geometry=geometry, depth_z=depth_z, rgb=rgb, **optional)
