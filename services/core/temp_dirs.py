"""Temporary folders (and files) named after the process that owns them, and the sweep that removes orphans.

A process killed with -9 (an API mid-upload, a worker mid-render, a mesh reader past its limit) never
runs its cleanup, so its temporary folder would stay forever (uploads are gigabytes; /dev/shm is
memory). Every such folder is named `omnidata-<kind>-<pid>-<random>`; `sweep_orphans` removes those
whose owner is no longer running, and those without a pid in their name (from before pids were
recorded) once older than `max_age_s`. The API sweeps when it starts, workers
whenever they set up a render scene, the upload checker right after killing a reader, and a scheduler
when it starts, whenever one of its planner processes ended without cleaning up, and with each reaper pass
(a planner of a scheduler killed with -9 may outlive the next scheduler's start by a moment).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

DAY_S = 24 * 3600.0
UPLOAD_KINDS = ("upload", "register", "space")  # what the API and the mesh readers it starts leave behind
PLANNER_KINDS = ("plan", "space")  # what a planner process leaves: its plan JSON parts, a loaded capture
_OURS = re.compile(r"^omnidata-([a-z]+)-(?:(\d+)-)?")


def owned_prefix(kind: str, pid: int | None = None) -> str:
    """The prefix of a temporary folder of `kind` owned by this process (or by `pid`)."""
    return f"omnidata-{kind}-{os.getpid() if pid is None else pid}-"


def owned_temp_dir(kind: str, parent: str | Path | None = None) -> tempfile.TemporaryDirectory[str]:
    """A TemporaryDirectory whose name says which process owns it."""
    return tempfile.TemporaryDirectory(prefix=owned_prefix(kind), dir=parent)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    # a zombie has exited and holds nothing (a container's init may never reap one, e.g. a killed planner)
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return not Path("/proc").is_dir()  # gone meanwhile; or no /proc here (not Linux): signal 0 decides
    return stat[stat.rindex(")") + 2] != "Z"


def sweep_orphans(
    kinds: Iterable[str],
    parents: Iterable[str | Path | None] = (None,),
    *,
    max_age_s: float = DAY_S,
    only_pid: int | None = None,
    now: float | None = None,
) -> list[Path]:
    """Remove our folders of `kinds` under `parents` (None: the temp dir) whose owner died; returns them.

    `only_pid`: remove just that (dead) process's folders, e.g. right after killing it.
    """
    wanted = set(kinds)
    now = time.time() if now is None else now
    removed: list[Path] = []
    for parent in parents:
        base = Path(parent) if parent is not None else Path(tempfile.gettempdir())
        try:
            entries = list(os.scandir(base))
        except OSError:
            continue
        for entry in entries:
            m = _OURS.match(entry.name)
            if m is None or m.group(1) not in wanted or entry.is_symlink():
                continue
            pid = int(m.group(2)) if m.group(2) else None
            if only_pid is not None and pid != only_pid:
                continue
            try:
                age = now - entry.stat(follow_symlinks=False).st_mtime
            except OSError:
                continue
            # a live owner keeps its folder however old (a worker renders one space for days); a folder
            # without a pid (named before pids were recorded) goes once it is older than max_age_s
            orphan = (not _alive(pid) and pid != os.getpid()) if pid is not None else age > max_age_s
            if orphan:
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(entry.path, ignore_errors=True)
                else:  # a temp file (an EXR being encoded)
                    Path(entry.path).unlink(missing_ok=True)
                removed.append(Path(entry.path))
    if removed:
        log.info("removed %d temporary folder(s) left by killed processes", len(removed))
    return removed
