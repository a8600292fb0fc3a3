"""The embedded scheduler loop's tick rate: bounded by a share of one core, never slower than TICK_MAX_S."""

from __future__ import annotations

import pytest

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


class _FakeQueues:
    def __init__(self) -> None:
        self.size = 0
        self.split = False  # renderers of their own

    def waiting(self) -> int:
        return self.size


class _FakePool:
    """A pool whose workers report on a script: drain(timeout) returns the messages due by then."""

    def __init__(self, messages: list[float], kind: str | tuple = "outcome",
                 exits_at: float | None = None) -> None:
        import time

        self.t0 = time.monotonic()
        self.due = sorted(messages)  # seconds after start
        self.kind = kind
        self.exits_at = exits_at  # a worker process found gone from then on (once)
        self.queues = _FakeQueues()
        self.procs = [object()]

    def drain(self, timeout: float) -> list[tuple[object, ...]]:
        import time

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.due and time.monotonic() - self.t0 >= self.due[0]:
                self.due.pop(0)
                return [self.kind if isinstance(self.kind, tuple) else (self.kind,)]
            time.sleep(0.005)
        return []

    def replace_dead(self) -> list[str]:
        import time

        if self.exits_at is not None and time.monotonic() - self.t0 >= self.exits_at:
            self.exits_at = None
            return ["w"]
        return []


class _FakeScheduler:
    def __init__(self, job_id: int, done_at: float, t0: float) -> None:
        self.job_id, self.done_at, self.t0 = job_id, done_at, t0
        self.ticks: list[tuple[float, bool]] = []

    def tick(self, *, plan: bool = True):  # type: ignore[no-untyped-def]
        import time

        from services.scheduler.loop import TickResult

        self.ticks.append((time.monotonic() - self.t0, plan))
        return TickResult(planned=[self.job_id] if len(self.ticks) == 1 else [])


def _run_fake(
    tmp_path, messages: list[float], done_at: float,
    queued: int = 0,  # type: ignore[no-untyped-def]
    split: bool = False,
    **pool_kw,
):
    import time

    from services.core.db.engine import make_engine, make_sessionmaker
    from services.core.db.models import Job, JobState
    from services.embedded.job import run_until_final

    url = f"sqlite:///{tmp_path / 'state.db'}"
    from services.core.db.engine import migrate

    migrate(url)
    sessions = make_sessionmaker(make_engine(url))
    pool = _FakePool(messages, **pool_kw)
    pool.queues.size = queued
    pool.queues.split = split
    sched = _FakeScheduler(0, done_at, pool.t0)
    with sessions() as s:
        job = Job(owner="local", name="j", spec={}, state=JobState.RUNNING, output_root="")
        s.add(job)
        s.commit()
        job_id = job.id
    sched.job_id = job_id
    real_tick = sched.tick

    def tick(*, plan: bool = True):  # type: ignore[no-untyped-def]
        res = real_tick(plan=plan)
        if time.monotonic() - pool.t0 >= done_at:
            with sessions() as s:
                j = s.get(Job, job_id)
                assert j is not None
                j.state = JobState.DONE
                s.commit()
        return res

    sched.tick = tick  # type: ignore[method-assign]
    state, _ = run_until_final(sessions, sched, pool, job_id)  # type: ignore[arg-type]
    return state, sched.ticks, time.monotonic() - pool.t0


def test_a_quiet_run_ticks_once_a_second_and_skips_planning_once_planned(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, _ = _run_fake(tmp_path, messages=[], done_at=2.5)
    assert state == "done"
    assert [plan for _, plan in ticks] == [True] + [False] * (len(ticks) - 1)  # the job runs: planned
    gaps = [b - a for (a, _), (b, _) in zip(ticks, ticks[1:], strict=False)]
    # a dead worker is seen within ~1 s
    assert 3 <= len(ticks) <= 5 and all(g <= TICK_MAX_S + 0.3 for g in gaps)


def test_a_message_with_a_short_queue_brings_a_prompt_tick(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, took = _run_fake(tmp_path, messages=[0.3], done_at=0.3)
    assert state == "done"
    assert took < 0.3 + 0.5  # finished as soon as the last outcome came, not at the next quiet tick


def test_messages_with_a_full_queue_wait_for_the_quiet_tick(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, _ = _run_fake(tmp_path, messages=[0.2, 0.25, 0.3, 0.35, 0.4, 0.45], done_at=1.5, queued=50)
    assert state == "done"
    assert len(ticks) <= 4  # ~ once a second, not once per outcome


def test_a_recycling_worker_is_replaced_promptly_even_with_a_full_queue(tmp_path) -> None:  # type: ignore[no-untyped-def]
    state, ticks, _ = _run_fake(
        tmp_path, messages=[0.2], done_at=1.9, queued=50, kind="recycle", exits_at=0.35
    )
    assert state == "done"
    # ticks at pace after the message until the worker is replaced
    assert any(0.3 <= t <= 0.7 for t, _ in ticks)


def test_a_view_handed_off_brings_a_tick_even_with_a_full_queue(tmp_path) -> None:  # type: ignore[no-untyped-def]
    # a renderer's `passes` done: its view's derived tasks are queued by the next tick, or the derivers idle
    handed = ("outcome", 1, 7, "done", "passes", None, None)
    state, ticks, _ = _run_fake(tmp_path, messages=[0.2], done_at=1.9, queued=50, kind=handed, split=True)
    assert state == "done"
    assert any(0.15 <= t <= 0.6 for t, _ in ticks)
    state, ticks, _ = _run_fake(tmp_path / "whole", messages=[0.2], done_at=1.9, queued=50, kind=handed)
    assert not any(0.15 <= t <= 0.6 for t, _ in ticks)  # every worker renders: its own view, no tick needed
