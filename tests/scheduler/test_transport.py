"""CeleryTransport against real Redis: every message is `render.cue(task_id)` on the cue's queue."""

from __future__ import annotations

import base64
import json

import pytest
import redis

from services.core.celery_config import TASK_RENDER_CUE, queue_for_cue
from services.core.settings import get_settings
from services.scheduler.transport import CeleryTransport


def _messages_on(redis_url: str, queue: str) -> list[dict]:
    """The Celery messages waiting in a Redis queue (kombu's Redis transport keeps each queue as a list)."""
    client = redis.Redis.from_url(redis_url)
    try:
        return [json.loads(raw) for raw in client.lrange(queue, 0, -1)]
    finally:
        client.close()


def test_both_send_paths_put_render_cue_messages_on_the_right_queues(redis_url):
    """The fast path and plain app.send_task enqueue the same thing: render.cue(task_id) on the cue's queue.

    Real workers consuming these messages are tested end to end (tests/e2e, tests/worker/test_celery_worker.py).
    """
    settings = get_settings(broker_url=redis_url)
    fast = [(i, "passes" if i % 4 == 0 else "rgb") for i in range(1, 61)]
    plain = [(i, "passes" if i % 3 == 0 else "vanishing_points") for i in range(100, 130)]
    for batch, is_fast in ((fast, True), (plain, False)):
        transport = CeleryTransport(settings=settings, fast=is_fast)
        try:
            transport.send(batch)
        finally:
            transport.close()
    got = []
    for queue in (settings.queue_render, settings.queue_derive):
        for msg in _messages_on(redis_url, queue):
            assert msg["headers"]["task"] == TASK_RENDER_CUE
            assert msg["properties"]["delivery_info"]["routing_key"] == queue
            args, kwargs, _embed = json.loads(base64.b64decode(msg["body"]))
            assert kwargs == {} and len(args) == 1
            got.append((args[0], queue))
    assert sorted(got) == sorted((i, queue_for_cue(c, settings)) for i, c in fast + plain)
    assert {q for _, q in got} == {"render", "derive"}


def test_broker_down_raises(redis_url):
    transport = CeleryTransport("redis://127.0.0.1:1/0", settings=get_settings())
    transport.app.conf.broker_connection_max_retries = 0
    transport.app.conf.broker_transport_options = {"max_retries": 0}
    with pytest.raises(Exception):  # noqa: B017  (kombu raises OperationalError / ConnectionError)
        transport.send([(1, "rgb")])
