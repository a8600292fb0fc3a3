"""CeleryTransport against real Redis and a real Celery worker: every message runs `render.cue(task_id)`."""

from __future__ import annotations

import threading
import time

import pytest
from celery.contrib.testing.worker import start_worker

from services.core.celery_config import TASK_RENDER_CUE, make_celery_app, queue_for_cue
from services.core.settings import get_settings
from services.scheduler.transport import CeleryTransport


def test_a_real_worker_runs_every_message_by_name(redis_url):
    """Both send paths (the fast one and plain app.send_task) reach a real worker as render.cue(task_id).

    One worker for both: Celery's in-process test worker is started once per test process.
    """
    settings = get_settings(broker_url=redis_url)
    worker_app = make_celery_app(settings, main="test-worker")  # knows the task; the scheduler's app does not
    got: list[tuple[int, str]] = []
    lock = threading.Lock()

    @worker_app.task(name=TASK_RENDER_CUE, bind=True)
    def render_cue(self, task_id: int) -> None:
        with lock:
            got.append((task_id, self.request.delivery_info["routing_key"]))

    fast = [(i, "passes" if i % 4 == 0 else "rgb") for i in range(1, 61)]
    plain = [(i, "passes" if i % 3 == 0 else "vanishing_points") for i in range(100, 130)]
    with start_worker(worker_app, pool="solo", perform_ping_check=False, shutdown_timeout=10,
                      queues=[settings.queue_render, settings.queue_derive]):
        for batch, is_fast in ((fast, True), (plain, False)):
            transport = CeleryTransport(settings=settings, fast=is_fast)
            try:
                transport.send(batch)
            finally:
                transport.close()
        deadline = time.monotonic() + 30
        while len(got) < len(fast) + len(plain) and time.monotonic() < deadline:
            time.sleep(0.05)
    assert sorted(got) == sorted((i, queue_for_cue(c, settings)) for i, c in fast + plain)
    assert {q for _, q in got} == {"render", "derive"}


def test_broker_down_raises(redis_url):
    transport = CeleryTransport("redis://127.0.0.1:1/0", settings=get_settings())
    transport.app.conf.broker_connection_max_retries = 0
    transport.app.conf.broker_transport_options = {"max_retries": 0}
    with pytest.raises(Exception):  # noqa: B017  (kombu raises OperationalError / ConnectionError)
        transport.send([(1, "rgb")])
