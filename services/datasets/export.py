"""A job's output rewritten for other loaders (`omnidata export`, services.cli.export, is its command).

webdataset: tar shards `OUT/shard-000000.tar`, ... with one sample per view keyed `<space>/point_<p>_view_<v>`
(or `<space>__point_<p>_view_<v>` with --flat-keys), one member per cue named `<key>.<cue>.<ext>` holding the
file's bytes unchanged, and `<key>.json` with {space, component, point, view, point_info}. Per-point cues
(nonfixated) go into every view of their point, so each sample stands alone.

omnidata: the tree the public Omnidata dataloader (omnidata_tools/torch/dataloader) reads:
`OUT/<cue>/<component>/<space>/point_<p>_view_<v>_domain_<cue>.<ext>` (per-point files copied per view, since
that loader parses every name as point_<p>_view_<v>_domain_<cue>), and the split CSVs its component class
opens (`OUT/component_datasets/<component>/train_val_test_*.csv`, id,train,val,test by space). That loader
reads them only from its own package folder: the command's `--loader-dir CHECKOUT` installs them there
(services.datasets.public_loader), or prints the one command that remains.

SOURCE is a job's output folder, s3://bucket/prefix of a job root, or a service job's id (its root `jobs/<id>`
in OMNIDATA_STORAGE_URL), read through its manifest. The output is
built in a temporary sibling folder and renamed into place at the end, so a failed export leaves nothing.
"""

from __future__ import annotations

import io
import json
import sys
import tarfile
from collections.abc import Iterator
from pathlib import Path

from services.core.domain.cues import CATALOG
from services.core.domain.errors import Invalid
from services.core.domain.json_types import JSONObject
from services.core.domain.keys import JOB_JSON_KEY
from services.core.storage import ObjectStore
from services.datasets.public_loader import LoaderComponent, split_rel_paths
from services.datasets.source import (
    ViewRecord,
    index_root,
    job_document,
    read_file,
    select_cues,
)
from services.datasets.splits import split_csv_text

FORMATS = ("webdataset", "omnidata")


def sample_key(record: ViewRecord, flat: bool = False) -> str:
    """WebDataset key of a view: `<space>/point_<p>_view_<v>` (flat: '__' instead of '/')."""
    return record.key.replace("/", "__") if flat else record.key


def omnidata_path(cue: str, component: str, record: ViewRecord) -> str:
    """Path of a cue file of a view in the public loader's tree (every cue named per view)."""
    return (f"{cue}/{component}/{record.space}/"
            f"point_{record.point}_view_{record.view}_domain_{cue}.{CATALOG[cue].ext}")


def _tar_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    # fixed metadata: identical input, identical shards
    info.size, info.mtime, info.mode = len(data), 0, 0o644
    tar.addfile(info, io.BytesIO(data))


class Exporter:
    """Reads a dataset root's views and files (sha256-checked on request) and writes one of the formats."""

    def __init__(self, store: ObjectStore, cues: list[str] | None, *, verify: bool, progress: bool):
        self.store = store
        self.verify = verify
        self.progress = progress
        self.job = job_document(store)
        self.records = index_root(store)
        if not self.records:
            raise Invalid(f"{store} lists no views")
        self.cues = select_cues(self.records, cues)

    def read(self, record: ViewRecord, cue: str) -> bytes:
        return read_file(self.store, record.files[cue], verify=self.verify)

    def _views(self, what: str) -> Iterator[ViewRecord]:
        if not self.progress:
            yield from self.records
            return
        from tqdm import tqdm

        yield from tqdm(self.records, desc=what, unit="view", file=sys.stderr, dynamic_ncols=True)

    def sample_json(self, record: ViewRecord) -> JSONObject:
        doc: JSONObject = {"space": record.space, "component": record.component, "point": record.point,
                               "view": record.view}
        if "point_info" in record.files:
            doc["point_info"] = json.loads(self.read(record, "point_info"))
        return doc

    def webdataset(self, out: Path, *, shard_size: int, flat_keys: bool) -> list[Path]:
        """Write the shards; returns their paths."""
        shards: list[Path] = []
        tar: tarfile.TarFile | None = None
        for i, record in enumerate(self._views("webdataset")):
            if i % shard_size == 0:
                if tar is not None:
                    tar.close()
                shards.append(out / f"shard-{len(shards):06d}.tar")
                tar = tarfile.open(shards[-1], "w", format=tarfile.USTAR_FORMAT)
            assert tar is not None
            key = sample_key(record, flat_keys)
            for cue in self.cues:
                if cue in record.files:
                    _tar_member(tar, f"{key}.{cue}.{CATALOG[cue].ext}", self.read(record, cue))
            _tar_member(tar, f"{key}.json", json.dumps(self.sample_json(record), sort_keys=True).encode())
        if tar is not None:
            tar.close()
        return shards

    def omnidata(self, out: Path, *, comp: LoaderComponent, splits: dict[str, str]) -> int:
        """Write the public loader's tree and split CSVs; returns the number of files written."""
        n = 0
        for record in self._views("omnidata"):
            for cue in self.cues:
                if cue in record.files:
                    target = out / omnidata_path(cue, comp.name, record)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(self.read(record, cue))
                    n += 1
        for rel in split_rel_paths(comp):  # the same split under every name the class opens
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            (out / rel).write_text(split_csv_text(splits))
        if self.job is not None:
            (out / JOB_JSON_KEY).write_text(json.dumps(self.job, indent=2))
        return n
