"""The user's caches that outlive a run: folders under $OMNIDATA_DATA_DIR (default ~/.omnidata).

`omnidata generate` writes its state under --out, but what depends only on a scan (its meshed cloud, its
parsed space, its per-vertex curvature) is kept here, so a rerun on the same scan into a new --out reads it
back. Every entry is named by a digest of everything it was computed from, so a changed input never meets an
old entry; a reader that finds nothing usable computes instead. A folder is kept under a size limit
(Settings.user_cache_mb): the entries used longest ago go first (a hit touches its entry).

Every entry is written to a temporary file in its folder and renamed into place; a writer killed between the
two leaves that file behind. Pruning a folder removes such leftovers once no live writer can own them
(remove_stale_temps): the same rule for these folders and for a run's loaded-space cache.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import tempfile
import time
from pathlib import Path

log = logging.getLogger(__name__)

MESHED, PARSED, CURVATURE, PACKED = "meshed", "parsed", "curvature", "packed"  # the folders
# Pruned after each `generate` run: folder -> the suffix of its entries. A curvature entry has a lock file
# beside it (services.worker.inputs.shared_curvature), a meshed cloud its record (services.core.ingest.
# pointcloud.mesh_cloud_cached): each goes with its entry.
PRUNED = {MESHED: ".ply", PARSED: ".space", CURVATURE: ".npy", PACKED: ".zip"}
RECORD_SUFFIX = ".json"
LOADED = "loaded"  # a run's own cache, --out/.omnidata/cache/loaded (services.worker.inputs.loaded_cache)
# The prefix of each folder's temporary files (tempfile.mkstemp(prefix=...)), renamed into place once whole.
TEMP_PREFIX = {MESHED: ".tmp-", PARSED: ".parsed-", CURVATURE: ".curvature-", PACKED: ".packed-",
               LOADED: ".loaded-"}
# A writer renames its temporary file seconds after creating it; one not written to for an hour is a killed
# writer's, never a live one's.
STALE_TEMP_S = 3600.0


def user_data_dir() -> Path:
    """$OMNIDATA_DATA_DIR, else ~/.omnidata (the user's, not a run's --out)."""
    return Path(os.environ.get("OMNIDATA_DATA_DIR") or Path.home() / ".omnidata").expanduser()


def user_cache_dir(name: str) -> Path:
    """The folder of one cache, e.g. `curvature`."""
    return user_data_dir() / name


def touch(path: Path) -> None:
    """Mark an entry as used now (eviction keeps the recently used); a read-only folder is no error."""
    try:
        os.utime(path)
    except OSError:
        pass


def write_checked(path: Path, magic: bytes, body: bytes | memoryview, temp_prefix: str) -> None:
    """Write `magic`, the sha256 of `body` (hex) and `body` to `path` atomically: into a temporary file of
    `temp_prefix` beside it, renamed into place, so a reader sees the whole file or none (read_checked).
    Raises OSError, the temporary file removed."""
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix, suffix=path.suffix, dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            fh.write(magic + hashlib.sha256(body).hexdigest().encode())
            fh.write(body)
        os.replace(tmp, path)
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


def read_checked(path: Path, magic: bytes) -> memoryview | None:
    """The body of the entry write_checked wrote at `path`; None when there is none, or when its header or
    its sha256 does not fit (a damaged file, or one of another layout: logged)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    head = len(magic) + 64
    body = memoryview(data)[head:]
    if data.startswith(magic) and data[len(magic):head] == hashlib.sha256(body).hexdigest().encode():
        return body
    log.warning("cache entry %s is damaged (or of another layout); computing it again", path)
    return None


def prune_user_caches(max_bytes: int) -> None:
    """Keep each folder of PRUNED under `max_bytes` (Settings.user_cache_mb)."""
    for name, suffix in PRUNED.items():
        evict_oldest(user_cache_dir(name), max_bytes, suffix)


def remove_stale_temps(folder: Path, older_than_s: float = STALE_TEMP_S) -> list[Path]:
    """Remove the temporary files of TEMP_PREFIX in `folder` not written to for `older_than_s`: what writers
    killed before their rename left; the removed paths. A younger one may be a write in flight and is kept."""
    cutoff = time.time() - older_than_s
    removed = []
    try:
        temps = [p for p in folder.iterdir() if p.name.startswith(tuple(TEMP_PREFIX.values()))]
    except OSError as e:
        if not isinstance(e, FileNotFoundError):
            log.warning("cache %s not cleaned: %s", folder, e)
        return []
    for p in temps:
        try:
            if p.is_file() and p.stat().st_mtime < cutoff:
                p.unlink()
                removed.append(p)
        except OSError:  # renamed or removed by its writer meanwhile, or not ours to remove
            continue
    if removed:
        log.info("removed %d leftover temporary file(s) from %s", len(removed), folder)
    return removed


def evict_oldest(folder: Path, max_bytes: int, suffix: str) -> list[Path]:
    """Remove the `suffix` files of `folder` used longest ago until the rest fit in `max_bytes`, each with its
    record and the lock file beside it that no process holds; the removed paths. Stale temporary files go
    first (remove_stale_temps). Trouble with the folder only logs: the cache is an optimisation."""
    remove_stale_temps(folder)
    try:
        entries = []
        for p in folder.iterdir():
            if p.name.endswith(suffix) and not p.name.startswith("."):
                st = p.stat()
                entries.append((st.st_mtime, st.st_size, p))
    except OSError as e:
        if not isinstance(e, FileNotFoundError):
            log.warning("cache %s not pruned: %s", folder, e)
        return []
    total = sum(size for _, size, _ in entries)
    removed = []
    for _, size, p in sorted(entries):
        if total <= max_bytes:
            break
        try:
            p.unlink()
        except OSError as e:
            log.warning("cache entry %s not removed: %s", p, e)
            continue
        total -= size
        removed.append(p)
        _drop_unheld(p.with_suffix(".lock"))
        p.with_suffix(RECORD_SUFFIX).unlink(missing_ok=True)
    return removed


def _drop_unheld(lock_path: Path) -> None:
    try:
        with open(lock_path, "r+b") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held: a process is computing that entry again
            lock_path.unlink()
    except OSError:
        pass
