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
