"""The embedded scheduler loop's tick rate: bounded by a share of one core, never slower than TICK_MAX_S.

The loop (services.embedded.job.run_until_final) runs against a fake pool on a fake clock that only the pool's
wait moves, so when each tick comes is computed, not timed: exact, and no test waits in real time."""

from __future__ import annotations

from unittest import mock

import pytest

from services.embedded import job as job_loop
from services.embedded.job import TICK_CPU_SHARE, TICK_MAX_S, TICK_S, tick_interval


def test_a_cheap_tick_keeps_the_fastest_rate():
    assert tick_interval(0.0) == TICK_S
    assert tick_interval(TICK_S * TICK_CPU_SHARE / 2) == TICK_S


def test_a_costly_tick_spaces_the_next_one_so_the_loop_stays_within_its_share_of_a_core():
    cpu = 0.02  # 20 ms of CPU: the next tick waits long enough that ticks take TICK_CPU_SHARE of a core
    wait = tick_interval(cpu)
    assert wait == pytest.approx(cpu / TICK_CPU_SHARE)
    assert cpu / wait <= TICK_CPU_SHARE + 1e-12


def test_however_costly_a_tick_the_job_is_still_seen_within_the_slowest_interval():
    assert tick_interval(5.0) == TICK_MAX_S


class _FakeClock:
    """The loop's clock (job_loop.time): seconds since the start, moved only by the fake pool's wait; every
    tick costs no CPU (process_time stands still), so the loop's fastest rate is TICK_S."""

    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def process_time(self) -> float:
        return 0.0


class _FakeQueues:
    def __init__(self) -> None:
        self.size = 0
        self.split = False  # renderers of their own

    def waiting(self) -> int:
        return self.size


class _FakePool:
    """A pool whose workers report on a script: drain(timeout) moves the clock to the next message due by then
    and returns it, or to the end of the wait."""

    def __init__(self, clock: _FakeClock, messages: list[float], kind: str | tuple = "outcome",
                 exits_at: float | None = None) -> None:
        self.clock = clock
        self.due = sorted(messages)  # seconds after start
        self.kind = kind
        self.exits_at = exits_at  # a worker process found gone from then on (once)
        self.queues = _FakeQueues()
        self.procs = [object()]

    def drain(self, timeout: float) -> list[tuple[object, ...]]:
        end = self.clock.now + timeout
        if self.due and self.due[0] <= end:
            self.clock.now = max(self.clock.now, self.due.pop(0))
            return [self.kind if isinstance(self.kind, tuple) else (self.kind,)]
        self.clock.now = end
        return []

    def replace_dead(self) -> list[str]:
        if self.exits_at is not None and self.clock.now >= self.exits_at:
            self.exits_at = None
            return ["w"]
        return []


class _FakeScheduler:
    def __init__(self, clock: _FakeClock, job_id: int) -> None:
        self.clock, self.job_id = clock, job_id
        self.ticks: list[tuple[float, bool]] = []

    def tick(self, *, plan: bool = True):  # type: ignore[no-untyped-def]
        from services.scheduler.loop import TickResult

        self.ticks.append((self.clock.now, plan))
        return TickResult(planned=[self.job_id] if len(self.ticks) == 1 else [])


