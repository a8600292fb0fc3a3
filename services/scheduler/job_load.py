"""A running job's load as dispatch and fairness see it: its priority, tenant and task counts by cue and
state."""

from __future__ import annotations

from dataclasses import dataclass, field

from services.core.db.models import TaskState

INFLIGHT = (TaskState.QUEUED, TaskState.RUNNING)


@dataclass
class JobLoad:
    """A running job's dispatch inputs, from its counters: priority and task counts by cue and state."""

    job_id: int
    priority: int
    counts: dict[str, dict[str, int]] = field(default_factory=dict)
    owner: str = ""  # the tenant: dispatch is shared fairly between tenants

    def n(self, cue: str, *states: str) -> int:
        """Tasks of `cue` in any of `states`."""
        per = self.counts.get(cue, {})
        return sum(per.get(s, 0) for s in states)

    @property
    def pending(self) -> int:
        """Pending tasks of the job."""
        return sum(per.get(TaskState.PENDING, 0) for per in self.counts.values())

    @property
    def inflight(self) -> int:
        """Queued + running tasks of the job."""
        return sum(per.get(s, 0) for per in self.counts.values() for s in INFLIGHT)
