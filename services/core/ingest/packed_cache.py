"""A scan's packed source kept across `omnidata generate` runs, in the user's $OMNIDATA_DATA_DIR/packed.

A scan stored as the deterministic zip of what its mesh needs (an OBJ with its materials and textures, a mesh
with the capture or recorded gravity beside it: services.core.ingest.registry.pack_source) is zipped by every
run for its checksum, before any worker starts: ~0.2-0.4 CPU-s for the 7-Scenes kitchen with its 100-frame
capture (306 files, 18 MB). A rerun reads the zip back instead. An entry is named by a sha256 of the packer's
settings (passed by the registry, which owns them) and of every packed file's path, size, mtime, ctime and
inode: a file written since has another ctime, so it misses. It holds the zip after its sha256
(user_cache.write_checked): a damaged entry is refused and the files zipped again. Only the user's own
entries are read (another user's could hold any zip under a name that fits). Any trouble with the folder
means zipping.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Hashable
from pathlib import Path

from services.core.user_cache import PACKED, TEMP_PREFIX, read_checked, touch, user_cache_dir, write_checked

log = logging.getLogger(__name__)

SUFFIX = ".zip"
_MAGIC = b"omnidata-packed-source-v1\n"


def entry_path(key: Hashable, folder: Path | None = None) -> Path:
    """Where the zip of `key` (the packer's settings and the files' identities) is kept."""
    digest = hashlib.sha256(json.dumps(key, default=str).encode()).hexdigest()
    return (folder if folder is not None else user_cache_dir(PACKED)) / f"{digest}{SUFFIX}"


def read(key: Hashable, folder: Path | None = None) -> bytes | None:
    """The zip kept for `key`, or None (none, another user's, or damaged)."""
    entry = entry_path(key, folder)
    try:
        if entry.stat().st_uid != os.getuid():
            return None
    except OSError:
        return None
    body = read_checked(entry, _MAGIC)
    if body is None:
        return None
    touch(entry)
    return bytes(body)


def keep(key: Hashable, data: bytes, folder: Path | None = None) -> None:
    """Keep the zip of `key`; failures only log (the next run zips again)."""
    entry = entry_path(key, folder)
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        write_checked(entry, _MAGIC, data, TEMP_PREFIX[PACKED])
    except OSError as e:
        log.warning("could not keep the packed source at %s: %s", entry, e)