def _run_fake(
    tmp_path, messages: list[float], done_at: float,
    queued: int = 0,  # type: ignore[no-untyped-def]
    split: bool = False,
    **pool_kw,
):
    """(final state, [(tick time, planned?)], the time the loop returned) of a job that is done from done_at
    (seen by the first tick from then), its workers reporting at `messages`."""
    from services.core.db.engine import make_engine, make_sessionmaker, migrate
    from services.core.db.models import Job, JobState

    url = f"sqlite:///{tmp_path / 'state.db'}"
    migrate(url)
    sessions = make_sessionmaker(make_engine(url))
    clock = _FakeClock()
    pool = _FakePool(clock, messages, **pool_kw)
    pool.queues.size = queued
    pool.queues.split = split
    with sessions() as s:
        job = Job(owner="local", name="j", spec={}, state=JobState.RUNNING, output_root="")
        s.add(job)
        s.commit()
        job_id = job.id
    sched = _FakeScheduler(clock, job_id)
    real_tick = sched.tick

    def tick(*, plan: bool = True):  # type: ignore[no-untyped-def]
        res = real_tick(plan=plan)
        if clock.now >= done_at:
            with sessions() as s:
                j = s.get(Job, job_id)
                assert j is not None
                j.state = JobState.DONE
                s.commit()
        return res

    sched.tick = tick  # type: ignore[method-assign]
    with mock.patch.object(job_loop, "time", clock):
        state, _ = job_loop.run_until_final(sessions, sched, pool, job_id)  # type: ignore[arg-type]
    return state, sched.ticks, clock.now


def _times(ticks: list[tuple[float, bool]]) -> list[float]:
    return [round(t, 9) for t, _ in ticks]


def test_a_quiet_run_ticks_once_a_second_and_skips_planning_once_planned(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, _ = _run_fake(tmp_path, messages=[], done_at=2.5)
    assert state == "done"
    assert [plan for _, plan in ticks] == [True] + [False] * 4  # the job runs: planned
    # the planning tick did work (busy): the next one follows at once; then, nothing reported, a tick every
    # TICK_MAX_S (a dead worker is seen within it), the last one sees the end
    assert _times(ticks) == [0.0, 0.0, TICK_MAX_S, 2 * TICK_MAX_S, 3 * TICK_MAX_S]


def test_a_message_with_a_short_queue_brings_a_prompt_tick(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, took = _run_fake(tmp_path, messages=[0.3], done_at=0.3)
    assert state == "done"
    # finished as soon as the last outcome came, not at the next quiet tick
    assert _times(ticks) == [0.0, 0.0, 0.3] and took == pytest.approx(0.3)


def test_messages_with_a_full_queue_wait_for_the_quiet_tick(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, _ = _run_fake(tmp_path, messages=[0.2, 0.25, 0.3, 0.35, 0.4, 0.45], done_at=1.5, queued=50)
    assert state == "done"
    assert _times(ticks) == [0.0, 0.0, TICK_MAX_S, 2 * TICK_MAX_S]  # once a second, not once per outcome


def test_a_recycling_worker_is_replaced_promptly_even_with_a_full_queue(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, _ = _run_fake(
        tmp_path, messages=[0.2], done_at=1.9, queued=50, kind="recycle", exits_at=0.35
    )
    assert state == "done"
    # at pace (TICK_S) from the message until the tick that finds the worker gone (0.4) and one more, then
    # quiet
    assert _times(ticks) == pytest.approx([0.0, 0.0, 0.2, 0.2 + TICK_S, 0.2 + 2 * TICK_S, 0.2 + 3 * TICK_S,
                                           0.2 + 3 * TICK_S + TICK_MAX_S, 0.2 + 3 * TICK_S + 2 * TICK_MAX_S])


def test_a_view_handed_off_brings_a_tick_even_with_a_full_queue(tmp_path) -> None:  # type: ignore[no-untyped-def]
    # a renderer's `passes` done: its view's derived tasks are queued by the next tick, or the derivers idle
    handed = ("outcome", 1, 7, "done", "passes", None, None)
    state, ticks, _ = _run_fake(tmp_path, messages=[0.2], done_at=1.9, queued=50, kind=handed, split=True)
    assert state == "done"
    assert 0.2 in _times(ticks)
    state, ticks, _ = _run_fake(tmp_path / "whole", messages=[0.2], done_at=1.9, queued=50, kind=handed)
    assert _times(ticks) == [0.0, 0.0, TICK_MAX_S, 2 * TICK_MAX_S]  # every worker renders: no tick needed
