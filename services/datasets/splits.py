"""Train/val/test splits by space, deterministic, and the Omnidata split CSV (`id,train,val,test`).

A space's split depends only on its name, the seed and the ratios (a hash mapped to [0, 1)), so it never
changes when other spaces are added to or removed from a dataset, and every run and machine agrees.
"""

from __future__ import annotations

import csv
import hashlib
import io
from collections.abc import Iterable
from pathlib import Path

SPLITS = ("train", "val", "test")
DEFAULT_RATIOS = (0.8, 0.1, 0.1)


def check_ratios(ratios: Iterable[float]) -> tuple[float, float, float]:
    """Three non-negative fractions (train, val, test) summing to 1."""
    r = tuple(float(x) for x in ratios)
    if len(r) != 3 or min(r) < 0 or abs(sum(r) - 1.0) > 1e-6:
        raise ValueError(
            f"split ratios must be three non-negative fractions (train, val, test) summing to 1, got {r}"
        )
    return r  # type: ignore[return-value]


def _unit(space: str, seed: int) -> float:
    """A uniform number in [0, 1) fixed by the space name and seed."""
    digest = hashlib.sha256(f"{seed}:{space}".encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2**64


def split_of(space: str, *, seed: int = 0, ratios: Iterable[float] = DEFAULT_RATIOS) -> str:
    """'train', 'val' or 'test' for one space."""
    r = check_ratios(ratios)
    u = _unit(space, seed)
    if u < r[0]:
        return "train"
    return "val" if u < r[0] + r[1] else "test"


def assign_splits(
    spaces: Iterable[str], *, seed: int = 0, ratios: Iterable[float] = DEFAULT_RATIOS
) -> dict[str, str]:
    """Split name per space."""
    r = check_ratios(ratios)
    return {s: split_of(s, seed=seed, ratios=r) for s in spaces}


def read_split_csv(path_or_text: str | Path) -> dict[str, set[str]]:
    """Spaces per split from an Omnidata split CSV (header `id,train,val,test`, 1 = member; a space may be in
    several)."""
    text = Path(path_or_text).read_text() if isinstance(path_or_text, Path) else path_or_text
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or [c.strip() for c in rows[0]] != ["id", *SPLITS]:
        raise ValueError("split CSV must start with the header 'id,train,val,test'")
    out: dict[str, set[str]] = {s: set() for s in SPLITS}
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != 4:
            raise ValueError(f"split CSV line {n}: expected 4 columns (id,train,val,test), got {len(row)}")
        for split, flag in zip(SPLITS, row[1:], strict=True):
            if flag.strip() == "1":
                out[split].add(row[0].strip())
    return out


def split_csv_text(assignment: dict[str, str]) -> str:
    """The Omnidata split CSV of a space -> split assignment (rows sorted by space)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", *SPLITS])
    for space in sorted(assignment):
        w.writerow([space, *(int(assignment[space] == s) for s in SPLITS)])
    return buf.getvalue()
