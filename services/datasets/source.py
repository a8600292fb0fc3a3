"""Where a dataset's files are and which views it holds: a job's output root, locally or on S3.

A root with a manifest.jsonl (every job's output) is indexed from the manifest alone: only the listed keys
are ever read, so an S3 prefix is never listed. A local folder without one (the released Omnidata starter
dataset, or a copied tree) is indexed by walking
`<cue>/<component>/<space>/point_<p>_view_<v>_domain_<cue>.<ext>`.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

from services.core.domain.cues import CATALOG, OUTPUT_CUES
from services.core.domain.job_document import JobDocument
from services.core.domain.json_types import JSONObject
from services.core.domain.keys import JOB_JSON_KEY, MANIFEST_KEY
from services.core.settings import Settings
from services.core.storage import LocalStore, ObjectNotFoundError, ObjectStore, open_store, prefixed

# Omnidata's file names; per-point cues (nonfixated) drop the view
FILE_RE = re.compile(
    r"^point_(?P<point>\d+)(?:_view_(?P<view>\d+))?_domain_(?P<cue>\w+?)\.(?P<ext>[A-Za-z0-9]+)$"
)

JOB_REF = re.compile(r"^(?:job:)?(?P<id>[1-9][0-9]{0,18})$")

# Folder names in released Omnidata components that differ from our cue names
STARTER_ALIASES = {"normals": "normal", "keypoint_unsup2d": "keypoints2d", "keypoint_unsup25d": "keypoints3d"}


@dataclass(frozen=True)
class FileRef:
    """One output file: its key under the root, and size and sha256 when the manifest lists them."""

    key: str
    size: int | None = None
    sha256: str | None = None


@dataclass
class ViewRecord:
    """One view of a dataset and its files by cue (per-point cues are attached to every view of their
    point)."""

    space: str
    point: int
    view: int
    component: str
    files: dict[str, FileRef] = field(default_factory=dict)

    @property
    def key(self) -> str:
        """`<space>/point_<p>_view_<v>`: a view's name, unique in a dataset."""
        return f"{self.space}/point_{self.point}_view_{self.view}"


class DatasetIntegrityError(ValueError):
    """A file's bytes do not match the sha256 its manifest records."""


def open_root(root: str | Path | ObjectStore, settings: Settings | None = None) -> ObjectStore:
    """The store of a dataset root: a folder path, file:// or s3://bucket/prefix URL, an open store, or the id
    of a service job (`42` or `job:42`: its outputs under `jobs/<id>` of the service's
    OMNIDATA_STORAGE_URL)."""
    if isinstance(root, ObjectStore):
        return root
    text = str(root)
    job = JOB_REF.match(text)
    if job and not Path(text).exists():
        from services.core.settings import get_settings

        s = settings or get_settings()
        return prefixed(open_store(s.storage_url, s), f"jobs/{job['id']}")
    if "://" not in text:
        path = Path(text).expanduser()
        if not path.is_dir():
            raise FileNotFoundError(
                f"{path} is not a folder (give a job's output folder, job id or s3:// URL)"
            )
        return LocalStore(path, fsync=False)
    return open_store(text, settings)


def read_json(store: ObjectStore, key: str) -> JSONObject | None:
    """The JSON object stored at `key`, or None when there is none."""
    try:
        doc: JSONObject = json.loads(store.get_bytes(key))
        return doc
    except ObjectNotFoundError:
        return None


def check_sha256(ref: FileRef, data: bytes) -> bytes:
    """`data` if it matches the recorded checksum (or none is recorded), else DatasetIntegrityError."""
    if ref.sha256 and hashlib.sha256(data).hexdigest() != ref.sha256:
        raise DatasetIntegrityError(
            f"{ref.key}: sha256 differs from manifest.jsonl (corrupt or changed file)"
        )
    return data


def read_file(store: ObjectStore, ref: FileRef, *, verify: bool) -> bytes:
    """The bytes of one listed file, sha256-checked when `verify` (ObjectNotFoundError when it is gone)."""
    data = store.get_bytes(ref.key)
    return check_sha256(ref, data) if verify else data


