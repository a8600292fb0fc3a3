"""What `omnidata generate` shows: a progress bar while the job runs, and a report of what was written or
failed."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy import case, func, select
from sqlalchemy.orm import Session, sessionmaker
from tqdm import tqdm

from services.core.db.compacted import compacted_tasks
from services.core.db.counters import job_progress
from services.core.db.models import Job, JobState, Task, TaskState, View, ViewOutput
from services.core.domain.cues import CATALOG
from services.core.storage import ObjectStore

VIEWS_REFRESH_S = 2.0


class Progress:
    """A tqdm bar on stderr: labels done of the total, labels/s, ETA, and views finished."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar: tqdm | None = None
        self._views_at = 0.0
        self.views_text = ""

    def update(self, sessions: sessionmaker[Session], job: Job, *, final: bool = False) -> None:
        """Refresh from the job's counters (and, every few seconds or at the end, the number of finished
        views)."""
        if not self.enabled:
            return
        with sessions() as s:
            prog = job_progress(s, job.id)
            now = time.monotonic()
            if final or now - self._views_at > VIEWS_REFRESH_S:
                self._views_at = now
                done, total = views_done(s, job.id)
                self.views_text = f"views {done}/{total}"
        total = sum(n for cue, st in prog.items() if not CATALOG[cue].internal for st_name, n in st.items()
                    if st_name != TaskState.CANCELLED)
        done = sum(st.get(TaskState.DONE, 0) for cue, st in prog.items() if not CATALOG[cue].internal)
        if total == 0:
            return
        if self.bar is None:
            self.bar = tqdm(total=total, initial=done, unit="label", file=sys.stderr, dynamic_ncols=True,
                            mininterval=0.5, desc="generate")
        self.bar.total = total
        # a job held for its store says why on the bar ("storage full: ..."), until it resumes on its own
        held = job.state == JobState.PAUSED and job.paused_by is not None and job.error
        waiting = f" | waiting: {job.error.split(';')[0]}" if held and job.error else ""
        self.bar.set_postfix_str(self.views_text + waiting, refresh=final or bool(waiting))
        if done > self.bar.n:
            self.bar.update(done - self.bar.n)  # redraws at most every mininterval

    def waiting(self, why: str) -> None:
        """Say on the bar what the run waits for (a full disk), until the next update."""
        if self.bar is not None:
            self.bar.set_postfix_str(f"{self.views_text} | waiting: {why}", refresh=True)

    def close(self) -> None:
        """Finish the bar."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def view_count(s: Session, job_id: int) -> int:
    """Views planned for the job."""
    return int(s.scalar(select(func.count()).select_from(View).where(View.job_id == job_id)) or 0)


def views_done(s: Session, job_id: int) -> tuple[int, int]:
    """(views whose every task is done, views planned)."""
    total = view_count(s, job_id)
    per_view = (
        select(Task.space_id, Task.point_idx, Task.view_idx)
        .where(Task.job_id == job_id)
        .group_by(Task.space_id, Task.point_idx, Task.view_idx)
        .having(func.sum(case((Task.state == TaskState.DONE, 0), else_=1)) == 0)
        .subquery()
    )
    done = int(s.scalar(select(func.count()).select_from(per_view)) or 0)
    compacted = int(
        s.scalar(select(func.count()).select_from(ViewOutput).where(ViewOutput.job_id == job_id)) or 0
    )
    return done + compacted, total


@dataclass
class Report:
    """How a run ended."""

    state: str
    outputs: int = 0
    views: int = 0
    missing: list[str] = field(default_factory=list)
    failed: dict[str, tuple[int, str]] = field(default_factory=dict)  # cue -> (count, first error)
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Every requested output exists."""
        return self.state == JobState.DONE and not self.missing and not self.failed


def build_report(sessions: sessionmaker[Session], store: ObjectStore, job_id: int) -> Report:
    """Check every requested output against the folder and collect failures (cue, count, first error)."""
    internal = [n for n, c in CATALOG.items() if c.internal]
    with sessions() as s:
        job = s.get(Job, job_id)
        assert job is not None
        rep = Report(state=job.state, error=job.error)
        rep.views = view_count(s, job_id)
        rows: list[tuple[Any, ...]] = [tuple(r) for r in s.execute(
            select(Task.cue, Task.state, Task.output_key, Task.error, Task.point_idx, Task.view_idx)
            .where(Task.job_id == job_id, Task.cue.not_in(internal)).order_by(Task.id)
        )]
        rows += [(t.cue, t.state, t.output_key, t.error, t.point_idx, t.view_idx)
                 for t in compacted_tasks(s, job) if t.cue not in internal]
        # Failed internal tasks (a render that kept failing) explain the missing outputs that depend on them.
        failed_internal = s.execute(
            select(Task.cue, Task.error)
            .where(Task.job_id == job_id, Task.state == TaskState.FAILED, Task.cue.in_(internal))
            .order_by(Task.id)
        ).all()
    for cue, state, key, error, p, v in rows:
        if state == TaskState.DONE and key and store.exists(key):
            rep.outputs += 1
            continue
        if state == TaskState.FAILED:
            n, first = rep.failed.get(cue, (0, (error or "no error recorded")))
            rep.failed[cue] = (n + 1, first)
        else:
            rep.missing.append(f"{cue} point {p} view {v} ({state})")
    for cue, error in failed_internal:
        n, first = rep.failed.get(cue, (0, error or "no error recorded"))
        rep.failed[cue] = (n + 1, first)
    return rep


def print_report(rep: Report, out: Path) -> None:
    """What was written, or what failed (cue, count, first error) on stderr."""
    if rep.ok:
        print(f"omnidata generate: {rep.outputs} files for {rep.views} views in {out} "
              "(manifest.jsonl, job.json)")
        return
    print(f"omnidata generate: job {rep.state}; {rep.outputs} outputs written to {out}", file=sys.stderr)
    if rep.error and not rep.failed:
        print(f"  {rep.error}", file=sys.stderr)
    for cue, (n, first) in sorted(rep.failed.items()):
        print(f"  {cue}: {n} failed; first error: {first.splitlines()[0] if first else ''}", file=sys.stderr)
    if rep.missing:
        shown = ", ".join(rep.missing[:5]) + (
            f" and {len(rep.missing) - 5} more" if len(rep.missing) > 5 else ""
        )
        print(f"  {len(rep.missing)} outputs missing: {shown}", file=sys.stderr)
