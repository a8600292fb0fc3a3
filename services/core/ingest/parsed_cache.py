"""A scan's parsed space kept across `omnidata generate` runs, in the user's $OMNIDATA_DATA_DIR/parsed.

`load_space` parses, checks and levels a scan on every run (0.2-0.5 CPU-s a room: bench/results/
startup_cpu.json, "parsed_cache"); a rerun on the same scan reads the LoadedSpace back instead (~0.01 CPU-s).
An entry's name is a sha256 of everything the result depends on:
- the checksum of the object register_space stores for the scan (Source.checksum: the mesh file, or the
  deterministic zip of all that the loader reads: materials, textures, a capture, a recorded gravity);
- the scan's resolved path (the LoadedSpace names it);
- load_space's frame arguments;
- the loader's version: the source of services/core/ingest and services/core/domain, and the versions of
  Python, numpy, trimesh and Pillow;
so a changed file, frame or loader never meets an old entry. The entry is the LoadedSpace pickled (its up and
unit evidence are nested dataclasses), after a sha256 of the pickle: a damaged file is refused before it is
unpickled, and written again. Unpickling runs what the file names, so only a file of this user's own is read.
Any trouble with the folder falls back to loading.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import pickle
import platform
from pathlib import Path

from services.core.domain.jobspec import SpaceFrame
from services.core.ingest.loading import LoadedSpace, load_space
from services.core.user_cache import (
    PARSED,
    PRUNED,
    TEMP_PREFIX,
    read_checked,
    touch,
    user_cache_dir,
    write_checked,
)

log = logging.getLogger(__name__)

SUFFIX = PRUNED[PARSED]
_MAGIC = b"omnidata-parsed-space 1\n"
_CODE = ("services/core/ingest", "services/core/domain")  # what load_space runs of ours


@functools.cache
def loader_version() -> str:
    """sha256 of the loader's source files and of the libraries whose objects an entry holds."""
    import numpy
    import PIL
    import trimesh

    root = Path(__file__).resolve().parents[3]
    h = hashlib.sha256(f"{platform.python_version()}:{numpy.__version__}:{trimesh.__version__}:"
                       f"{PIL.__version__}".encode())
    for folder in _CODE:
        for p in sorted((root / folder).rglob("*.py")):
            h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def parsed_key(checksum: str, path: Path, frame: SpaceFrame) -> str:
    """The entry name of scan `path` (stored checksum `checksum`) loaded with `frame`."""
    words = json.dumps({"checksum": checksum, "path": str(Path(path).resolve()), "frame": frame,
                        "loader": loader_version()}, sort_keys=True, default=repr)
    return hashlib.sha256(words.encode()).hexdigest()


def load_space_kept(path: Path, checksum: str, frame: SpaceFrame, folder: Path | None = None) -> LoadedSpace:
    """`load_space(path, **frame)`, read from the user's cache when a run loaded the same scan before."""
    folder = folder if folder is not None else user_cache_dir(PARSED)
    entry = folder / f"{parsed_key(checksum, path, frame)}{SUFFIX}"
    found = _read(entry)
    if found is not None:
        log.info("parsed space of %s read from %s", Path(path).name, entry)
        touch(entry)
        return found
    loaded = load_space(path, **frame)
    _write(entry, loaded)
    return loaded


def _read(entry: Path) -> LoadedSpace | None:
    try:
        if entry.stat().st_uid != os.getuid():  # unpickling runs what the file names: only the user's own
            return None
    except OSError:
        return None
    body = read_checked(entry, _MAGIC)  # a damaged file is refused before it is unpickled
    if body is None:
        return None
    try:
        loaded = pickle.loads(body)
    except Exception as e:  # a library changed under the same version string: load instead
        log.warning("parsed space cache %s unusable (%s); loading the scan", entry, e)
        return None
    return loaded if isinstance(loaded, LoadedSpace) else None


def _write(entry: Path, loaded: LoadedSpace) -> None:
    """Keep `loaded` at `entry` (user_cache.write_checked); failures only log."""
    try:
        body = pickle.dumps(loaded, protocol=pickle.HIGHEST_PROTOCOL)
        entry.parent.mkdir(parents=True, exist_ok=True)
        write_checked(entry, _MAGIC, body, TEMP_PREFIX[PARSED])
    except Exception as e:  # an unpicklable object, a full or read-only disk: the next run loads again
        log.warning("could not keep the parsed space at %s: %s", entry, e)
