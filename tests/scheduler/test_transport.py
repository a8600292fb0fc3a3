"""CeleryTransport against real Redis: every message is `render.cue(task_id)` on the cue's queue."""

from __future__ import annotations

import base64
import json

import pytest
import redis

from services.core.celery_config import TASK_RENDER_CUE, queue_for_cue
from services.core.settings import get_settings
from services.scheduler.celery_transport import CeleryTransport


def _messages_on(redis_url: str, queue: str) -> list[dict]:
    """The Celery messages waiting in a Redis queue (kombu's Redis transport keeps each queue as a list)."""
    client = redis.Redis.from_url(redis_url)
    try:
        return [json.loads(raw) for raw in client.lrange(queue, 0, -1)]
    finally:
        client.close()


def test_both_send_paths_put_render_cue_messages_on_the_right_queues(redis_url):
    """The fast path and plain app.send_task enqueue the same thing: render.cue(task_id) on the cue's queue.

    Real workers consuming these messages are tested end to end (tests/e2e,
    tests/worker/test_celery_worker.py).
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


def _normalised(msg: dict) -> dict:
    """A message with its per-send values (task id, correlation id, delivery tag, origin) blanked."""
    out = json.loads(json.dumps(msg))
    for k in ("id", "root_id", "origin"):
        out["headers"][k] = "*"
    out["properties"]["correlation_id"] = out["properties"]["delivery_tag"] = "*"
    return out


def test_prebuilt_envelope_is_the_message_kombu_stores(redis_url):
    """The Redis fast path (services.scheduler.envelope) writes exactly what Celery + kombu write for the same
    task, key for key, apart from the fresh ids; a kombu or Celery upgrade that changes the layout fails
    here."""
    settings = get_settings(broker_url=redis_url)
    for task_id, cue in ((7, "rgb"), (8, "passes")):
        for prebuilt in (True, False):  # ours, then Celery's message published by kombu
            transport = CeleryTransport(settings=settings, prebuilt=prebuilt)
            try:
                transport.send([(task_id, cue)])
            finally:
                transport.close()
        queue = queue_for_cue(cue, settings)
        plain, fast = _messages_on(redis_url, queue)  # LPUSH: the newest (kombu's) first
        assert _normalised(fast) == _normalised(plain)
        assert fast["headers"]["id"] == fast["headers"]["root_id"] == fast["properties"]["correlation_id"]
        assert fast["headers"]["id"] != plain["headers"]["id"]
        assert fast["properties"]["delivery_tag"] != fast["headers"]["id"]
        redis.Redis.from_url(redis_url).delete(queue)


def test_fast_path_keeps_the_dispatch_order_and_unique_ids(redis_url):
    """Workers pop the oldest message first (BRPOP from the tail), in the order the dispatcher sent them."""
    settings = get_settings(broker_url=redis_url)
    transport = CeleryTransport(settings=settings)
    try:
        transport.send([(i, "rgb") for i in range(1, 2501)])  # more than one LPUSH of PUBLISH_BATCH
    finally:
        transport.close()
    msgs = list(reversed(_messages_on(redis_url, settings.queue_derive)))
    assert [json.loads(base64.b64decode(m["body"]))[0][0] for m in msgs] == list(range(1, 2501))
    assert (
        len({m["headers"]["id"] for m in msgs})
        == len({m["properties"]["delivery_tag"] for m in msgs})
        == 2500
    )
