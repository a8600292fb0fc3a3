"""Compacted views: the done tasks of a finished view packed into one `view_output` row, and back.

A done task row costs ~350 bytes with its indexes; a view's ~18 of them ~6.3 KB. The packed row keeps, per
task, what the manifest, the views API and a resume read: the task id, cue, attempts, size, sha256 (32 raw
bytes), duration and finish time, and the output key only where it is not the deterministic one
(`default_key`), about 70 bytes a task. What it drops: the worker, queued/started times, lease and backoff
columns of done tasks.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from services.core.db.models import Job, Task, TaskState
from services.core.domain.cues import CATALOG
from services.core.domain.keys import output_key, passes_key

FORMAT = 1
# The cue of a packed task is its index here (and bit `index` of `cue_mask`): rows outlive a catalog change,
# so this list only ever grows at its end (tests/scheduler/test_compaction.py checks that it covers the
# catalog).
CUE_NAMES = (
    "passes", "rgb", "normal", "depth_zbuffer", "depth_euclidean", "mask_valid", "reshading",
    "principal_curvature", "edge_texture", "edge_occlusion", "keypoints2d", "keypoints3d", "segment_unsup2d",
    "segment_unsup25d", "segment_semantic", "segment_instance", "segment_panoptic", "fragments", "point_info",
    "nonfixated", "vanishing_points", "position", "mask_photo", "augment_params", "rgb_refocus", "rgb_fog",
    "rgb_motion_blur",
    "rgb_flash",
)
CUE_INDEX = {name: i for i, name in enumerate(CUE_NAMES)}

_HEAD = struct.Struct("<BB")  # format, number of tasks
# id, cue index, flags, attempts, size, duration_s, finished_at (us since epoch)
_FIXED = struct.Struct("<qBBHqdq")
_LEN = struct.Struct("<H")
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_US = timedelta(microseconds=1)

# flags
KEY_DEFAULT, KEY_TEXT, SHA_HEX, SHA_TEXT, HAS_SIZE, HAS_DURATION, HAS_FINISHED = (1 << i for i in range(7))


@dataclass(frozen=True)
class DoneTask:
    """A done task as a compacted view keeps it (output_key: the stored key, the job root included or not)."""

    id: int
    cue: str
    attempts: int
    output_key: str | None
    size: int | None
    sha256: str | None
    duration_s: float | None
    finished_at: datetime | None


def default_key(job: Job, space_name: str, cue: str, point: int, view: int) -> str:
    """The store key a worker records for a task's output: deterministic from the job, space, cue and view."""
    root = (job.output_root or "").strip("/")
    rel = (
        passes_key(space_name, point, view)
        if CATALOG[cue].internal
        else output_key(cue, job.name, space_name, point, view)
    )
    return f"{root}/{rel}" if root else rel


def keys_of(job: Job, space_name: str, point: int, view: int) -> Callable[[str], str]:
    """cue -> its default key in this view (what `pack` and `unpack` take)."""
    def key_of(cue: str) -> str:
        return default_key(job, space_name, cue, point, view)
    return key_of


def _text(value: str) -> bytes:
    raw = value.encode("utf-8")
    return _LEN.pack(len(raw)) + raw


def _sha_bytes(sha: str | None) -> bytes | None:
    if sha is None or len(sha) != 64:
        return None
    try:
        raw = bytes.fromhex(sha)
    except ValueError:
        return None
    return raw if raw.hex() == sha else None  # upper case would not come back as it was: keep it as text


def pack(tasks: Sequence[DoneTask], key_of: Callable[[str], str]) -> bytes:
    """The packed form of a view's done tasks; `key_of(cue)` is the default key of its cue in this view."""
    if len(tasks) > 255:
        raise ValueError(f"a view of {len(tasks)} tasks cannot be compacted (255 at most)")
    out = [_HEAD.pack(FORMAT, len(tasks))]
    for t in tasks:
        sha = _sha_bytes(t.sha256)
        flags = (
            (KEY_DEFAULT if t.output_key == key_of(t.cue) else KEY_TEXT if t.output_key is not None else 0)
            | (SHA_HEX if sha is not None else SHA_TEXT if t.sha256 is not None else 0)
            | (HAS_SIZE if t.size is not None else 0)
            | (HAS_DURATION if t.duration_s is not None else 0)
            | (HAS_FINISHED if t.finished_at is not None else 0)
        )
        finished = 0 if t.finished_at is None else (t.finished_at.astimezone(UTC) - _EPOCH) // _US
        out.append(
            _FIXED.pack(t.id, CUE_INDEX[t.cue], flags, t.attempts, t.size or 0, t.duration_s or 0.0, finished)
        )
        if sha is not None:
            out.append(sha)
        elif t.sha256 is not None:
            out.append(_text(t.sha256))
        if flags & KEY_TEXT:
            out.append(_text(str(t.output_key)))
    return b"".join(out)


def _read_text(data: bytes, at: int) -> tuple[str, int]:
    (n,) = _LEN.unpack_from(data, at)
    at += _LEN.size
    return data[at : at + n].decode("utf-8"), at + n


def unpack(data: bytes, key_of: Callable[[str], str]) -> list[DoneTask]:
    """The done tasks of a packed view (the inverse of `pack`, with the same `key_of`)."""
    version, count = _HEAD.unpack_from(data, 0)
    if version != FORMAT:
        raise ValueError(f"view_output format {version} is not known to this version ({FORMAT})")
    at = _HEAD.size
    tasks = []
    for _ in range(count):
        tid, cue_i, flags, attempts, size, duration, finished = _FIXED.unpack_from(data, at)
        at += _FIXED.size
        sha: str | None = None
        if flags & SHA_HEX:
            sha, at = data[at : at + 32].hex(), at + 32
        elif flags & SHA_TEXT:
            sha, at = _read_text(data, at)
        cue = CUE_NAMES[cue_i]
        key: str | None = key_of(cue) if flags & KEY_DEFAULT else None
        if flags & KEY_TEXT:
            key, at = _read_text(data, at)
        tasks.append(DoneTask(
            id=tid, cue=cue, attempts=attempts, output_key=key,
            size=size if flags & HAS_SIZE else None, sha256=sha,
            duration_s=duration if flags & HAS_DURATION else None,
            finished_at=_EPOCH + finished * _US if flags & HAS_FINISHED else None,
        ))
    return tasks


def cue_mask(cues: Iterable[str]) -> int:
    """Bit i set for the catalog's i-th cue."""
    mask = 0
    for cue in cues:
        mask |= 1 << CUE_INDEX[cue]
    return mask


def as_task(t: DoneTask, job_id: int, space_id: int, point: int, view: int) -> Task:
    """A transient (never added to a session) Task of a compacted view, for readers written for task rows."""
    return Task(
        id=t.id, job_id=job_id, space_id=space_id, point_idx=point, view_idx=view, cue=t.cue,
        state=TaskState.DONE, attempts=t.attempts, output_key=t.output_key, size=t.size, sha256=t.sha256,
        duration_s=t.duration_s, finished_at=t.finished_at, error=None, worker_id=None, lease_until=None,
        queued_at=None, started_at=None,
        not_before=None,
    )
