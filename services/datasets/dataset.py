"""`OmnidataDataset`: a job's output (local folder or S3) as a map-style dataset of decoded arrays in metric
units.

Works with torch's DataLoader and its default collate without importing torch: items are dicts of numpy arrays
(channels first), Python ints and strings. Units and encodings are in services/datasets/decode.py.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import cast

import numpy as np

from services.core.domain.cues import validate_cue_names
from services.core.settings import Settings
from services.core.storage import ObjectStore
from services.datasets.decode import cue_params, decode_cue
from services.datasets.point_info import camera_of
from services.datasets.source import (
    ViewRecord,
    index_root,
    job_document,
    open_root,
    read_file,
    select_cues,
)
from services.datasets.splits import DEFAULT_RATIOS, SPLITS, assign_splits, read_split_csv
from services.datasets.steering_filter import keep_in_ranges

# cue name -> decoded array (JSON cues: their text); space, point, view; K and world_to_camera. Items of
# several views hold a list (text, names) or a stacked array per key.
ItemValue = np.ndarray | str | int | list[np.ndarray | str | int]
Item = dict[str, ItemValue]


class OmnidataDataset:
    """Views of a job's output as dicts of arrays: one item per view, or per anchor view and its point's
    others.

    root: output folder, file:// or s3://bucket/prefix URL of a job root (S3 is read through manifest.jsonl),
    or an open ObjectStore. cues: the cues to decode (views lacking one are left out). spaces: keep only
    these. split: 'train', 'val' or 'test', by space: from `split_csv` (Omnidata format) when given, else from
    `split_seed` and `split_ratios`. views_per_sample > 1: each item stacks that many views of the same point
    (the anchor, then the point's next views in order); points with fewer views are left out.
    verify_sha256: check every file read against its manifest checksum. where: keep the views whose steering
    values lie in these ranges, e.g. {"pitch_deg": (-10, 10), "height_m": (1.0, 1.8)}
    (services.datasets.steering_filter; names as services.core.domain.steering.DISTRIBUTIONS).
    """

    def __init__(
        self,
        root: str | Path | ObjectStore,
        cues: str | Sequence[str],
        *,
        spaces: Iterable[str] | None = None,
        split: str | None = None,
        views_per_sample: int = 1,
        split_seed: int = 0,
        split_ratios: Sequence[float] = DEFAULT_RATIOS,
        split_csv: str | Path | None = None,
        verify_sha256: bool = False,
        settings: Settings | None = None,
        where: Mapping[str, tuple[float, float]] | None = None,
    ):
        self.cues = validate_cue_names([cues] if isinstance(cues, str) else list(cues))
        if views_per_sample < 1:
            raise ValueError(f"views_per_sample must be >= 1, got {views_per_sample}")
        if split is not None and split not in SPLITS:
            raise ValueError(f"split must be one of {', '.join(SPLITS)} (or None), got {split!r}")
        self.root = root if isinstance(root, ObjectStore) else str(root)
        self.settings = settings
        self.views_per_sample = views_per_sample
        self.verify_sha256 = verify_sha256
        self._store: ObjectStore | None = None
        store = self.store
        self.job = job_document(store)
        self.params = cue_params(self.job)
        records = index_root(store)
        self.all_spaces = sorted({r.space for r in records})
        if spaces is not None:
            wanted = set(spaces)
            unknown = wanted - set(self.all_spaces)
            if unknown:
                raise ValueError(f"unknown space(s) {sorted(unknown)}; the dataset has {self.all_spaces}")
            records = [r for r in records if r.space in wanted]
        if split is not None:
            records = self._in_split(records, split, split_csv, split_seed, split_ratios)
        if where:
            records = keep_in_ranges(store, self.job, records, where)
        if records:
            select_cues(records, self.cues)  # a cue no view has is a mistake, not an empty dataset
        complete = [r for r in records if all(c in r.files for c in self.cues)]
        self.incomplete_views = len(records) - len(complete)  # views lacking a requested cue
        self.views: list[ViewRecord] = complete
        self.samples = self._samples(complete)

    def _in_split(
        self, records: list[ViewRecord], split: str, csv: str | Path | None, seed: int,
        ratios: Sequence[float],
    ) -> list[ViewRecord]:
        if csv is not None:
            members = read_split_csv(Path(csv))[split]
        else:
            members = {
                s
                for s, name in assign_splits(self.all_spaces, seed=seed, ratios=ratios).items()
                if name == split
            }
        return [r for r in records if r.space in members]

    def _samples(self, records: list[ViewRecord]) -> list[tuple[int, ...]]:
        """Indices into self.views of each item: the anchor first, then the other views of its point."""
        if self.views_per_sample == 1:
            return [(i,) for i in range(len(records))]
        by_point: dict[tuple[str, int], list[int]] = {}
        for i, r in enumerate(records):
            by_point.setdefault((r.space, r.point), []).append(i)
        out = []
        n = self.views_per_sample
        for members in by_point.values():
            if len(members) < n:
                continue
            for j in range(len(members)):
                out.append(tuple(members[(j + k) % len(members)] for k in range(n)))
        return out

    # ------------------------------------------------------------------ storage (reopened in each worker
    # process)

    @property
    def store(self) -> ObjectStore:
        if self._store is None:
            self._store = open_root(self.root, self.settings)
        return self._store

    def __getstate__(self) -> dict[str, object]:
        state = self.__dict__.copy()
        if not isinstance(self.root, ObjectStore):
            state["_store"] = None  # boto3 clients do not pickle; DataLoader workers open their own
        return state

    def read(self, record: ViewRecord, cue: str) -> bytes:
        """The bytes of one cue file of a view (sha256-checked when verify_sha256)."""
        return read_file(self.store, record.files[cue], verify=self.verify_sha256)

    # ------------------------------------------------------------------ items

    def __len__(self) -> int:
        return len(self.samples)

    def load_view(self, record: ViewRecord) -> Item:
        """One view: every requested cue decoded, plus K, world_to_camera (when it has point_info) and its
        names."""
        item: Item = {cue: decode_cue(cue, self.read(record, cue), self.params) for cue in self.cues}
        if "point_info" in record.files:
            text = (
                item["point_info"]
                if "point_info" in item
                else self.read(record, "point_info").decode("utf-8")
            )
            item["K"], item["world_to_camera"] = camera_of(json.loads(cast(str, text)))
        item.update(space=record.space, point=record.point, view=record.view)
        return item

    def __getitem__(self, index: int) -> Item:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} samples")
        views = [self.load_view(self.views[i]) for i in self.samples[index]]
        if len(views) == 1:
            return views[0]
        out: Item = {"space": views[0]["space"], "point": views[0]["point"]}
        out["view"] = np.array([v["view"] for v in views], dtype=np.int64)
        for key, value in views[0].items():
            if key in out:
                continue
            if isinstance(value, np.ndarray):
                out[key] = np.stack([cast(np.ndarray, v[key]) for v in views])
            else:
                out[key] = [cast(np.ndarray | str | int, v[key]) for v in views]
        return out

    def __repr__(self) -> str:
        return (f"OmnidataDataset({self.root!r}, cues={self.cues}, {len(self)} samples, "
                f"{len({v.space for v in self.views})} spaces)")