def missing_file_message(e: ObjectNotFoundError) -> str:
    """One line for a file the dataset lists but its root lacks (the commands print it instead of a
    traceback)."""
    return f"{e.key}: listed in manifest.jsonl but missing from the dataset root (deleted or moved?)"


def _component_of(key: str) -> str:
    parts = key.split("/")
    return parts[1] if len(parts) >= 4 else ""


def _attach_per_point(records: list[ViewRecord]) -> None:
    """Give every view of a point the point's per-point files (stored once, on view 0)."""
    shared: dict[tuple[str, int], dict[str, FileRef]] = {}
    for r in records:
        for cue, ref in r.files.items():
            if CATALOG[cue].per_point:
                shared.setdefault((r.space, r.point), {})[cue] = ref
    for r in records:
        for cue, ref in shared.get((r.space, r.point), {}).items():
            r.files.setdefault(cue, ref)


def index_manifest(store: ObjectStore) -> list[ViewRecord]:
    """Views from manifest.jsonl, in its order (space, point, view)."""
    records = []
    for line in store.get_bytes(MANIFEST_KEY).decode("utf-8").splitlines():
        if not line.strip():
            continue
        entry = json.loads(line)
        files = {
            cue: FileRef(o["key"], o.get("size"), o.get("sha256"))
            for cue, o in entry["outputs"].items() if cue in CATALOG
        }
        component = next((_component_of(f.key) for f in files.values()), "")
        records.append(ViewRecord(entry["space"], int(entry["point"]), int(entry["view"]), component, files))
    _attach_per_point(records)
    return records


def index_folder(root: Path) -> list[ViewRecord]:
    """Views found by walking a folder in the Omnidata layout (no manifest): any component names."""
    found: dict[tuple[str, str, int, int], ViewRecord] = {}
    per_point: list[tuple[str, str, int, str, FileRef]] = []
    for cue_dir in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(("_", "."))):
        cue = STARTER_ALIASES.get(cue_dir.name, cue_dir.name)
        if cue not in OUTPUT_CUES:
            continue
        for space_dir in sorted(cue_dir.glob("*/*")):
            if not space_dir.is_dir():
                continue
            component, space = space_dir.parent.name, space_dir.name
            for f in sorted(space_dir.iterdir()):
                m = FILE_RE.match(f.name)
                if m is None:
                    continue
                ref = FileRef(f.relative_to(root).as_posix())
                if m["view"] is None:
                    per_point.append((component, space, int(m["point"]), cue, ref))
                    continue
                k = (component, space, int(m["point"]), int(m["view"]))
                rec = found.setdefault(k, ViewRecord(space, k[2], k[3], component))
                rec.files[cue] = ref
    by_point: dict[tuple[str, str, int], list[ViewRecord]] = {}
    for (component, space, point, _view), rec in found.items():
        by_point.setdefault((component, space, point), []).append(rec)
    for component, space, point, cue, ref in per_point:
        for rec in by_point.get((component, space, point), []):
            rec.files[cue] = ref
    return [found[k] for k in sorted(found, key=lambda k: (k[1], k[0], k[2], k[3]))]


def index_root(store: ObjectStore) -> list[ViewRecord]:
    """The views of a dataset root: from its manifest, else (local folders) from its files."""
    if store.exists(MANIFEST_KEY):
        return index_manifest(store)
    if isinstance(store, LocalStore):
        return index_folder(store.root)
    raise FileNotFoundError(
        f"{store} holds no {MANIFEST_KEY}: object-store datasets are read through their manifest"
    )


def select_cues(records: list[ViewRecord], cues: list[str] | None) -> list[str]:
    """The requested cues (default: every cue some view has), in catalog order; ValueError naming any absent
    one."""
    present = [c for c in CATALOG if any(c in r.files for r in records)]
    if cues is None:
        return present
    missing = [c for c in cues if c not in present]
    if missing:
        raise ValueError(f"cue(s) {', '.join(missing)} are not in this dataset; it has {', '.join(present)}")
    return [c for c in CATALOG if c in cues]


def job_document(store: ObjectStore) -> JobDocument | None:
    """The root's job.json, or None (starter datasets have none)."""
    return cast(JobDocument | None, read_json(store, JOB_JSON_KEY))  # our own schema (format omnidata.job/N)
