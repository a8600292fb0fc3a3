"""Output key naming: `<cue>/<component>/<space>/point_<p>_view_<v>_domain_<cue>.<ext>`.

The released Omnidata starter dataset's layout, so its loaders read our outputs unchanged.
"""

from __future__ import annotations

import re
from pathlib import Path

from services.core.domain.cues import get_cue

_SAFE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")

MANIFEST_KEY = "manifest.jsonl"
JOB_JSON_KEY = "job.json"


def check_name(kind: str, value: str) -> str:
    """Names that become path segments: letters, digits, '.', '_', '-'; no traversal."""
    if not _SAFE.match(value) or value in {".", ".."}:
        raise ValueError(
            f"{kind} {value!r} is not a valid name: use 1-128 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit"
        )
    return value


def space_name(path: Path) -> str:
    """A space's name in the output layout from its path: the folder name, or the file name without its
    extension; characters other than letters, digits, '.', '_' and '-' become '_', and those three are
    stripped from both ends (`scan_.obj` is `scan`)."""
    raw = path.name if path.is_dir() else path.stem
    return check_name("space", _UNSAFE.sub("_", raw).strip("._-")[:128] or "space")


def file_name(cue: str, point: int, view: int) -> str:
    """`point_<p>_view_<v>_domain_<cue>.<ext>`; per-point cues drop the view:
    `point_<p>_domain_<cue>.<ext>`."""
    c = get_cue(cue)
    if c.per_point:
        return f"point_{point}_domain_{cue}.{c.ext}"
    return f"point_{point}_view_{view}_domain_{cue}.{c.ext}"


def output_key(cue: str, component: str, space: str, point: int, view: int) -> str:
    """Object key of one output relative to the job's root."""
    return f"{cue}/{component}/{space}/{file_name(cue, point, view)}"


def passes_key(space: str, point: int, view: int) -> str:
    """Internal cache key of a view's render pass set (not part of the dataset)."""
    return f"_cache/passes/{space}/point_{point}_view_{view}.npz"
