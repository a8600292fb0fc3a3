"""Run times of compacted tasks as histogram rows (`compacted_duration`), so /metrics keeps counting them.

The metrics histogram of task durations reads done task rows; compaction (services.scheduler.compaction)
deletes those rows, so it adds their durations here, by (job, cue, bucket), in the same transaction, and an
expanded view takes them back out.
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Iterable

from sqlalchemy import text
from sqlalchemy.orm import Session

# upper bounds (s) of the histogram's buckets; bucket len(DURATION_BUCKETS_S) is +Inf
DURATION_BUCKETS_S = (0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0)

_ADD_SQL = text(
    "INSERT INTO compacted_duration (job_id, cue, bucket, n, sum_s) VALUES (:job_id, :cue, "
    ":bucket, :n, :sum_s) "
    "ON CONFLICT (job_id, cue, bucket) DO UPDATE SET n = compacted_duration.n + excluded.n, "
    "sum_s = compacted_duration.sum_s + excluded.sum_s"
)


def bucket_of(duration_s: float) -> int:
    """Index of the first bucket whose upper bound is >= duration_s (Prometheus' `le`)."""
    return bisect.bisect_left(DURATION_BUCKETS_S, duration_s)


def add_durations(
    session: Session, job_id: int, durations: Iterable[tuple[str, float | None]], sign: int = 1
) -> None:
    """Add (sign=1) or take out (sign=-1) the (cue, duration) pairs of tasks to the job's histogram rows."""
    n: Counter[tuple[str, int]] = Counter()
    total: dict[tuple[str, int], float] = {}
    for cue, d in durations:
        if d is None:
            continue
        key = (cue, bucket_of(d))
        n[key] += 1
        total[key] = total.get(key, 0.0) + d
    rows = [{"job_id": job_id, "cue": cue, "bucket": b, "n": sign * k, "sum_s": sign * total[(cue, b)]}
            for (cue, b), k in sorted(n.items())]
    if rows:
        session.execute(_ADD_SQL, rows)
